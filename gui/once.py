"""A background thread started at most once per process (the app's warm-ups: the live view's numba kernels, the
analysis jobs' fork server): the first :meth:`StartOnce.start` starts it, later calls return the same thread."""

from __future__ import annotations

import threading
from collections.abc import Callable


class StartOnce:
    """``target`` run in a daemon thread named ``name``, started by the first :meth:`start` of this process."""

    def __init__(self, target: Callable[[], None], name: str):
        self._target, self._name = target, name
        self._lock = threading.Lock()
        self.thread: threading.Thread | None = None  # None until started

    def start(self) -> threading.Thread:
        """Start the thread unless it was started already; returns it. Never waits for it."""
        with self._lock:
            if self.thread is None:
                self.thread = threading.Thread(target=self._target, name=self._name, daemon=True)
                self.thread.start()
            return self.thread


__all__ = ["StartOnce"]
