"""Spiking activity encoding: Izhikevich tonic-spiking SA and RA neurons (paper eqs. 3-5, Methods; Fig. 2D).

Model (eqs. 3-5), one neuron per taxel and encoding::

    dv/dt = 0.04 v^2 + 5 v + 140 - u + k I          (3)
    du/dt = a (b v - u)                              (4)
    if v >= 30 mV: v <- c, u <- u + d                (5)

Tonic spiking: a = 0.02, b = 0.2, c = -65, d = 6. SA: k = 100 on the normalised reading (0-1 per taxel, times the
force coefficient C of eq. 1); RA: k = 3 on the 20 Hz low-passed, differentiated reading
(:mod:`rigctl.encoding.filters`).

Integration scheme (Izhikevich 2003, the model's reference code): time in ms, one step per sample (1 ms at 1 kHz);
``v`` is advanced in two 0.5 ms Euler half-steps for numerical stability, then ``u`` one 1 ms step from the *new*
``v``; then, if ``v >= 30``, the sample is a spike: ``v <- c``, ``u <- u + d``. A spike found at sample ``n`` of a
trial gets the time ``n / fs`` seconds (trial start = 0). Initial state: ``v = c = -65`` mV, ``u = b * v``.

Two kernels. :func:`encode_sa`, :func:`encode_ra`, :func:`encode_trials` and :class:`StreamingEncoder` run the
fused kernel (:mod:`rigctl.encoding.fused`: raw counts in, normalisation, SA and the RA filter in the same pass,
float32 SA state by default, within the model's own rounding sensitivity); ``dtype=np.float64`` gives the float64
reference. :func:`run_izhikevich` / :func:`encode` are the float64 kernel on a given input current (no RA filter).
Neither allows FMA contraction or reassociation, so every lane does the same IEEE operations: batch encoding,
:class:`StreamingEncoder` and the pipeline give the same spikes, and the float64 kernels follow a plain per-sample
Python loop.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ, RA_CUTOFF_HZ
from rigctl.encoding.filters import lowpass_coefficients
from rigctl.encoding.fused import FusedResult, FusedState, on_threads, run_fused
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.rate import StreamResampler, rate_conversion
from rigctl.encoding.spikes import SpikeTrains

__all__ = [
    "IzhikevichParams",
    "TONIC_SPIKING",
    "K_SA",
    "K_RA",
    "FS_HZ",
    "Ragged",
    "as_ragged",
    "run_izhikevich",
    "encode",
    "encode_sa",
    "encode_ra",
    "encode_trials",
    "StreamingEncoder",
    "EncodedChunk",
]

K_SA = 100.0  #: eq. (3) input scaling for SA (Methods)
K_RA = 3.0  #: eq. (3) input scaling for RA (Methods)
#: the model's step rate, Hz (:data:`rigctl.encoding.rate.MODEL_RATE_HZ`, its one home): one 1 ms step per input
#: sample (other rates are resampled)
FS_HZ = MODEL_RATE_HZ


@dataclass(frozen=True)
class IzhikevichParams:
    """Free parameters of eqs. (3)-(5); defaults: tonic spiking (Izhikevich 2004; paper Methods)."""

    a: float = 0.02
    b: float = 0.2
    c: float = -65.0
    d: float = 6.0
    v_peak: float = 30.0  #: mV, spike threshold of eq. (5)


TONIC_SPIKING = IzhikevichParams()


# ---------------------------------------------------------------------------------------------------------- kernel
#: no FMA contraction or reassociation: every lane computes exactly the same IEEE operations, so batch, streaming
#: and a plain Python loop agree bit for bit, whatever lane a channel lands in.
_FASTMATH = {"nnan", "ninf", "nsz"}


#: steps buffered per block before their spikes are appended to the trains' sample-number slots
_SPK_ROWS = 64

#: trials interleaved per SIMD block: K trials x n_channels lanes (18 channels -> 144 lanes)
BLOCK_TRIALS = 8


@numba.njit(fastmath=_FASTMATH, inline="always", cache=True)
def _izh_step(vv, uu, sb, xb, g, a, b, c, d, v_peak):  # pragma: no cover
    """One 1 ms step of eqs. (3)-(5) on every lane (contiguous, SIMD): two 0.5 ms half-steps of v, then u from
    the new v, then the branch-free spike reset; ``sb`` gets 1 where a lane spiked."""
    for j in range(vv.size):
        i_in = xb[j] * g[j]
        v0 = vv[j]
        u0 = uu[j]
        v1 = v0 + 0.5 * (0.04 * v0 * v0 + 5.0 * v0 + 140.0 - u0 + i_in)
        v2 = v1 + 0.5 * (0.04 * v1 * v1 + 5.0 * v1 + 140.0 - u0 + i_in)
        u1 = u0 + a * (b * v2 - u0)
        s = v2 >= v_peak
        vv[j] = c if s else v2
        uu[j] = u1 + d if s else u1
        sb[j] = s


def _izh_kernel_py(x, starts, order, offset, gain, v, u, counts, raster, spk, block,  # pragma: no cover
                   a, b, c, d, v_peak):
    """Run eqs. (3)-(5) over trials.

    x (N, C) input rows; starts (T+1,) row starts of trials; order (M,) the trials to run (sorted by length, so
    a block's trials end together); offset (C,); gain (T, C) = k * scale * coeff; v, u (T, C) float64 state
    (in/out); counts (T, C) int64 (added to); raster (N, C) uint8 or (0, C) to skip; spk (T * C, cap) int32 or
    (0, 1) to skip: the sample numbers (from the trial start) of each train's first ``cap - 1`` spikes, written
    directly, branch-free (row ``t * C + ch``; ``counts`` says how many, ``>= cap`` = overflow; the last slot is
    scratch); block = trials per SIMD
    block. Blocks of ``block`` trials run in parallel (on threads: :func:`_run`); inside a block, time is the outer loop and the
    ``block * C`` lanes (trial-major, channel-minor) are the contiguous SIMD axis.
    """
    n_ch = x.shape[1]
    n_run = order.shape[0]
    n_blocks = (n_run + block - 1) // block
    write = raster.shape[0] > 0
    write_spk = spk.shape[0] > 0
    cap = spk.shape[1]
    for bi in range(n_blocks):
        i0 = bi * block
        m = min(n_run, i0 + block) - i0
        n_lanes = m * n_ch
        vv = np.empty(n_lanes)
        uu = np.empty(n_lanes)
        g = np.empty(n_lanes)
        xb = np.empty(n_lanes)
        sb = np.zeros(n_lanes, dtype=np.uint8)
        cnt = np.zeros(n_lanes, dtype=np.int64)
        rb = np.empty((_SPK_ROWS if write_spk else 0, n_lanes), dtype=np.uint8)  # the last steps' spikes
        n_max = 0
        for k in range(m):
            t = order[i0 + k]
            n_max = max(n_max, starts[t + 1] - starts[t])
            for ch in range(n_ch):
                vv[k * n_ch + ch] = v[t, ch]
                uu[k * n_ch + ch] = u[t, ch]
                g[k * n_ch + ch] = gain[t, ch]
        for n in range(n_max):
            for k in range(m):
                t = order[i0 + k]
                row = starts[t] + n
                if row < starts[t + 1]:
                    for ch in range(n_ch):
                        xb[k * n_ch + ch] = x[row, ch] - offset[ch]
                else:  # trial over: keep the lanes running on 0 input, their output is not used
                    for ch in range(n_ch):
                        xb[k * n_ch + ch] = 0.0
            _izh_step(vv, uu, sb, xb, g, a, b, c, d, v_peak)
            if write_spk:  # buffer _SPK_ROWS steps (L1-resident), then append them train by train, branch-free
                nb = n % _SPK_ROWS
                for j in range(n_lanes):
                    rb[nb, j] = sb[j]
                if nb == _SPK_ROWS - 1 or n == n_max - 1:
                    base = n - nb
                    for k in range(m):
                        t = order[i0 + k]
                        lim = min(nb + 1, starts[t + 1] - starts[t] - base)
                        for ch in range(n_ch):
                            j = k * n_ch + ch
                            r = t * n_ch + ch
                            cj = cnt[j]
                            for i in range(lim):
                                spk[r, min(cj, cap - 1)] = base + i
                                cj += rb[i, j]
                            cnt[j] = cj
            for k in range(m):
                t = order[i0 + k]
                row = starts[t] + n
                if row < starts[t + 1]:
                    if not write_spk:
                        for ch in range(n_ch):
                            cnt[k * n_ch + ch] += sb[k * n_ch + ch]
                    if write:
                        for ch in range(n_ch):
                            raster[row, ch] = sb[k * n_ch + ch]
                    if row == starts[t + 1] - 1:  # last sample: this is the trial's final state
                        for ch in range(n_ch):
                            v[t, ch] = vv[k * n_ch + ch]
                            u[t, ch] = uu[k * n_ch + ch]
        for k in range(m):
            t = order[i0 + k]
            for ch in range(n_ch):
                counts[t, ch] += cnt[k * n_ch + ch]


#: one serial build (no ``parallel=True`` build: ~3x the compile time); more than a block of trials runs on threads
#: (:func:`rigctl.encoding.fused.on_threads`: the next block on each, the kernel releases the GIL)
_izh_kernel = numba.njit(fastmath=_FASTMATH, cache=True, nogil=True)(_izh_kernel_py)


def _raster_to_times_py(raster, starts, index_start, n0, dt, out):  # pragma: no cover
    """Fill flat spike times trial-major, channel-major from a (N, C) raster; index_start (T, C) row starts;
    n0 (T,) int64 sample number of each trial's first row (0 in batch, the samples already seen when streaming)."""
    n_trials = starts.shape[0] - 1
    n_ch = raster.shape[1]
    for t in range(n_trials):
        pos = index_start[t].copy()
        s0 = starts[t]
        for n in range(s0, starts[t + 1]):
            rn = raster[n]
            for ch in range(n_ch):
                if rn[ch]:
                    out[pos[ch]] = (n - s0 + n0[t]) * dt
                    pos[ch] += 1


_raster_to_times = numba.njit(cache=True, nogil=True)(_raster_to_times_py)


# ---------------------------------------------------------------------------------------------------------- input
@dataclass(frozen=True)
class Ragged:
    """Trials of different lengths stored flat: ``data[starts[t]:starts[t+1]]`` is trial ``t``.

    data : (n_total_samples, n_channels), any real dtype (C-contiguous); starts : (n_trials + 1,) int64.
    """

    data: np.ndarray
    starts: np.ndarray

    @property
    def n_trials(self) -> int:
        return self.starts.size - 1

    @property
    def n_channels(self) -> int:
        return self.data.shape[1]

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.starts)

    def trial(self, t: int) -> np.ndarray:
        return self.data[self.starts[t] : self.starts[t + 1]]

    def map_trials(self, fn) -> "Ragged":
        """Apply ``fn((n, C)) -> (n, C)`` trial by trial (e.g. the RA filter, which must restart per trial)."""
        out = [fn(self.trial(t)) for t in range(self.n_trials)]
        data = np.concatenate(out, axis=0) if out else np.zeros((0, self.n_channels))
        return Ragged(np.ascontiguousarray(data), self.starts)

    def select(self, trials) -> "Ragged":
        trials = np.arange(self.n_trials)[trials]
        if not trials.size:
            return Ragged(self.data[:0], np.zeros(1, np.int64))
        return as_ragged([self.trial(t) for t in trials])


