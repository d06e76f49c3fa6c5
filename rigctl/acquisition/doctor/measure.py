"""The doctor's measurements as plain functions of recorded arrays (no rig): a force step response, the taxels'
noise floor, their crosstalk, a clock error in ppm.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["StepResponse", "step_response", "noise_floor", "crosstalk", "clock_error_ppm", "row_correlations"]


@dataclasses.dataclass(frozen=True)
class StepResponse:
    """A force step response measured from a trace (see :func:`step_response`).

    Attributes
    ----------
    contact_s : time of first contact (force above 10 % of the setpoint) after the step command, s; NaN if none
    overshoot_pct : highest force above the setpoint after contact, % of the setpoint (0 when it never exceeds it)
    settling_time_s : from contact until the force stays within the tolerance to the end of the trace, s; NaN if it
        does not settle
    residual_pp_g : peak-to-peak force over the trace's last ``tail_s`` seconds, g
    stiffness_g_per_mm : slope of force over actuator travel between 20 % and 80 % of the setpoint, g/mm (NaN with
        too few points)
    """

    contact_s: float
    overshoot_pct: float
    settling_time_s: float
    residual_pp_g: float
    stiffness_g_per_mm: float

    @property
    def settled(self) -> bool:
        return not math.isnan(self.settling_time_s)


def step_response(t_s: np.ndarray, force_g: np.ndarray, actuator_mm: np.ndarray, setpoint_g: float,
                  tolerance_g: float, *, tail_s: float = 1.0, settled_for_s: float = 0.5) -> StepResponse:
    """Overshoot, settling time, residual oscillation and contact stiffness of a force step.

    Parameters
    ----------
    t_s : (n,) seconds since the step command (PRESS), increasing
    force_g : (n,) measured force, g
    actuator_mm : (n,) actuator travel from home, mm
    setpoint_g : the step's target, g (> 0)
    tolerance_g : the settle band, g (the controller's FORCE_TOLERANCE_G, docs/wire-protocol.md 2.1)
    tail_s : window at the end of the trace for the residual peak-to-peak, s
    settled_for_s : the force must have stayed in the band at least this long at the end of the trace to count as
        settled, s
    """
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(force_g, dtype=float)
    x = np.asarray(actuator_mm, dtype=float)
    nan = math.nan
    touch = np.flatnonzero(f > 0.1 * setpoint_g)
    if len(t) == 0 or len(touch) == 0:
        return StepResponse(nan, nan, nan, nan, nan)
    i0 = int(touch[0])
    contact = float(t[i0])
    after = f[i0:]
    overshoot = max(0.0, float(after.max()) - setpoint_g) / setpoint_g * 100.0
    outside = np.flatnonzero(np.abs(after - setpoint_g) > tolerance_g)
    if len(outside) == 0:
        settling = 0.0
    else:
        last = i0 + int(outside[-1])
        if last + 1 >= len(t) or t[-1] - t[last + 1] < settled_for_s:
            settling = nan
        else:
            settling = float(t[last + 1]) - contact
    tail = f[t >= t[-1] - tail_s]
    residual = float(tail.max() - tail.min()) if len(tail) else nan
    rise = np.flatnonzero((f >= 0.2 * setpoint_g) & (f <= 0.8 * setpoint_g))
    rise = rise[rise <= (i0 + int(np.argmax(after)))]
    stiffness = nan
    if len(rise) >= 3 and np.ptp(x[rise]) > 0:
        stiffness = float(np.polyfit(x[rise], f[rise], 1)[0])
    return StepResponse(contact, overshoot, settling, residual, stiffness)


def noise_floor(samples: np.ndarray) -> np.ndarray:
    """Per-taxel standard deviation of readings at rest, ADC counts: ``(n, channels) -> (channels,)``."""
    s = np.asarray(samples, dtype=float)
    if s.ndim != 2 or len(s) < 2:
        raise ValueError("noise_floor needs (n >= 2, channels) samples")
    return s.std(axis=0, ddof=1)


def crosstalk(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much two taxels share, sample by sample: the correlation of their sample-to-sample changes, less the
    median over all pairs (what every taxel shares: supply and ground noise).

    A reading that keeps a fraction ``a`` of the previously converted channel (a multiplexer node that has not
    settled through a high source impedance, /work/shared/notes/bench-facts.md "74HC4051") is ``x_j = (1 - a) s_j +
    a x_i``; with the taxels' own noise independent and alike, the correlation of the changes is
    ``a / sqrt((1 - a)^2 + a^2)``, about ``a`` for small ``a`` (0.24 at a = 0.2). Which of the two leaks into the
    other cannot be told from noise at rest, hence a symmetric matrix. Differences remove the noise's low-pass
    correlation in time and any offset. Resolution: about ``1 / sqrt(n)`` for n samples.

    Parameters
    ----------
    samples : (n, channels) ADC counts at rest (no texture moving)

    Returns
    -------
    (coupling, noise) : coupling (channels, channels), symmetric, diagonal 0 (NaN for a taxel whose change has no
        variance); noise (channels,) the sd of each taxel's change, counts
    """
    s = np.asarray(samples, dtype=float)
    d = np.diff(s, axis=0)
    d -= d.mean(axis=0)
    sd = np.sqrt((d * d).mean(axis=0))
    cov = d.T @ d / len(d)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    corr[sd == 0, :] = np.nan
    corr[:, sd == 0] = np.nan
    np.fill_diagonal(corr, np.nan)
    base = np.nanmedian(corr) if np.isfinite(corr).any() else 0.0
    coupling = corr - base
    np.fill_diagonal(coupling, 0.0)
    return coupling, sd


def clock_error_ppm(measured_hz: float, nominal_hz: float) -> float:
    """``(measured / nominal - 1) * 1e6``: a device's clock error against the host clock, ppm."""
    return (measured_hz / nominal_hz - 1.0) * 1e6


def row_correlations(front: np.ndarray, back: np.ndarray, lag: float, spread: float = 0.2) -> tuple[float, float]:
    """How well ``back`` (a taxel row's readings, (n,) or (n, k) for k columns) repeats ``front`` (the row ahead of it
    along the drum's travel) ``lag`` samples later, and how well ``lag`` samples earlier: the largest normalised
    correlation (-1..1) over lags within ``spread`` of +``lag`` and of -``lag``. A drum turning forwards brings the
    texture to the front row first (the first is high), one turning backwards to the back row (the second). Only
    the two windows are searched: a periodic texture correlates again one period away. ValueError for fewer than
    ``3 * lag`` samples or arrays of different shapes."""
    a = np.asarray(front, dtype=np.float64).reshape(len(front), -1)
    b = np.asarray(back, dtype=np.float64).reshape(len(back), -1)
    n, hi = a.shape[0], int(math.ceil(lag * (1.0 + spread)))
    if n < 3 * lag or b.shape != a.shape or lag < 1:
        raise ValueError(f"row_correlations needs two (n, k) arrays of the same shape, n >= 3 x lag ({lag:g}); got "
                         f"{a.shape}, {b.shape}")
    a, b = a - a.mean(axis=0), b - b.mean(axis=0)

    def corr(k: int) -> float:
        x, y = (a[: n - k], b[k:]) if k >= 0 else (a[-k:], b[: n + k])
        den = math.sqrt(float((x * x).sum()) * float((y * y).sum()))
        return float((x * y).sum()) / den if den > 0 else 0.0

    lo = int(math.floor(lag * (1.0 - spread)))
    return max(corr(k) for k in range(lo, hi + 1)), max(corr(-k) for k in range(lo, hi + 1))
