"""The fused encoder: raw ADC counts -> SA and RA spike times in one pass (paper eqs. 3-5, Methods; Fig. 2D).

One numba kernel reads each sample of a trial once and, per taxel, in the same time step:

1. normalises it, ``x = (raw - offset) * scale`` (per-taxel 0-1 range of the whole dataset,
   :class:`~rigctl.encoding.normalise.TaxelRange`);
2. advances one or more SA neurons (tonic spiking, input ``k_SA * C * x``: one population per set of force
   coefficients C of eq. 1, e.g. C = 1, the per-texture C and the label-free C of the pipeline's variants);
3. advances the RA path: the 20 Hz 2nd-order Butterworth low-pass (direct form II transposed, the structure of
   ``scipy.signal.lfilter``; started at the steady state of the trial's first sample), the backward difference in
   normalised units per second (0 at the first sample), half-wave rectified, and the RA neuron (input
   ``k_RA * d``) -- exactly :mod:`rigctl.encoding.filters` + :mod:`rigctl.encoding.izhikevich`, but without the
   float64 copy of the filtered trial;
4. records spikes branch-free (``v >= 30``: ``v <- c``, ``u <- u + d`` by selects, no branch) as bits of a per-lane
   32-step mask; every 32 steps the set bits are turned into sample numbers appended to the train's slots (the
   work is proportional to the spikes, not to the samples; no ``(n_samples, n_channels)`` raster exists).

Layout: time is the outer loop; the lanes are ``block`` trials x n_channels (trial-major, channel-minor,
contiguous: the SIMD axis); blocks of trials run in parallel (``prange``); trials are sorted by length so a block's
trials end together.

**Precision.** The state (v, u, filter) is float32 by default: half the bytes of float64, twice the SIMD lanes. The
model itself is sensitive to rounding: the same float64 per-sample loop fed the input nudged by one ulp changes a
train's SA count by a median 0.5 %, p99 3.4 %, max 6.6 % on real FabricSlide trials (issue 12); the float32 kernel
stays inside that band against the float64 reference (``tests/encoding/test_enc_fused.py``;
``benchmarks/bench_encoder.py`` prints the agreement beside the speed). ``dtype=np.float64`` runs the same kernel
in double precision. No FMA contraction or reassociation is allowed, so every lane does the same IEEE operations
whatever its position: the batch encoding and :class:`~rigctl.encoding.izhikevich.StreamingEncoder` (chunk by chunk,
state carried over) give bit-identical spikes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from rigctl.encoding.filters import lowpass_coefficients
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["FusedState", "FusedResult", "run_fused", "BLOCK_TRIALS"]

#: trials interleaved per SIMD block: block x n_channels lanes (18 channels -> 144 float32 lanes, 18 AVX2 vectors)
BLOCK_TRIALS = 8

#: no FMA contraction or reassociation (see the module docstring): bit-identical lanes
_FASTMATH = {"nnan", "ninf", "nsz"}


@numba.njit(fastmath=_FASTMATH, inline="always", cache=True)
def _step(vv, uu, pv, cnt, msk, act, p, j, i_in, sh, a, b, c, d, v_peak, kc):  # pragma: no cover - compiled by numba
    """One 1 ms step of eqs. (3)-(5) on lane ``j`` (state row ``pv``, count/mask row ``p``): two 0.5 ms half-steps
    of v, u from the new v, the branch-free reset; a spike of a live lane is counted and set as bit ``sh`` of the
    lane's mask."""
    v0 = vv[pv, j]
    u0 = uu[pv, j]
    h, q, f, e = kc[0], kc[1], kc[2], kc[3]  # 0.5, 0.04, 5, 140 in the state's dtype (a literal is float64)
    v1 = v0 + h * (q * v0 * v0 + f * v0 + e - u0 + i_in)
    v2 = v1 + h * (q * v1 * v1 + f * v1 + e - u0 + i_in)
    u1 = u0 + a * (b * v2 - u0)
    s = v2 >= v_peak
    vv[pv, j] = c if s else v2
    uu[pv, j] = u1 + d if s else u1
    sv = np.uint32(s) & np.uint32(act[j])
    cnt[p, j] += np.int32(sv)
    msk[p, j] = msk[p, j] | (sv << sh)