def as_ragged(readings) -> Ragged:
    """``(n_trials, n_samples, n_channels)`` array, ``(n_samples, n_channels)`` (one trial), a list of
    ``(n_i, n_channels)`` arrays, or a :class:`Ragged` -> :class:`Ragged` (no copy for C-contiguous 3-D input).

    Raises
    ------
    ValueError
        on other shapes or mismatched channel counts.
    """
    if isinstance(readings, Ragged):
        return readings
    if isinstance(readings, np.ndarray):
        if readings.ndim == 2:
            readings = readings[None]
        if readings.ndim != 3:
            raise ValueError(f"readings must be (n_trials, n_samples, n_channels), got {readings.shape}")
        t, s, c = readings.shape
        data = np.ascontiguousarray(readings).reshape(t * s, c)
        return Ragged(data, np.arange(t + 1, dtype=np.int64) * s)
    trials = [np.asarray(r) for r in readings]
    if not trials:
        raise ValueError("no trials")
    if any(r.ndim != 2 or r.shape[1] != trials[0].shape[1] for r in trials):
        raise ValueError("every trial must be (n_samples, n_channels) with the same n_channels")
    starts = np.zeros(len(trials) + 1, dtype=np.int64)
    np.cumsum([r.shape[0] for r in trials], out=starts[1:])
    return Ragged(np.ascontiguousarray(np.concatenate(trials, axis=0)), starts)


