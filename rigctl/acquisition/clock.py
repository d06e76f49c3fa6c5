"""The host <-> taxel-board clock mapping of a rig, per trial (:mod:`rigctl.core.clocksync`).

:class:`rigctl.acquisition.rig.Rig` feeds every captured frame (the Uno's sequence numbers against host receive
times) into one :class:`~rigctl.core.clocksync.DeviceClockFit` for as long as it is open (fitted online, outliers
rejected); :func:`trial_clock_attrs` turns the fit at a trial's end into the trial's attributes
(docs/session-format.md):

- ``host_time_origin_s``: the host monotonic time at which the trial's first kept frame was received (its
  ``host_time_s`` are relative to it);
- ``device_count_origin``: that frame's running count on the board (``seq`` unwrapped);
- ``fitted_time_origin_s``: the fitted host time of that frame: sample ``i``'s time on the host clock is
  ``fitted_time_origin_s + (count_i - device_count_origin) * clock_period_s`` (``count_i`` from the ``seq``
  steps), free of the link's delays and the board's clock error;
- ``clock_period_s``, ``clock_drift_ppm``, ``clock_residual_s``, ``clock_blocks``, ``clock_rejected``,
  ``clock_span_s``, ``clock_segment``: the fit (:class:`~rigctl.core.clocksync.ClockMapping`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.core.clocksync import DeviceClockFit

__all__ = ["fitted_times", "trial_clock_attrs"]


def trial_clock_attrs(fit: DeviceClockFit, counts: np.ndarray, host_time_s: np.ndarray) -> dict[str, Any]:
    """The clock attributes (module docstring) of a trial whose kept frames have running ``counts`` (from
    :meth:`DeviceClockFit.add`) and absolute host receive times ``host_time_s`` (s)."""
    m = fit.mapping()
    out: dict[str, Any] = {"host_time_origin_s": float(host_time_s[0]), "device_count_origin": int(counts[0])}
    if m is None:  # too few frames yet for a fit: the nominal rate from the first frame's receive time
        out.update(fitted_time_origin_s=float(host_time_s[0]), clock_period_s=1.0 / fit.nominal_rate_hz,
                   clock_drift_ppm=math.nan, clock_residual_s=math.nan, clock_blocks=0, clock_rejected=0,
                   clock_span_s=0.0, clock_segment=fit.segment)
        return out
    out.update(fitted_time_origin_s=float(m.host_time(counts[0])), clock_period_s=m.period_s,
               clock_drift_ppm=m.drift_ppm, clock_residual_s=m.residual_s, clock_blocks=m.n_blocks,
               clock_rejected=m.n_rejected, clock_span_s=m.span_s, clock_segment=m.segment)
    return out


def fitted_times(attrs: dict[str, Any], seq: np.ndarray) -> np.ndarray | None:
    """Every sample's fitted host time (s) from a trial's ``seq`` and its clock attributes; None for a trial
    recorded without them."""
    if "fitted_time_origin_s" not in attrs:
        return None
    s = np.asarray(seq, dtype=np.int64)
    steps = np.concatenate(([0], (np.diff(s) & 0xFFFF)))
    return float(attrs["fitted_time_origin_s"]) + np.cumsum(steps) * float(attrs["clock_period_s"])
