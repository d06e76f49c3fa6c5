"""The host's side of the simavr harnesses' clock-lock file (``arduino/simavr/rigctl_simavr.c``, "clock lock"): the
boards' simulated times (slot 0 the Mega's, slot 1 the Uno's) and the host's grant (slot 2), each ns + 1 (0: not
yet), shared memory between the harness processes and the host (docs/architecture.md "Time on a simulated rig").

:class:`HilClockFile` gives a :class:`rigctl.core.shared_clock.SharedClock` the world's time (the slower board's:
the two run in lock step within 2 ms) and publishes its grants; the harnesses run no further than the grant.
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path

import numpy as np

from rigctl.core.shared_clock import SharedClock

__all__ = ["HilClockFile", "LOCK_SLOTS"]

#: the file's slots: the Mega's time, the Uno's, the host's grant (uint64 each)
LOCK_SLOTS = 3


class HilClockFile:
    """The clock-lock file at ``path`` (created, zeroed: no board has published, no grant yet), mapped."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.ftruncate(fd, LOCK_SLOTS * 8)
            self._map: mmap.mmap | None = mmap.mmap(fd, LOCK_SLOTS * 8)
        finally:
            os.close(fd)
        # aligned 8-byte loads and stores (one instruction each on the machines simavr runs on), as the harness's atomics
        self._slots: np.ndarray | None = np.frombuffer(self._map, dtype=np.uint64)
        self._last_s = 0.0

    def shared_clock(self) -> SharedClock:
        """A :class:`SharedClock` on the boards' time whose grants go to the file (its first one written now)."""
        clock = SharedClock(self.world_now, on_grant=self.grant)
        self.grant(clock.horizon_s)
        return clock

    def world_now(self) -> float:
        """The simulated rig's time, s: the slower board's that has published (0 before either has); never moves
        back (a board that starts publishing later, behind the other, is caught up by the lock)."""
        slots = self._slots
        if slots is None:
            return self._last_s
        mega, uno = int(slots[0]), int(slots[1])
        started = [v for v in (mega, uno) if v]
        if started:
            t = (min(started) - 1) * 1e-9
            if t > self._last_s:
                self._last_s = t
        return self._last_s

    def grant(self, horizon_s: float) -> None:
        """Let the boards run to ``horizon_s`` of simulated time (s)."""
        slots = self._slots
        if slots is not None:
            slots[2] = np.uint64(int(horizon_s * 1e9) + 1)

    def board_times_s(self) -> tuple[float | None, float | None]:
        """The Mega's and the Uno's published times, s (None: not yet)."""
        slots = self._slots
        if slots is None:
            return None, None
        return tuple((int(v) - 1) * 1e-9 if v else None for v in slots[:2])  # type: ignore[return-value]

    def close(self) -> None:
        """Unmap the file (the harnesses keep their own mappings)."""
        self._slots = None
        if self._map is not None:
            try:
                self._map.close()
            except BufferError:  # an array view still alive somewhere: left to the garbage collector
                pass
            self._map = None