def _kernel_dtype(x: np.ndarray) -> np.ndarray:
    if x.dtype in (np.float32, np.float64, np.uint16, np.int16, np.int32):
        return np.ascontiguousarray(x)
    return np.ascontiguousarray(x, dtype=np.float64)


# ---------------------------------------------------------------------------------------------------------- batch
def run_izhikevich(readings, *, k: float, gain=1.0, offset=0.0, scale=1.0, params: IzhikevichParams = TONIC_SPIKING,
                   state=None, active=None, want_raster: bool = True,
                   block: int = BLOCK_TRIALS):
    """Run eqs. (3)-(5) on every channel of every trial: the low-level entry point.

    Parameters
    ----------
    readings : :class:`Ragged` or anything :func:`as_ragged` takes; ``(n_trials, n_samples, n_channels)``.
    k : eq. (3) input scale (100 SA, 3 RA).
    gain : scalar, (n_channels,) or (n_trials, n_channels) extra input scale (the force coefficient C of eq. 1).
    offset, scale : scalar or (n_channels,) affine normalisation applied first: ``I = (x - offset) * scale``.
    state : optional ``(v, u)`` (n_trials, n_channels) float64 arrays, updated in place (streaming).
    active : optional (n_trials,) bool; inactive trials are skipped (their counts are 0).
    want_raster : also return the (n_total_samples, n_channels) uint8 spike raster.
    block : trials interleaved per SIMD block (default 8: 144 lanes for 18 taxels).

    Returns
    -------
    counts : (n_trials, n_channels) int64 spikes per train.
    raster : (n_total_samples, n_channels) uint8 (1 = spike at that sample) or None.
    state : (v, u) after the last sample.
    """
    counts, raster, state, _ = _run(readings, k=k, gain=gain, offset=offset, scale=scale, params=params, state=state,
                                    active=active, want_raster=want_raster, spike_cap=0, block=block)
    return counts, raster, state


