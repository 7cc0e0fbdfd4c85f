"""Stopping a training run cleanly on Ctrl-C or SIGTERM."""

from __future__ import annotations

import signal


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
