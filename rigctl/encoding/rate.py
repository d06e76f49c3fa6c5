"""The readings' sample rate and the model's time step: an explicit resampling step.

The Izhikevich neurons (eqs. 3-5, :mod:`rigctl.encoding.izhikevich`) are integrated in fixed 1 ms steps (two 0.5 ms
half-steps of ``v``, Izhikevich 2003), one step per input sample: the paper's sensor is read at 1 kHz, so one sample
is one step. Readings at another rate (a 100 Hz sensor, a 2 kHz one) are first resampled to the model's rate,
:data:`MODEL_RATE_HZ`, with a polyphase FIR filter (``scipy.signal.resample_poly``: up by ``up``, an anti-aliasing
low-pass, down by ``down``); the ends are padded by extending the line through the first and last samples
(``padtype="line"``), so a trial that starts or ends at a high reading does not ring down to zero. The model's time
step cannot simply be stretched to the sample interval instead: at 100 Hz that is a 10 ms explicit Euler step of
eq. (3), which is unstable (the ``0.04 v^2`` term overshoots) and fires spurious spikes.

At :data:`MODEL_RATE_HZ` (the paper's rig) nothing is resampled: the readings reach the kernel unchanged (``uint16``
counts, no copy), so the paper's numerics are untouched.

The encoded file records the step (``input_rate_hz``, ``model_rate_hz``, ``resampled``, ``resampling``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from rigctl.encoding.izhikevich import FS_HZ

__all__ = ["MODEL_RATE_HZ", "RateConversion", "rate_conversion"]

#: the model's step rate, Hz: one Izhikevich step per ms
MODEL_RATE_HZ: float = FS_HZ


@dataclass(frozen=True)
class RateConversion:
    """How readings at ``input_rate_hz`` become model input at ``model_rate_hz``.

    Attributes
    ----------
    input_rate_hz : the session's sample rate, Hz.
    model_rate_hz : the rate the model steps at, Hz (``input_rate_hz * up / down``).
    up, down : the polyphase factors (1, 1 when nothing is resampled).
    """

    input_rate_hz: float
    model_rate_hz: float
    up: int = 1
    down: int = 1

    @property
    def resampled(self) -> bool:
        return self.up != self.down

    def n_out(self, n_samples: int) -> int:
        """Model steps for ``n_samples`` readings: ``ceil(n_samples * up / down)`` (``resample_poly``'s length)."""
        return int(n_samples) if not self.resampled else -(-int(n_samples) * self.up // self.down)

    def apply(self, readings) -> np.ndarray:
        """``(n_samples, n_channels)`` readings -> ``(n_out(n_samples), n_channels)`` model input.

        Unchanged (same array, same dtype) when nothing is resampled; otherwise float64 (ADC counts, interpolated:
        values may slightly overshoot the recorded range near steep edges).
        """
        x = np.asarray(readings)
        if not self.resampled or x.shape[0] == 0:
            return x
        from scipy.signal import resample_poly

        if x.shape[0] == 1:
            return np.repeat(x.astype(np.float64), self.n_out(1), axis=0)
        return resample_poly(x.astype(np.float64), self.up, self.down, axis=0, padtype="line")

    def describe(self) -> str:
        """One line for logs and the encoded file's ``resampling`` attribute."""
        if not self.resampled:
            return f"none: the readings' {self.input_rate_hz:g} Hz is the model's rate (one 1 ms step per sample)"
        return (f"{self.input_rate_hz:g} Hz -> {self.model_rate_hz:g} Hz with scipy.signal.resample_poly "
                f"(up {self.up}, down {self.down}, padtype 'line') before the model's 1 ms steps")

    def to_dict(self) -> dict:
        return {"input_rate_hz": self.input_rate_hz, "model_rate_hz": self.model_rate_hz, "up": self.up,
                "down": self.down, "resampled": self.resampled}


def rate_conversion(input_rate_hz: float, model_rate_hz: float = MODEL_RATE_HZ, *,
                    max_factor: int = 1000) -> RateConversion:
    """The resampling from ``input_rate_hz`` to ``model_rate_hz`` (Hz).

    ``model / input`` is approximated by ``up / down`` with ``down <= max_factor``; when that is not exact (a rate
    such as 99.87 Hz), the model rate becomes ``input * up / down`` (within 0.1 % of the asked rate) and is what
    :attr:`RateConversion.model_rate_hz` reports.

    Raises
    ------
    ValueError
        if a rate is not positive and finite, or no ratio within 0.1 % exists.
    """
    rin, rmod = float(input_rate_hz), float(model_rate_hz)
    if not (math.isfinite(rin) and rin > 0 and math.isfinite(rmod) and rmod > 0):
        raise ValueError(f"sample rates must be positive and finite, got {input_rate_hz!r} -> {model_rate_hz!r}")
    if rin == rmod:
        return RateConversion(rin, rmod)
    ratio = Fraction(rmod / rin).limit_denominator(max_factor)
    up, down = ratio.numerator, ratio.denominator
    eff = rin * up / down
    if up < 1 or abs(eff - rmod) > 1e-3 * rmod:
        raise ValueError(f"cannot resample {rin:g} Hz to {rmod:g} Hz with factors up to {max_factor}")
    return RateConversion(rin, eff if abs(eff - rmod) > 1e-9 * rmod else rmod, up, down)