def _run(readings, *, k, gain, offset, scale, params, state, active, want_raster, spike_cap, block=BLOCK_TRIALS):
    """:func:`run_izhikevich`, plus (``spike_cap > 0``) the (n_trials * n_channels, spike_cap) int32 sample numbers
    of each train's first ``spike_cap - 1`` spikes, written by the kernel (a train with more spikes overflows: its
    ``counts`` is ``>= spike_cap``). Returns ``counts, raster, state, spk``."""
    rg = as_ragged(readings)
    x = _kernel_dtype(rg.data)
    n_trials, n_ch = rg.n_trials, rg.n_channels
    offset = np.ascontiguousarray(np.broadcast_to(np.asarray(offset, np.float64), (n_ch,)))
    scale = np.broadcast_to(np.asarray(scale, np.float64), (n_ch,))
    g = np.asarray(gain, dtype=np.float64)
    if g.ndim == 1 and g.size == n_ch:
        g = g[None, :]
    g = np.ascontiguousarray(np.broadcast_to(g, (n_trials, n_ch)) * (float(k) * scale)[None, :])
    if state is None:
        v = np.full((n_trials, n_ch), params.c, dtype=np.float64)
        u = params.b * v
    else:
        v, u = state
        if v.shape != (n_trials, n_ch) or u.shape != (n_trials, n_ch):
            raise ValueError(f"state must be two ({n_trials}, {n_ch}) arrays")
    act = np.ones(n_trials, dtype=np.bool_) if active is None else np.asarray(active, dtype=np.bool_)
    lengths = rg.lengths
    order = np.flatnonzero(act & (lengths > 0))
    order = order[np.argsort(lengths[order], kind="stable")]
    counts = np.zeros((n_trials, n_ch), dtype=np.int64)
    raster = np.zeros((x.shape[0] if want_raster else 0, n_ch), dtype=np.uint8)
    spk = np.empty((n_trials * n_ch, spike_cap) if spike_cap > 0 else (0, 1), dtype=np.int32)
    on_threads(lambda i, j: _izh_kernel(x, rg.starts, order[i:j], offset, g, v, u, counts, raster, spk, int(block),
                                         params.a, params.b, params.c, params.d, params.v_peak),
                order.size, int(block))  # whole blocks: no two calls write the same trial
    return counts, (raster if want_raster else None), (v, u), spk