def _fused_py(x, starts, order, off, scl, gains, ra, off_r, scl_r, k_ra, bq, fs_ra, rectify, izr, v, u, filt, fresh,
              counts, spk, block, a, b, c, d, v_peak):  # pragma: no cover - compiled by numba
    """Run the fused encoder over the trials ``order`` (see the module docstring).

    x (N, C) raw input rows (uint16 counts or float); starts (T+1,) int64 row starts; order (M,) trials to run;
    off, scl (C,) normalisation; gains (P_sa, T, C) SA input scale (k_SA * C); ra: run the RA population (index
    P_sa of counts and spk); off_r, scl_r (C,) the normalisation, k_ra, bq (7,) b0, b1, b2, a1, a2, zi0, zi1 of the
    low-pass, fs_ra (Hz) derivative scale and izr (5,) a, b, c, d, v_peak in the RA path's dtype; rectify;
    v, u (P_sa, T, C) SA neuron state (in/out); filt (5, T, C) the RA path's z1, z2, last filtered value, v, u
    (in/out); fresh (T,) uint8: start the filter at this trial's first sample (cleared); counts (P, T, C) int64
    (added to); spk (P, T * C, cap) int32 slots for the sample numbers of each train's spikes (row t * C + ch, from 0
    in this call), or (P, 0, 1) for counts only; block trials per SIMD block. The SA arrays share the SA dtype
    (``off``'s), the RA ones the RA dtype (``filt``'s)."""
    n_ch = x.shape[1]
    n_sa = gains.shape[0]
    n_pop = n_sa + (1 if ra else 0)
    n_run = order.shape[0]
    n_blocks = (n_run + block - 1) // block
    want_spk = spk.shape[1] > 0
    cap = spk.shape[2]
    kc = np.empty(5, dtype=off.dtype)
    kc[0], kc[1], kc[2], kc[3], kc[4] = 0.5, 0.04, 5.0, 140.0, 0.0
    kr = np.empty(5, dtype=filt.dtype)
    kr[0], kr[1], kr[2], kr[3], kr[4] = 0.5, 0.04, 5.0, 140.0, 0.0
    zero = kr[4]
    ar, br, cr, dr, vpr = izr[0], izr[1], izr[2], izr[3], izr[4]
    b0, b1, b2, a1, a2, zi0, zi1 = bq[0], bq[1], bq[2], bq[3], bq[4], bq[5], bq[6]
    for bi in numba.prange(n_blocks):
        i0 = bi * block
        m = min(n_run, i0 + block) - i0
        n_l = m * n_ch
        xb = np.empty(n_l, dtype=off.dtype)
        act = np.zeros(n_l, dtype=np.uint8)
        vv = np.empty((n_sa, n_l), dtype=off.dtype)
        uu = np.empty((n_sa, n_l), dtype=off.dtype)
        gg = np.empty((n_sa, n_l), dtype=off.dtype)
        xr = np.empty(n_l, dtype=filt.dtype)
        vr = np.empty((1, n_l), dtype=filt.dtype)
        ur = np.empty((1, n_l), dtype=filt.dtype)
        z1 = np.empty(n_l, dtype=filt.dtype)
        z2 = np.empty(n_l, dtype=filt.dtype)
        yl = np.empty(n_l, dtype=filt.dtype)
        cnt = np.zeros((n_pop, n_l), dtype=np.int32)  # the lane width of float32: keeps the step one SIMD loop
        wp = np.zeros((n_pop, n_l), dtype=np.int64)
        msk = np.zeros((n_pop, n_l), dtype=np.uint32)
        n_max = 0
        for k in range(m):
            t = order[i0 + k]
            n_max = max(n_max, starts[t + 1] - starts[t])
            for ch in range(n_ch):
                j = k * n_ch + ch
                for p in range(n_sa):
                    vv[p, j] = v[p, t, ch]
                    uu[p, j] = u[p, t, ch]
                    gg[p, j] = gains[p, t, ch]
                vr[0, j] = filt[3, t, ch]
                ur[0, j] = filt[4, t, ch]
                if fresh[t]:  # the filter's steady state for the first sample (scipy's lfilter_zi * x[0])
                    xr[j] = x[starts[t], ch]
                    x0 = (xr[j] - off_r[ch]) * scl_r[ch]
                    z1[j] = zi0 * x0
                    z2[j] = zi1 * x0
                    yl[j] = b0 * x0 + z1[j]  # what the first step computes: its derivative is exactly 0
                else:
                    z1[j] = filt[0, t, ch]
                    z2[j] = filt[1, t, ch]
                    yl[j] = filt[2, t, ch]
            fresh[t] = 0
        for n in range(n_max):
            for k in range(m):
                t = order[i0 + k]
                row = starts[t] + n
                live = row < starts[t + 1]
                if not live:  # trial over: its lanes run on its first row; nothing of them is recorded
                    row = starts[t]
                for ch in range(n_ch):
                    j = k * n_ch + ch
                    xb[j] = x[row, ch]
                    xb[j] = (xb[j] - off[ch]) * scl[ch]
                    act[j] = live
                if ra:
                    for ch in range(n_ch):
                        j = k * n_ch + ch
                        xr[j] = x[row, ch]
                        xr[j] = (xr[j] - off_r[ch]) * scl_r[ch]
            sh = np.uint32(n & 31)
            for p in range(n_sa):
                for j in range(n_l):
                    _step(vv, uu, p, cnt, msk, act, p, j, xb[j] * gg[p, j], sh, a, b, c, d, v_peak, kc)
            if ra:
                for j in range(n_l):
                    xn = xr[j]
                    y = b0 * xn + z1[j]
                    z1[j] = b1 * xn - a1 * y + z2[j]
                    z2[j] = b2 * xn - a2 * y
                    dd = (y - yl[j]) * fs_ra
                    yl[j] = y
                    if rectify:
                        dd = max(dd, zero)
                    _step(vr, ur, 0, cnt, msk, act, n_sa, j, k_ra * dd, sh, ar, br, cr, dr, vpr, kr)
            if want_spk and (sh == 31 or n == n_max - 1):  # turn the mask bits into sample numbers
                base = n - (n & 31)
                for p in range(n_pop):
                    for k in range(m):
                        t = order[i0 + k]
                        for ch in range(n_ch):
                            j = k * n_ch + ch
                            mm = msk[p, j]
                            w = wp[p, j]
                            while mm:
                                spk[p, t * n_ch + ch, min(w, cap - 1)] = base + trailing_zeros(mm)  # type: ignore[call-arg]
                                w += 1
                                mm = mm & (mm - np.uint32(1))
                            wp[p, j] = w
                            msk[p, j] = 0
            for k in range(m):
                t = order[i0 + k]
                if starts[t] + n == starts[t + 1] - 1:  # last sample: this is the trial's final state
                    for ch in range(n_ch):
                        j = k * n_ch + ch
                        for p in range(n_sa):
                            v[p, t, ch] = vv[p, j]
                            u[p, t, ch] = uu[p, j]
                        filt[0, t, ch] = z1[j]
                        filt[1, t, ch] = z2[j]
                        filt[2, t, ch] = yl[j]
                        filt[3, t, ch] = vr[0, j]
                        filt[4, t, ch] = ur[0, j]
        for k in range(m):
            t = order[i0 + k]
            for ch in range(n_ch):
                for p in range(n_pop):
                    counts[p, t, ch] += cnt[p, k * n_ch + ch]


