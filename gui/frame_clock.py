"""The app's frame clock: ticks on a fixed grid of ``1 / max_fps`` s, so the frame cap is both a ceiling and the rate
the app keeps (issue 26).

A repeating QTimer of whole milliseconds cannot do both: 33 ms is 30.3 ticks/s (over a 30/s cap), 34 ms is 29.4/s,
and on the app's busy event loop a 33 ms PreciseTimer measured 29.4 ticks/s (median interval 34.0 ms: each timeout
lost the time it was dispatched late). :class:`FramePacer` keeps the grid instead: tick ``k`` is due at ``t0 + k /
max_fps`` and the single-shot timer is armed, in whole ms rounded up, for the next due time, so a tick dispatched
late is followed by a shorter wait and the mean rate is the cap. It never runs ahead of the grid (at most ``max_fps
* T + 1`` ticks in any ``T`` s), and after a stall longer than a period the grid restarts from now instead of
catching up with a burst of frames.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from PySide6 import QtCore


class FramePacer:
    """The due times of a clock capped at ``max_fps`` ticks/s (> 0): :meth:`start` and :meth:`next_delay_ms` return
    how long (whole ms, >= 0) to wait for the next due tick; ``now`` is ``time.monotonic()`` s. Raises ValueError for
    a cap that is not a positive finite number."""

    def __init__(self, max_fps: float):
        if not (math.isfinite(max_fps) and max_fps > 0):
            raise ValueError(f"max_fps must be a positive number of frames/s, got {max_fps!r}")
        self.period_s = 1.0 / float(max_fps)
        self.due_s = math.nan

    def start(self, now: float) -> int:
        """Begin the grid at ``now``: the first tick is due one period later."""
        self.due_s = now + self.period_s
        return self._delay_ms(now)

    def next_delay_ms(self, now: float) -> int:
        """Called as a tick is dispatched at ``now``: the wait until the next tick's due time (one period after this
        tick's; one period after ``now`` if this tick came more than a period late)."""
        self.due_s += self.period_s
        if self.due_s <= now:  # a stall of more than a period: no burst of catch-up frames
            self.due_s = now + self.period_s
        return self._delay_ms(now)

    def _delay_ms(self, now: float) -> int:
        return max(0, math.ceil((self.due_s - now) * 1000.0))


class FrameClock(QtCore.QObject):
    """A single-shot precise QTimer re-armed by a :class:`FramePacer`: calls ``on_tick()`` at most ``max_fps`` times a
    second, ``max_fps`` times a second on average while the event loop keeps up. ``timer``: the QTimer (its
    ``timeout`` is each tick, dispatched just before ``on_tick``)."""

    def __init__(self, max_fps: float, on_tick: Callable[[], object], parent: QtCore.QObject | None = None):
        super().__init__(parent)
        self.pacer = FramePacer(max_fps)
        self._on_tick = on_tick
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.setSingleShot(True)
        self.timer.timeout.connect(self._fire)

    @property
    def period_s(self) -> float:
        return self.pacer.period_s

    def start(self) -> None:
        self.timer.start(self.pacer.start(time.monotonic()))

    def stop(self) -> None:
        self.timer.stop()

    def isActive(self) -> bool:  # noqa: N802 - Qt style
        return self.timer.isActive()

    def _fire(self) -> None:
        # armed before the tick's work, so an exception in it never stops the clock
        self.timer.start(self.pacer.next_delay_ms(time.monotonic()))
        self._on_tick()