def _times_from_spk_py(spk, index_start, counts, n0, dt, out):  # pragma: no cover
    """Flat spike times from the kernel's per-train sample numbers: row r = t * C + ch of ``spk`` holds
    ``counts[t, ch]`` sample numbers; time = (sample + n0[t]) * dt, written from ``index_start[t, ch]``."""
    n_trials, n_ch = counts.shape
    for t in range(n_trials):
        for ch in range(n_ch):
            r = t * n_ch + ch
            p0 = index_start[t, ch]
            for i in range(counts[t, ch]):
                out[p0 + i] = (np.int64(spk[r, i]) + n0[t]) * dt


_times_from_spk = numba.njit(cache=True, nogil=True)(_times_from_spk_py)


def _spike_cap(n_max: int) -> int:
    """Spike slots per train: exact (one spike per sample at most) for short trials, else a 250 Hz bound at 1 kHz
    (tonic spiking at k = 100 on a reading of 1.0 fires at ~250 Hz; more spikes fall back to the raster path).
    The int32 slots are allocated uninitialised, so only the pages actually written are touched."""
    return n_max + 1 if n_max <= 1024 else n_max // 4 + 16


def _encode_trains(rg: Ragged, *, k, gain=1.0, offset=0.0, scale=1.0, fs=FS_HZ, params=TONIC_SPIKING, state=None,
                   n0=0) -> SpikeTrains:
    """Run the kernel and build the NWB-style trains directly from the spike sample numbers it writes (no raster).
    ``state`` is updated in place as in :func:`run_izhikevich`; ``n0`` is added to every sample number."""
    n_trials = rg.n_trials
    n_max = int(rg.lengths.max()) if n_trials else 0
    cap = _spike_cap(n_max)
    saved = None if state is None else (state[0].copy(), state[1].copy())
    counts, _, _, spk = _run(rg, k=k, gain=gain, offset=offset, scale=scale, params=params, state=state,
                             active=None, want_raster=False, spike_cap=cap)
    if counts.size and int(counts.max()) >= cap:  # a train overflowed its slots: redo it with the raster
        if saved is not None:
            state[0][...], state[1][...] = saved
        counts, raster, _, _ = _run(rg, k=k, gain=gain, offset=offset, scale=scale, params=params, state=state,
                                    active=None, want_raster=True, spike_cap=0)
        return _trains_from_raster(raster, rg.starts, counts, fs, n0)
    flat = counts.ravel()
    index = np.cumsum(flat, dtype=np.int64)
    index_start = (index - flat).reshape(counts.shape)
    out = np.empty(int(index[-1]) if index.size else 0, dtype=np.float64)
    n0 = np.broadcast_to(np.asarray(n0, np.int64), (n_trials,)).copy()
    n_ch = counts.shape[1]
    on_threads(lambda i, j: _times_from_spk(spk[i * n_ch:j * n_ch], index_start[i:j], counts[i:j], n0[i:j], 1.0 / fs,
                                             out), n_trials, BLOCK_TRIALS)  # (out: written at index_start)
    return SpikeTrains(out, index, counts.shape[1])


