"""Ctrl-C as a request to stop at the next scan boundary.

A Taichi kernel cannot be interrupted halfway (and a map left halfway through a scan would be
worth nothing), so while a run maps, SIGINT only notes the request; the run acts on it between
scans (`tisem.run.MappingRun`: checkpoint, then `RunInterrupted`). A second Ctrl-C stops at
once (KeyboardInterrupt), for a run that does not reach its next boundary.

    stop = StopRequest()
    with stop:                  # SIGINT noted while inside (main thread only)
        for scan in scans:
            ...
            if stop.requested:
                break
"""

from __future__ import annotations

import logging
import signal
import threading

log = logging.getLogger(__name__)

__all__ = ["StopRequest"]


class StopRequest:
    """Notes SIGINT while inside its `with` block; `requested` says whether one came."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None
        self._installed = False

    def __enter__(self) -> StopRequest:
        # signal handlers can only be set from the main thread; elsewhere Ctrl-C is not ours
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._note)
            self._installed = True
        return self

    def __exit__(self, *exc) -> bool:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False
        return False

    def _note(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("Ctrl-C: stopping after this scan (Ctrl-C again to stop at once)")
