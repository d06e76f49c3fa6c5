"""The simulators' slow noise: white noise through a one-pole low-pass (an Ornstein-Uhlenbeck process), in floats.

Used by the dataset renderer (:mod:`rigctl.simulation.dataset`: the stepper's speed wobble, the force loop's residual)
and the simulated operator (:mod:`rigctl.simulation.operator`). They ran ``scipy.signal.lfilter([b], [1, -a], x)``;
importing scipy.signal costs ~0.65-1 CPU-s in every process that renders, for a recurrence of two roundings a step.
The recurrence runs in a numba kernel (the renderer's own kernels are numba's already): ~3 us for a 3,000-sample
trace where Python floats through :func:`itertools.accumulate` took ~0.45 ms (two traces a trial: a quarter of a
rendered trial's time), the same two roundings a step in the same order, so bit for bit the same numbers.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["one_pole"]


@numba.njit(cache=True, nogil=True)
def _recurrence(bx: np.ndarray, a: float, out: np.ndarray) -> None:  # pragma: no cover - compiled
    # no fastmath: a fused multiply-add would round once where lfilter rounds twice
    y = 0.0
    for k in range(bx.shape[0]):
        y = bx[k] + a * y
        out[k] = y


def one_pole(b: float, a: float, x: np.ndarray) -> np.ndarray:
    """``y[k] = b x[k] + a y[k-1]`` from rest (``y[-1] = 0``), as ``scipy.signal.lfilter([b], [1, -a], x)``.

    Parameters
    ----------
    b, a : the filter's gain and pole (``0 <= a < 1`` for a low-pass).
    x : ``(n,)`` float64 input, finite (white noise).

    Returns
    -------
    ``(n,)`` float64: bit for bit lfilter's for finite ``x`` (its direct form II transposed does the same two
    roundings a step, ``b x[k] + (0 x[k-1] - (-a) y[k-1])``; only the sign of an exact zero could differ), computed
    by a compiled loop (:func:`_recurrence`) over ``b x`` (computed by numpy, as before).
    """
    bx = b * np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
    out = np.empty_like(bx)
    _recurrence(bx, float(a), out)
    return out