def _trains_from_raster(raster, starts, counts, fs, n0=0) -> SpikeTrains:
    n_trials = starts.size - 1
    index = np.cumsum(counts.ravel(), dtype=np.int64)
    index_start = (index - counts.ravel()).reshape(counts.shape)
    out = np.empty(int(index[-1]) if index.size else 0, dtype=np.float64)
    n0 = np.broadcast_to(np.asarray(n0, np.int64), (n_trials,)).copy()
    index_start = np.ascontiguousarray(index_start)
    on_threads(lambda i, j: _raster_to_times(raster, starts[i:j + 1], index_start[i:j], n0[i:j], 1.0 / fs, out),
                n_trials, BLOCK_TRIALS)  # (rows and out: at starts and index_start)
    return SpikeTrains(out, index, counts.shape[1])


def encode(readings, *, k: float, gain=1.0, offset=0.0, scale=1.0, fs: float = FS_HZ,
           params: IzhikevichParams = TONIC_SPIKING) -> SpikeTrains:
    """Encode input currents into spike trains with eqs. (3)-(5) (no filtering): see :func:`run_izhikevich`.

    ``fs`` is the readings' rate, Hz: at another rate than the model's 1 kHz (1 ms steps) each trial is resampled
    to 1 kHz first (:mod:`rigctl.encoding.rate`, ``scipy.signal.resample_poly``).

    Returns
    -------
    SpikeTrains of shape (n_trials, n_channels), spike times in seconds from each trial's first sample.
    """
    rg, fs = _at_model_rate(as_ragged(readings), fs)
    return _encode_trains(rg, k=k, gain=gain, offset=offset, scale=scale, fs=fs, params=params)


def _at_model_rate(rg: Ragged, fs: float, model_fs: float = FS_HZ) -> tuple[Ragged, float]:
    """Trials at ``fs`` Hz -> trials at the model's rate ``model_fs`` and that rate (no copy when equal). Raises
    ValueError as :func:`rigctl.encoding.rate.rate_conversion`."""
    conv = rate_conversion(fs, model_fs)
    if not conv.resampled or not rg.n_trials:
        return rg, conv.model_rate_hz
    return as_ragged([conv.apply(rg.trial(t)) for t in range(rg.n_trials)]), conv.model_rate_hz


def _norm_args(normalise: TaxelRange | None):
    if normalise is None:
        return 0.0, 1.0
    return normalise.offset_scale()


def _fused(rg: Ragged, *, normalise: TaxelRange | None, sa_coeffs: tuple[Any, ...], k_sa: float, ra: bool, k_ra: float,
           cutoff_hz: float, rectify: bool, fs: float, params: IzhikevichParams, dtype,
           state: FusedState | None = None, n0: int = 0) -> FusedResult:
    offset, scale = _norm_args(normalise)
    return run_fused(rg.data, rg.starts, offset=offset, scale=scale, sa_gains=sa_coeffs, k_sa=k_sa, ra=ra, k_ra=k_ra,
                     cutoff_hz=cutoff_hz, rectify=rectify, fs=fs,
                     izhikevich=(params.a, params.b, params.c, params.d, params.v_peak), dtype=dtype, state=state,
                     n0=n0)


def encode_sa(readings, k: float = K_SA, coeff=1.0, *, normalise: TaxelRange | None = None, fs: float = FS_HZ,
              params: IzhikevichParams = TONIC_SPIKING, dtype=np.float32) -> SpikeTrains:
    """SA encoding (Methods): tonic spiking, k = 100, on the (force-scaled) normalised reading.

    Runs the fused kernel (:mod:`rigctl.encoding.fused`: normalisation in the kernel, float32 state by default).

    Parameters
    ----------
    readings : (n_trials, n_samples, n_taxels) normalised 0-1 float readings, a list of ragged
        (n_i, n_taxels) trials, or a :class:`Ragged`. With ``normalise`` given, raw readings (ADC counts).
    k : eq. (3) scale, default 100.
    coeff : force-invariance coefficient C (eq. 1): scalar, (n_taxels,) or (n_trials, n_taxels).
    normalise : per-taxel min/max of the whole dataset; applied in the kernel.
    fs : the readings' rate, Hz; the model steps in 1 ms, so readings at another rate are resampled to 1 kHz first
        (:mod:`rigctl.encoding.rate`); spike times are in s of the recording either way.
    dtype : the kernel's state, np.float32 (default) or np.float64.

    Returns
    -------
    SpikeTrains (n_trials, n_taxels), spike times in s.
    """
    rg, fs = _at_model_rate(as_ragged(readings), fs)
    return _fused(rg, normalise=normalise, sa_coeffs=(coeff,), k_sa=k, ra=False, k_ra=K_RA, cutoff_hz=RA_CUTOFF_HZ,
                  rectify=True, fs=fs, params=params, dtype=dtype).sa[0]


