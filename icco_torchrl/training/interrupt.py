"""Stopping a training run cleanly on Ctrl-C or SIGTERM."""

from __future__ import annotations

import signal
from contextlib import contextmanager


class GracefulInterrupt:
    """The first Ctrl-C (SIGINT) or SIGTERM (what Slurm, ``timeout``, docker and submitit send
    before a kill) asks the loop to stop after the current batch and save a checkpoint; a second
    one raises at once.

    Stopping between batches, not inside the collector or an update, keeps every object in a
    state that can be checkpointed.
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