def _renamed(fn: Any, name: str) -> Any:
    """A copy of ``fn`` under another name, so numba caches its serial and parallel builds apart."""
    import types

    new = types.FunctionType(fn.__code__, fn.__globals__, name, fn.__defaults__, fn.__closure__)
    new.__qualname__ = name
    new.__module__ = fn.__module__
    return new


_fused = numba.njit(parallel=True, fastmath=_FASTMATH, cache=True, nogil=True)(_fused_py)
#: without the thread pool, for small calls (streaming chunks, a few trials): no parallel launch overhead
_fused_serial = numba.njit(parallel=False, fastmath=_FASTMATH, cache=True, nogil=True)(
    _renamed(_fused_py, "_fused_serial_py"))


def _times_py(spk, counts, n0, dt, out):  # pragma: no cover - compiled by numba
    """Flat spike times, trial-major then train: row r = t * C + ch of ``spk`` holds ``counts[t, ch]`` sample
    numbers; time = (sample + n0[t]) * dt."""
    n_trials, n_ch = counts.shape
    starts = np.empty(n_trials + 1, dtype=np.int64)
    starts[0] = 0
    for t in range(n_trials):
        s = 0
        for ch in range(n_ch):
            s += counts[t, ch]
        starts[t + 1] = starts[t] + s
    for t in numba.prange(n_trials):
        pos = starts[t]
        for ch in range(n_ch):
            r = t * n_ch + ch
            for i in range(counts[t, ch]):
                out[pos] = (np.int64(spk[r, i]) + n0[t]) * dt
                pos += 1


_times = numba.njit(parallel=True, cache=True, nogil=True)(_times_py)
_times_serial = numba.njit(parallel=False, cache=True, nogil=True)(_renamed(_times_py, "_times_serial_py"))