def encode_ra(readings, k: float = K_RA, cutoff_hz: float = RA_CUTOFF_HZ, *, normalise: TaxelRange | None = None,
              rectify: bool = True, fs: float = FS_HZ, params: IzhikevichParams = TONIC_SPIKING,
              dtype=np.float32) -> SpikeTrains:
    """RA encoding (Methods): tonic spiking, k = 3, on the 20 Hz low-passed, differentiated reading.

    The filter and derivative (units: normalised reading per second; rectified) are described in
    :mod:`rigctl.encoding.filters`; they restart at every trial, initialised to its first sample. The fused kernel
    (:mod:`rigctl.encoding.fused`) runs them sample by sample beside the neuron (no filtered copy of the trial).

    Parameters
    ----------
    readings : as :func:`encode_sa`.
    k : eq. (3) scale, default 3. cutoff_hz : low-pass cutoff (20 Hz).
    fs : the readings' rate, Hz (resampled to the model's 1 kHz first when different; the filter runs at 1 kHz).
    dtype : the kernel's state, np.float32 (default) or np.float64.

    Returns
    -------
    SpikeTrains (n_trials, n_taxels), spike times in s.
    """
    rg, fs = _at_model_rate(as_ragged(readings), fs)
    res = _fused(rg, normalise=normalise, sa_coeffs=(), k_sa=K_SA, ra=True, k_ra=k, cutoff_hz=cutoff_hz,
                 rectify=rectify, fs=fs, params=params, dtype=dtype)
    assert res.ra is not None
    return res.ra


def encode_trials(readings, *, normalise: TaxelRange | None = None, coeff=1.0, fs: float = FS_HZ,
                  rectify: bool = True, params: IzhikevichParams = TONIC_SPIKING, dtype=np.float32) -> SpikeTrains:
    """SA and RA trains side by side: (n_trials, 2 * n_taxels), SA taxels first, then RA (the paper's 36 trains);
    one pass of the fused kernel."""
    rg, fs = _at_model_rate(as_ragged(readings), fs)
    res = _fused(rg, normalise=normalise, sa_coeffs=(coeff,), k_sa=K_SA, ra=True, k_ra=K_RA, cutoff_hz=RA_CUTOFF_HZ,
                 rectify=rectify, fs=fs, params=params, dtype=dtype)
    assert res.ra is not None
    return SpikeTrains.hstack([res.sa[0], res.ra])


# ---------------------------------------------------------------------------------------------------------- streaming
@dataclass(frozen=True)
class EncodedChunk:
    """Spikes of one streamed chunk: ``sa`` and ``ra`` are SpikeTrains of shape (1, n_taxels) with times in s
    since the stream (trial) start (``ra`` None from an SA-only encoder, ``StreamingEncoder(ra=False)``);
    ``n_samples`` the chunk length (readings fed in)."""

    sa: SpikeTrains
    ra: SpikeTrains | None
    n_samples: int

    def events(self, which: str = "sa") -> tuple[np.ndarray, np.ndarray]:
        """``(times_s, taxel)`` flat arrays of one population, for raster plots."""
        st = self.sa if which == "sa" else self.ra
        if st is None:
            raise ValueError("this chunk has no RA spikes (an SA-only encoder)")
        return st.spike_times, st.row_ids()


