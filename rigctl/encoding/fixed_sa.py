"""The integer (fixed-point) SA kernel: the on-board encoder's arithmetic (``rigctl/arduino/common/sa_encoder.c``
built with ``-DSA_FIXED``), integer for integer on the host, so the board and the host's real-time path agree by
construction (issue 37, part 7; docs/firmware.md, "The integer kernel").

The model is the paper's tonic-spiking Izhikevich SA neuron (eqs. 3-4; a = 0.02, b = 0.2, c = -65, d = 6, k = 100,
two 0.5 ms half-steps of v per 1 ms sample, u from the new v), rescaled so that the only products left are a square
and constants: y = v / 50, z = u / 100, J = I / 100 (with k = 100, J is the normalised reading), all Q24 in int32:

    w  = 1.4 + J - z0
    y1 = y0^2 + 3.5 y0 + w,     y2 = y1^2 + 3.5 y1 + w
    z1 = z0 - 0.02 z0 + 0.002 y2
    y2 >= 0.6 (v >= 30 mV): spike, y <- -1.3, z <- z1 + 0.06

with the C file's exact integer operations (floor shifts, 16 x 16 -> 32 bit partial products, the clamps that keep
every intermediate inside int32: the input to [-2, 4] of the taxel's range, y to [-8, 8) before each square).
Its spikes are those of a model with its own rounding (about 1e-7 of the float kernels' values per step), so they
are not the float kernels' spike for spike: the model is chaotic in its rounding (docs/firmware.md gives the
agreement and the classification).
"""

from __future__ import annotations

import numba
import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ
from rigctl.core.normalisation import TaxelRange
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["FixedSAEncoder", "K_MAX", "fixed_gains"]

#: the largest input scale k the integer kernel takes (SA_FIXED_K_MAX: keeps every intermediate inside int32)
K_MAX = 255

_Y_PEAK = 10066330  # ceil(0.6 * 2^24): v >= 30 mV
_Y_RESET = -21810381  # round(-1.3 * 2^24): c = -65 mV
_Z_REST = -2181038  # round(-0.13 * 2^24): u = b c = -13
_Z_JUMP = 1006633  # round(0.06 * 2^24): d = 6
_W_E = 23488102  # round(1.4 * 2^24): h e / 50
_Y_MAX = 134217727  # 8 * 2^24 - 1
_K_A = 1311  # round(0.02 * 2^16): a (0.0200043)
_K_AB = 33554  # round(0.002 * 2^24): a b 50 / 100


@numba.njit(inline="always", cache=True)
def _sq(y):  # pragma: no cover - compiled by numba
    h = y >> 16
    lo = y & 0xFFFF
    m = lo >> 8
    return ((h * h) << 8) + (((2 * h) * lo) >> 8) + ((m * m) >> 8)


@numba.njit(inline="always", cache=True)
def _mulc(y, c, s):  # pragma: no cover - compiled by numba
    """floor(h c / 2^s) + floor(l c / 2^(16 + s)) of y = h 2^16 + l (the C file's mulc16: s = 0, mulc24: s = 8)"""
    return (((y >> 16) * c) >> s) + (((y & 0xFFFF) * c) >> (16 + s))


@numba.njit(inline="always", cache=True)
def _clamp_y(y):  # pragma: no cover - compiled by numba
    return min(max(y, -_Y_MAX - 1), _Y_MAX)


@numba.njit(cache=True)
def _run(x, offset, gain, d_lo, d_hi, y, z, raster):  # pragma: no cover - compiled by numba
    """x (n, C) int64 ADC counts; offset, gain, d_lo, d_hi (C,) int64; y, z (C,) int64 state (updated);
    raster (n, C) uint8 out (1 = spike)."""
    n, n_ch = x.shape
    for t in range(n):
        for i in range(n_ch):
            d = min(max(x[t, i] - offset[i], d_lo[i]), d_hi[i])
            z0 = z[i]
            w = _W_E + d * gain[i] - z0
            y0 = _clamp_y(y[i])
            y1 = _clamp_y(_sq(y0) + 4 * y0 - (y0 >> 1) + w)
            y2 = _sq(y1) + 4 * y1 - (y1 >> 1) + w
            z1 = z0 - _mulc(z0, _K_A, 0) + _mulc(y2, _K_AB, 8)
            if y2 >= _Y_PEAK:
                y[i] = _Y_RESET
                z[i] = z1 + _Z_JUMP
                raster[t, i] = 1
            else:
                y[i] = y2
                z[i] = z1
                raster[t, i] = 0


