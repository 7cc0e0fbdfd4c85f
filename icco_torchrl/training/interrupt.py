"""Stopping a training run cleanly on Ctrl-C or SIGTERM."""

from __future__ import annotations

import signal
from contextlib import contextmanager


class UpdateAbandoned(KeyboardInterrupt):
    """A stop cut short a block marked :func:`abandonable` (the compile of an update)."""


_abandonable = 0  # how many abandonable blocks the main thread is in


@contextmanager
def abandonable():
    """A block that a :class:`GracefulInterrupt` stop may cut short, raising
    :class:`UpdateAbandoned` in it at once: one that changes nothing a checkpoint holds, such as
    the forward and backward of an update before its optimiser step, where ``train.compile``
    compiles for a minute or more (Docker waits 10 s after SIGTERM, Slurm 30 s)."""
    global _abandonable
    _abandonable += 1
    try:
        yield
    finally:
        _abandonable -= 1


class GracefulInterrupt:
    """The first Ctrl-C (SIGINT) or SIGTERM (what Slurm, ``timeout``, docker and submitit send
    before a kill) asks the loop to stop after the current batch and save a checkpoint; a second
    one raises at once.

    Stopping between batches, not inside the collector or an update, keeps every object in a
    state that can be checkpointed; only an :func:`abandonable` block (an update's compile) is
    cut short by the first one.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested, self.signal_name = False, None
        self._previous = {}
        try:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread: keep Python's default behaviour
            self._previous = {}

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested, self.signal_name = True, signal.Signals(signum).name
        if _abandonable:
            raise UpdateAbandoned

    def restore(self) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous = {}


class Interrupted(Exception):
    """A Ctrl-C or SIGTERM outside the training loop (:class:`StopAtOnce`)."""

    def __init__(self, signal_name: str):
        super().__init__(signal_name)
        self.signal_name = signal_name


class StopAtOnce:
    """Outside the collector loop (building, the reference evaluation, the final evaluation, the
    learning curve) there is no batch to finish: the first Ctrl-C or SIGTERM raises
    :class:`Interrupted` at once, except inside :meth:`held` (a checkpoint and the record of what
    was written), which it lets finish first; a second one raises even there (the writes are
    atomic). While the loop runs, its :class:`GracefulInterrupt` handles the signals, and hands
    them back after."""

    SIGNALS = GracefulInterrupt.SIGNALS

    def __init__(self):
        self.signal_name: str | None = None
        self._holding = 0
        self._previous = {}

    def __enter__(self) -> StopAtOnce:
        try:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread: keep Python's default behaviour
            self._previous = {}
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous = {}

    def _handle(self, signum, frame):
        again, self.signal_name = self.signal_name is not None, signal.Signals(signum).name
        if again or not self._holding:
            raise Interrupted(self.signal_name)

    @contextmanager
    def held(self):
        """A block a signal does not cut (it is raised as soon as the block ends)."""
        self._holding += 1
        try:
            yield
        finally:
            self._holding -= 1
        if self.signal_name is not None and not self._holding:
            raise Interrupted(self.signal_name)