@dataclass
class FusedState:
    """The state of a :func:`run_fused` call, carried over between calls (streaming).

    v, u : (n_sa_populations, n_trials, n_channels) SA membrane potential (mV) and recovery variable (eqs. 3-4);
    filt : (5, n_trials, n_channels) the RA path: low-pass state z1, z2, its last output, the RA neuron's v and u;
    fresh : (n_trials,) uint8, 1 = the next sample starts the trial (the filter starts at its steady state).
    """

    v: np.ndarray
    u: np.ndarray
    filt: np.ndarray
    fresh: np.ndarray

    @classmethod
    def rest(cls, n_sa: int, n_trials: int, n_channels: int, *, c: float = -65.0, b: float = 0.2,
             dtype: Any = np.float32, ra_dtype: Any = np.float64) -> "FusedState":
        """Every neuron at rest (``v = c``, ``u = b c``), every filter fresh."""
        v = np.full((n_sa, n_trials, n_channels), c, dtype=dtype)
        u = (np.asarray(b, dtype) * v).astype(dtype)
        filt = np.zeros((5, n_trials, n_channels), dtype=ra_dtype)
        filt[3] = c
        filt[4] = np.asarray(b, ra_dtype) * filt[3]
        return cls(v, u, filt, np.ones(n_trials, dtype=np.uint8))


@dataclass(frozen=True)
class FusedResult:
    """What :func:`run_fused` gives: the SA trains of each gain set, the RA trains (or None), and the counts.

    sa : tuple of :class:`SpikeTrains` (n_trials, n_channels), one per SA gain set (empty when counts only);
    ra : SpikeTrains (n_trials, n_channels) or None;
    counts : (n_populations, n_trials, n_channels) int64 (SA gain sets first, then RA).
    """

    sa: tuple[SpikeTrains, ...]
    ra: SpikeTrains | None
    counts: np.ndarray


def _gain_matrix(gain: Any, n_trials: int, n_ch: int, dtype: Any) -> np.ndarray:
    g = np.asarray(gain, dtype=np.float64)
    if g.ndim == 2 and g.shape != (n_trials, n_ch) or g.ndim > 2:
        raise ValueError(f"gain must be a scalar, ({n_ch},) or ({n_trials}, {n_ch}), got {g.shape}")
    return np.broadcast_to(g, (n_trials, n_ch))


def _input_dtype(x: np.ndarray) -> np.ndarray:
    if x.dtype in (np.uint16, np.int16, np.int32, np.float32, np.float64):
        return np.ascontiguousarray(x)
    return np.ascontiguousarray(x, dtype=np.float64)


