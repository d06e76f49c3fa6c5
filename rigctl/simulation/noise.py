"""The simulators' slow noise: white noise through a one-pole low-pass (an Ornstein-Uhlenbeck process), in floats.

Used by the dataset renderer (:mod:`rigctl.simulation.dataset`: the stepper's speed wobble, the force loop's residual)
and the simulated operator (:mod:`rigctl.simulation.operator`). They ran ``scipy.signal.lfilter([b], [1, -a], x)``;
importing scipy.signal costs ~0.65-1 CPU-s in every process that renders, for a recurrence of two roundings a step.
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["one_pole"]


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
    on Python floats with :func:`itertools.accumulate`.
    """
    bx = b * np.asarray(x, dtype=np.float64)
    return np.fromiter(itertools.accumulate(bx.tolist(), lambda y, v: v + a * y), np.float64, bx.size)
