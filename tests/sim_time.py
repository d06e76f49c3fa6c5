"""Waiting for a simulated world to run on, judged against a bound on a hang rather than a speed (shared by the
simulation and firmware tests)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wall_to_run_on(now: Callable[[], float], sim_s: float, within_s: float) -> float | None:
    """The wall time (s) a world whose simulated time is ``now()`` (s) takes to run ``sim_s`` s on; None if it does not
    within ``within_s`` s of wall time."""
    t0, w0 = now(), time.monotonic()
    while time.monotonic() - w0 < within_s:
        if now() - t0 > sim_s:
            return time.monotonic() - w0
        time.sleep(0.01)
    return None