def run_fused(data: np.ndarray, starts: np.ndarray, *, offset: Any = 0.0, scale: Any = 1.0,
              sa_gains: Sequence[Any] = (1.0,), k_sa: float = 100.0, ra: bool = True, k_ra: float = 3.0,
              cutoff_hz: float = 20.0, rectify: bool = True, fs: float = 1000.0,
              izhikevich: tuple[float, float, float, float, float] = (0.02, 0.2, -65.0, 6.0, 30.0),
              dtype: Any = np.float32, ra_dtype: Any = np.float64, want_times: bool = True,
              state: FusedState | None = None, n0: Any = 0, active: np.ndarray | None = None,
              block: int = BLOCK_TRIALS) -> FusedResult:
    """Encode trials stored flat with the fused kernel (see the module docstring).

    Parameters
    ----------
    data : (n_total_samples, n_channels) raw readings (uint16 ADC counts, or float), trials one after the other,
        at the model's rate (1 kHz: one 1 ms step per sample).
    starts : (n_trials + 1,) int64 row starts (``data[starts[t]:starts[t + 1]]`` is trial t).
    offset, scale : scalar or (n_channels,): ``(raw - offset) * scale`` is the normalised 0-1 reading.
    sa_gains : one SA population per entry: scalar, (n_channels,) or (n_trials, n_channels) force coefficient C
        (eq. 1); the SA input is ``k_sa * C * x``. Empty: no SA population.
    k_sa, k_ra : eq. (3) input scales (100, 3). ra : run the RA population too. cutoff_hz : RA low-pass (Hz).
    rectify : half-wave rectify the RA derivative. fs : the model's rate, Hz (derivative per second, spike times).
    izhikevich : (a, b, c, d, v_peak) of eqs. (3)-(5) (tonic spiking).
    dtype : np.float32 (default) or np.float64 state and arithmetic of the SA populations.
    ra_dtype : the RA path's (normalisation, low-pass, derivative, neuron): np.float64 (default; the derivative
        multiplies the low-pass output's rounding by fs, which float32 would turn into RA count changes beyond the
        model's own sensitivity) or np.float32.
    want_times : build the spike trains (False: counts only, e.g. force bisection).
    state : a :class:`FusedState` carried over from the previous call (streaming; updated in place) or None (rest).
    n0 : scalar or (n_trials,) samples already encoded before this call (added to every spike's sample number).
    active : optional (n_trials,) bool; inactive trials are skipped (counts 0, state untouched).
    block : trials per SIMD block.

    Returns
    -------
    FusedResult
        Spike times in s from each trial's first sample: ``(sample + n0) / fs``.

    Raises
    ------
    ValueError
        On mismatched shapes or a cutoff outside (0, fs/2).
    """
    dt, rdt = np.dtype(dtype), np.dtype(ra_dtype)
    if dt not in (np.float32, np.float64) or rdt not in (np.float32, np.float64):
        raise ValueError(f"dtype and ra_dtype must be float32 or float64, got {dt}, {rdt}")
    x = _input_dtype(np.asarray(data))
    if x.ndim != 2:
        raise ValueError(f"data must be (n_samples, n_channels), got {x.shape}")
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    n_trials, n_ch = starts.size - 1, x.shape[1]
    if n_trials < 0 or (n_trials and (starts[0] != 0 or starts[-1] != x.shape[0] or np.any(np.diff(starts) < 0))):
        raise ValueError("starts must be non-decreasing row starts from 0 to len(data)")
    off64 = np.ascontiguousarray(np.broadcast_to(np.asarray(offset, np.float64), (n_ch,)))
    scl64 = np.ascontiguousarray(np.broadcast_to(np.asarray(scale, np.float64), (n_ch,)))
    off, scl = off64.astype(dt), scl64.astype(dt)
    n_sa = len(sa_gains)
    gains = np.empty((n_sa, n_trials, n_ch), dtype=dt)
    for i, g in enumerate(sa_gains):
        gains[i] = float(k_sa) * _gain_matrix(g, n_trials, n_ch, dt)
    n_pop = n_sa + (1 if ra else 0)
    a, b, c, d, v_peak = (float(p) for p in izhikevich)
    if state is None:
        state = FusedState.rest(n_sa, n_trials, n_ch, c=c, b=b, dtype=dt, ra_dtype=rdt)
    if (state.v.shape != (n_sa, n_trials, n_ch) or state.v.dtype != dt or state.filt.shape != (5, n_trials, n_ch)
            or state.filt.dtype != rdt):
        raise ValueError(f"state must be ({n_sa}, {n_trials}, {n_ch}) {dt} and (5, {n_trials}, {n_ch}) {rdt} arrays")
    bq = np.zeros(7, dtype=rdt)
    if ra:
        bb, aa, zi = lowpass_coefficients(float(cutoff_hz), float(fs))
        bq[:] = [bb[0], bb[1], bb[2], aa[1], aa[2], zi[0], zi[1]]
    lengths = np.diff(starts)
    act = np.ones(n_trials, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    order = np.flatnonzero(act & (lengths > 0))
    order = order[np.argsort(lengths[order], kind="stable")]
    counts = np.zeros((n_pop, n_trials, n_ch), dtype=np.int64)
    n_max = int(lengths.max(initial=0))
    # one slot per sample at most: never overflows; np.empty leaves the untouched pages unallocated
    spk = np.empty((n_pop, n_trials * n_ch if want_times else 0, n_max + 1 if want_times else 1), dtype=np.int32)
    kernel = _fused if order.size > block else _fused_serial
    kernel(x, starts, order, off, scl, gains, bool(ra), off64.astype(rdt), scl64.astype(rdt), rdt.type(k_ra), bq,
           rdt.type(fs), bool(rectify), np.array([a, b, c, d, v_peak], dtype=rdt), state.v, state.u, state.filt,
           state.fresh, counts, spk, int(block), dt.type(a), dt.type(b), dt.type(c), dt.type(d), dt.type(v_peak))
    if not want_times:
        return FusedResult((), None, counts)
    n0a = np.ascontiguousarray(np.broadcast_to(np.asarray(n0, np.int64), (n_trials,)))
    fill = _times if n_trials > block else _times_serial
    trains = []
    for p in range(n_pop):
        cp = np.ascontiguousarray(counts[p])
        out = np.empty(int(cp.sum()), dtype=np.float64)
        fill(spk[p], cp, n0a, 1.0 / float(fs), out)
        trains.append(SpikeTrains.from_counts(out, cp))
    return FusedResult(tuple(trains[:n_sa]), trains[n_sa] if ra else None, counts)
