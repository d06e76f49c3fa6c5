"""The drum's speed marks inside one trial (docs/wire-protocol.md 2.6, docs/session-format.md trial attributes).

The drum carries :data:`rigctl.core.drum.DRUM_MARKS_PER_REV` speed marks (a slotted disc); the controller timestamps
each on its own timer (not host time) and counts the microsteps it sent between two (MARK_PERIOD_0P1MS, MARK_STEPS,
MARK_COUNT). A paper trial (240 mm) is shorter than one revolution (314 mm) but spans about six mark intervals, so
the drum's speed and slip are measured several times inside every trial. The controller itself latches DRUM_SLIP
when a mark is late by more than :data:`rigctl.core.drum.DRUM_SLIP_TOLERANCE` (a slip or a stall): the trial then
fails with that latched fault; these attributes say what the marks measured in a trial that completed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

from rigctl.core.drum import (
    DRUM_CIRCUMFERENCE_MM,
    DRUM_MARKS_PER_REV,
    DRUM_MICROSTEPS,
    DRUM_SLIP_TOLERANCE,
    DRUM_STEPS_PER_REV,
)

__all__ = ["MarkReading", "mark_intervals", "mark_attrs"]


class MarkReading(Protocol):
    """What one status read tells of the speed marks (``rigctl.core.drum.DrumStatus`` has these fields)."""

    mark_period_s: float
    mark_steps: int
    mark_count: int


def mark_intervals(statuses: Sequence[MarkReading]) -> list[tuple[float, int]]:
    """The mark intervals that began and ended between the first and the last of ``statuses`` (read in order, at
    least once per interval: the capture reads the status every 20 ms, an interval is >= 196 ms), as ``(period_s,
    steps)``, oldest first. An interval that ended at the first status's MARK_COUNT + 1 began before the first read:
    left out."""
    if not statuses:
        return []
    c0 = int(statuses[0].mark_count)
    out: dict[int, tuple[float, int]] = {}
    for st in statuses:
        k = (int(st.mark_count) - c0) % 65536
        if k >= 2 and st.mark_period_s > 0 and st.mark_steps > 0:
            out.setdefault(k, (float(st.mark_period_s), int(st.mark_steps)))
    return [out[k] for k in sorted(out)]


def mark_attrs(statuses: Sequence[MarkReading]) -> dict[str, float | int | bool]:
    """A trial's speed-mark attributes from the status reads of its capture, in order.

    Returns ``drum_mark_intervals`` (mark intervals measured inside the capture), ``drum_speed_marks_mm_s`` (the
    drum's mean surface speed over them: (pi x diameter / marks per revolution) / period; NaN when none),
    ``drum_speed_marks_min_mm_s`` (the slowest interval's, NaN when none), ``drum_slip_max`` (the largest relative
    excess of the microsteps of one interval over the nominal steps_per_rev x microsteps / marks: 0.25 for a 20 %
    slip; NaN when none) and ``drum_slip`` (True when that excess passed :data:`DRUM_SLIP_TOLERANCE`).
    """
    iv = mark_intervals(statuses)
    pitch_mm = DRUM_CIRCUMFERENCE_MM / DRUM_MARKS_PER_REV
    nominal = DRUM_STEPS_PER_REV * DRUM_MICROSTEPS / DRUM_MARKS_PER_REV
    if not iv:
        return {"drum_mark_intervals": 0, "drum_speed_marks_mm_s": math.nan, "drum_speed_marks_min_mm_s": math.nan,
                "drum_slip_max": math.nan, "drum_slip": False}
    total_s = sum(p for p, _ in iv)
    slip = max(steps / nominal - 1.0 for _, steps in iv)
    return {"drum_mark_intervals": len(iv), "drum_speed_marks_mm_s": len(iv) * pitch_mm / total_s,
            "drum_speed_marks_min_mm_s": pitch_mm / max(p for p, _ in iv), "drum_slip_max": float(slip),
            "drum_slip": bool(slip > DRUM_SLIP_TOLERANCE)}