class StreamingEncoder:
    """Stateful SA + RA encoder fed chunk by chunk (the GUI's live rasters); identical spikes to batch encoding.

    Feeding a trial in any chunking gives exactly the spike times of :func:`encode_sa` / :func:`encode_ra` on the
    whole trial: the neuron state (v, u), the RA low-pass state and the last filtered value carry over.

    A stream at another rate than the model's 1 kHz (``fs``) is resampled chunk by chunk
    (:class:`rigctl.encoding.rate.StreamResampler`): spike times stay in s of the stream, but come ``10 * max(up,
    down) / up`` input samples late (100 ms for a 100 Hz stream), and the first 100 ms and the trial's end differ
    slightly from the batch encoding, which resamples whole trials with look-ahead.

    Parameters
    ----------
    n_taxels : int
    normalise : optional :class:`TaxelRange` (then chunks are raw readings, e.g. uint16 ADC counts).
    coeff : SA force coefficient C (scalar or (n_taxels,)).
    k_sa, k_ra, cutoff_hz, rectify, params : as the batch functions.
    fs : the stream's sample rate, Hz (default 1 kHz, the model's rate: no resampling).
    ra : run the RA population too (default); False: SA only (the same SA spikes, ``EncodedChunk.ra`` None, no RA
        filter: what a consumer of SA spikes alone needs, e.g. :class:`rigctl.encoding.realtime.ScanEncoder`).
    """

    def __init__(self, n_taxels: int, *, normalise: TaxelRange | None = None, coeff=1.0, k_sa: float = K_SA,
                 k_ra: float = K_RA, cutoff_hz: float = RA_CUTOFF_HZ, rectify: bool = True, fs: float = FS_HZ,
                 params: IzhikevichParams = TONIC_SPIKING, dtype=np.float32, ra: bool = True):
        self.n_taxels = n_taxels
        self.normalise = normalise
        self.offset, self.scale = _norm_args(normalise)
        self.coeff = np.broadcast_to(np.asarray(coeff, np.float64), (n_taxels,)).copy()
        self.input_fs = float(fs)
        self.dtype = np.dtype(dtype)
        self.ra_dtype = np.dtype(np.float64)  # the fused kernel's RA path (rigctl.encoding.fused)
        self._resampler = None
        if self.input_fs != FS_HZ:
            conv = rate_conversion(self.input_fs, FS_HZ)
            fs = conv.model_rate_hz
            if conv.resampled:
                self._resampler = StreamResampler(conv, n_taxels)
        self.k_sa, self.k_ra, self.fs, self.params = float(k_sa), float(k_ra), float(fs), params
        self.cutoff_hz, self.rectify, self.ra = float(cutoff_hz), bool(rectify), bool(ra)
        if self.ra:
            lowpass_coefficients(self.cutoff_hz, self.fs)  # a bad cutoff fails here, not at the first chunk
        self.reset()

    def reset(self) -> None:
        """Start a new trial: neuron and filter state back to rest, time back to 0."""
        p = self.params
        self._state = FusedState.rest(1, 1, self.n_taxels, c=p.c, b=p.b, dtype=self.dtype, ra_dtype=self.ra_dtype)
        if self._resampler is not None:
            self._resampler.reset()
        self.n_samples = 0  # model steps (samples at the model's rate) so far

    def process(self, chunk: np.ndarray) -> EncodedChunk:
        """Encode ``(n, n_taxels)`` readings that follow the previous chunk.

        Raises
        ------
        ValueError
            if the chunk is not ``(n, n_taxels)``.
        """
        x = np.asarray(chunk)
        if x.ndim != 2 or x.shape[1] != self.n_taxels:
            raise ValueError(f"chunk must be (n, {self.n_taxels}), got {x.shape}")
        n_in = x.shape[0]
        if self._resampler is not None:
            x = self._resampler.process(x)
        n = x.shape[0]
        rg = Ragged(np.ascontiguousarray(x), np.array([0, n], dtype=np.int64))
        res = _fused(rg, normalise=self.normalise, sa_coeffs=(self.coeff,), k_sa=self.k_sa, ra=self.ra,
                     k_ra=self.k_ra, cutoff_hz=self.cutoff_hz, rectify=self.rectify, fs=self.fs, params=self.params,
                     dtype=self.dtype, state=self._state, n0=self.n_samples)
        self.n_samples += n
        return EncodedChunk(res.sa[0], res.ra, n_in)


def default_threads() -> int:
    """Threads numba uses (all cores unless NUMBA_NUM_THREADS says otherwise)."""
    return int(os.environ.get("NUMBA_NUM_THREADS", numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined,arg-type]