def fixed_gains(taxel_min: np.ndarray, taxel_max: np.ndarray, k: float = 100.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The per-taxel constants the board computes in ``sa_init`` from the integer range: ``(offset, gain, d_lo,
    d_hi)`` int64 (C,): gain = round(k 2^24 / (100 span)) (0 when max <= min), the input clamp [-2 span, 4 span].

    Raises
    ------
    ValueError
        The range is not integer ADC counts in 0..65535, or k is not an integer in 0..:data:`K_MAX`.
    """
    lo, hi = np.asarray(taxel_min, np.float64), np.asarray(taxel_max, np.float64)
    if lo.shape != hi.shape or np.any(lo != np.round(lo)) or np.any(hi != np.round(hi)) or np.any(lo < 0) \
            or np.any(hi > 0xFFFF):
        raise ValueError("the integer kernel needs the range as integer ADC counts 0..65535")
    if k != round(k) or not 0 <= k <= K_MAX:
        raise ValueError(f"the integer kernel takes an integer k in 0..{K_MAX}, got {k!r}")
    off = lo.astype(np.int64)
    span = np.maximum(hi.astype(np.int64) - off, 0)
    gain = np.where(span > 0, (int(k) * (1 << 24) + 50 * span) // np.maximum(100 * span, 1), 0)
    return off, gain.astype(np.int64), -2 * span, 4 * span


class FixedSAEncoder:
    """The integer SA kernel fed chunk by chunk (state carried over), as :class:`rigctl.encoding.izhikevich.
    StreamingEncoder`'s SA path: :meth:`process` gives the chunk's spikes.

    Parameters
    ----------
    normalise : the per-taxel range (integer ADC counts; the board's ``sa_init`` minimum and maximum).
    k_sa : the input scale k (integer, <= :data:`K_MAX`; the paper's 100).
    fs : the readings' rate, Hz (spike times are sample / fs; the model steps once per sample: 1 kHz).

    Raises
    ------
    ValueError
        As :func:`fixed_gains`.
    """

    def __init__(self, normalise: TaxelRange, *, k_sa: float = 100.0, fs: float = MODEL_RATE_HZ) -> None:
        self.n_taxels = normalise.n_taxels
        self.fs = float(fs)
        self._off, self._gain, self._lo, self._hi = fixed_gains(normalise.taxel_min, normalise.taxel_max, k_sa)
        self.reset()

    def reset(self) -> None:
        """Neurons at rest, time 0."""
        self._y = np.full(self.n_taxels, _Y_RESET, np.int64)
        self._z = np.full(self.n_taxels, _Z_REST, np.int64)
        self.n_samples = 0

    def raster(self, chunk: np.ndarray) -> np.ndarray:
        """``(n, n_taxels)`` ADC counts -> ``(n, n_taxels)`` uint8, 1 where the taxel spiked at that sample.

        Raises
        ------
        ValueError
            The chunk is not ``(n, n_taxels)``.
        """
        x = np.asarray(chunk)
        if x.ndim != 2 or x.shape[1] != self.n_taxels:
            raise ValueError(f"chunk must be (n, {self.n_taxels}), got {x.shape}")
        out = np.zeros(x.shape, np.uint8)
        _run(np.ascontiguousarray(x, np.int64), self._off, self._gain, self._lo, self._hi, self._y, self._z, out)
        return out

    def process(self, chunk: np.ndarray) -> SpikeTrains:
        """``(n, n_taxels)`` ADC counts following the previous chunk -> their spikes, SpikeTrains (1, n_taxels),
        times in s since the scan's start."""
        r = self.raster(chunk)
        n0 = self.n_samples
        self.n_samples += r.shape[0]
        return SpikeTrains.from_lists([[(n0 + np.flatnonzero(r[:, i])) / self.fs for i in range(self.n_taxels)]])
