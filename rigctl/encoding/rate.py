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

Streams (the live view) are resampled chunk by chunk by :class:`StreamResampler`: the same low-pass FIR as
``resample_poly`` (Kaiser window, beta 5, ``2 * 10 * max(up, down) + 1`` taps), run causally with its state carried
over; its output is aligned in time with the input (the filter's delay is dropped at the start), so it lags the
stream by ``10 * max(up, down) / up`` input samples (100 ms for a 100 Hz stream) and does not equal the batch
resampling at the trial's ends (no look-ahead, no line padding at the end).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ

__all__ = ["MODEL_RATE_HZ", "RateConversion", "rate_conversion", "StreamResampler"]



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

    def to_dict(self) -> dict[str, Any]:
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
        raise ValueError(f"sample rates must be positive and finite, got {rin:g} -> {rmod:g} Hz")
    if rin == rmod:
        return RateConversion(rin, rmod)
    ratio = Fraction(rmod / rin).limit_denominator(max_factor)
    up, down = ratio.numerator, ratio.denominator
    eff = rin * up / down
    if up < 1 or abs(eff - rmod) > 1e-3 * rmod:
        raise ValueError(f"cannot resample {rin:g} Hz to {rmod:g} Hz with factors up to {max_factor}")
    return RateConversion(rin, eff if abs(eff - rmod) > 1e-9 * rmod else rmod, up, down)


class StreamResampler:
    """Chunk-by-chunk resampling of a stream to the model's rate (see the module docstring).

    ``process((n, n_channels))`` returns the model-rate samples that are complete so far, float64; over a stream
    their count approaches ``n_total * up / down`` minus the filter's delay. :meth:`reset` starts a new stream.

    Parameters
    ----------
    conv : RateConversion
        The conversion (``rate_conversion(stream_rate_hz)``).
    n_channels : int
        Channels of the stream.
    """

    def __init__(self, conv: RateConversion, n_channels: int):
        from scipy.signal import firwin

        self.conv = conv
        self.n_channels = int(n_channels)
        up, down = conv.up, conv.down
        self.half_len = 10 * max(up, down)
        self.h = firwin(2 * self.half_len + 1, 1.0 / max(up, down), window=("kaiser", 5.0)) * up
        self.reset()

    def reset(self) -> None:
        self._zi: np.ndarray | None = None
        self._n_up = 0  # upsampled samples filtered so far

    def process(self, chunk) -> np.ndarray:
        """``(n, n_channels)`` readings -> ``(m, n_channels)`` float64 model-rate samples (m may be 0)."""
        from scipy.signal import lfilter

        x = np.asarray(chunk, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_channels:
            raise ValueError(f"chunk must be (n, {self.n_channels}), got {x.shape}")
        if not self.conv.resampled:
            return x
        up, down = self.conv.up, self.conv.down
        if x.shape[0] == 0:
            return np.zeros((0, self.n_channels))
        if self._zi is None:  # a stream that was at its first reading forever: no start-up ramp from 0
            self._zi = np.zeros((self.h.size - 1, self.n_channels))
            n_prime = -(-(self.h.size - 1) // up)
            prime = np.zeros((n_prime * up, self.n_channels))
            prime[::up] = x[0]
            _, self._zi = lfilter(self.h, 1.0, prime, axis=0, zi=self._zi)
        stuffed = np.zeros((x.shape[0] * up, self.n_channels))
        stuffed[::up] = x
        y, self._zi = lfilter(self.h, 1.0, stuffed, axis=0, zi=self._zi)
        # model sample m is the filter output at upsampled index m * down + half_len (the linear-phase delay)
        g = self._n_up + np.arange(y.shape[0])
        keep = (g >= self.half_len) & ((g - self.half_len) % down == 0)
        self._n_up += y.shape[0]
        return y[keep]
