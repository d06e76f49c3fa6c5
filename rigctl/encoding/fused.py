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
   32-step mask; at the end of each 32-step word the mask gives the count (popcount) and is stored as one word of
   the train's spike bitmap (1 bit per sample: no ``(n_samples, n_channels)`` raster, no per-spike work in the
   step loop); a second pass turns the set bits into NWB spike times (work proportional to the spikes).

Layout: time is the outer loop, in chunks of at most 32 steps (never across a bitmap word or a trial's end); the
lanes are ``block`` trials x n_channels (trial-major, channel-minor, contiguous: the SIMD axis). Per chunk a pre-
pass gathers and normalises the block's readings into a (32, lanes) buffer (integer readings by explicit SIMD
vectors, a row rounded up to whole registers: a loop over a row's 18 channels ran behind LLVM's run-time overlap
checks with a scalar tail, about as long as the SA steps), then each population steps every lane through the chunk
in one contiguous loop (float32 SA lanes 16 at a time as explicit vectors, :func:`_sa_vec_one`: LLVM's own
vectoriser kept them in 256-bit registers, the one-thread kernel ~20 % slower). The spike times are decoded from the
bitmaps a word at a time (:mod:`rigctl.encoding.bitmaps`: no branch on how many spikes a word holds). Blocks of
trials run in parallel on threads of ours: the kernel's one (serial) build, once on each of
``numba.get_num_threads()`` threads (it releases the GIL), each claiming the next block from an atomic counter
(:func:`~rigctl.encoding.llvm_ops.claim`). No ``parallel=True`` build: it took ~2.4x the
compile time of the serial one (12.2 against 5.1 s of CPU, on the first encoding of an installation) and ran 128
trials x 6 s x 18 taxels in the same CPU time (SA: 12-15 against 13-14 ms). Trials are sorted by length so a block's
trials end together.

**Precision.** The state (v, u, filter) is float32 by default: half the bytes of float64, twice the SIMD lanes. The
model itself is sensitive to rounding: the same float64 per-sample loop fed the input nudged by one ulp changes a
train's SA count by a median 0.5 %, p99 3.4 %, max 6.6 % on real FabricSlide trials (issue 12); the float32 kernel
stays inside that band against the float64 reference (``tests/encoding/test_enc_fused.py``;
``benchmarks/bench_encoder.py`` prints the agreement beside the speed). In float32 the step is the same model with
its constants folded (``v + h (q v^2 + f v + e - u + I) = v (h q v + 1 + h f) + h (e - u + I)``, the input term
shared by both half-steps: 11 operations instead of 21); float64 keeps the paper's expressions as written, so the
float64 kernel is the per-sample reference bit for bit. ``dtype=np.float64`` runs the same kernel
in double precision. No FMA contraction or reassociation is allowed, so every lane does the same IEEE operations
whatever its position: the batch encoding and :class:`~rigctl.encoding.izhikevich.StreamingEncoder` (chunk by chunk,
state carried over) give bit-identical spikes.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

from rigctl.core.encoding_model import MODEL_RATE_HZ, RA_CUTOFF_HZ
from rigctl.encoding.bitmaps import WORD, decode_times
from rigctl.encoding.filters import lowpass_coefficients
from rigctl.encoding.llvm_ops import claim, popcount, splat, vector_at
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["FusedState", "FusedResult", "run_fused", "on_threads", "BLOCK_TRIALS"]

#: trials interleaved per SIMD block: block x n_channels lanes (18 channels -> 144 float32 lanes, 18 AVX2 vectors)
BLOCK_TRIALS = 8

#: no FMA contraction or reassociation (see the module docstring): bit-identical lanes
_FASTMATH = {"nnan", "ninf", "nsz"}


def _sa_step(v0, u0, i_in, kc):  # pragma: no cover - replaced by the overload below inside numba
    """v2 and u1 of one 1 ms step (two 0.5 ms half-steps of v, u from the new v; eqs. 3-4), before the reset."""
    raise NotImplementedError


@overload(_sa_step, inline="always", jit_options={"fastmath": _FASTMATH})
def _sa_step_impl(v0, u0, i_in, kc):  # pragma: no cover - compiled by numba
    """float64: the paper's expressions as written (the reference: the per-sample loop's operations, bit for bit).
    float32: the same model, rearranged with the half-step constants folded (kc[4:9] = h q, 1 + h f, h e, 1 - a, a b)
    and the input term shared by both half-steps: 11 operations instead of 21. The rearrangement only moves float32
    rounding, which stays inside the model's own sensitivity band (module docstring)."""
    if v0 == types.float32:
        def fast(v0, u0, i_in, kc):
            w = kc[6] + kc[0] * (i_in - u0)  # h (e - u + I)
            v1 = v0 * (kc[4] * v0 + kc[5]) + w
            v2 = v1 * (kc[4] * v1 + kc[5]) + w
            return v2, kc[7] * u0 + kc[8] * v2
        return fast

    def exact(v0, u0, i_in, kc):
        h, q, f, e, a, b = kc[0], kc[1], kc[2], kc[3], kc[9], kc[10]
        v1 = v0 + h * (q * v0 * v0 + f * v0 + e - u0 + i_in)
        v2 = v1 + h * (q * v1 * v1 + f * v1 + e - u0 + i_in)
        return v2, u0 + a * (b * v2 - u0)
    return exact


#: float32 SA lanes stepped at once by :func:`_sa_vec_one` (one 512-bit register where the CPU has AVX-512; LLVM
#: splits it into two 256-bit ones elsewhere): the block's lane arrays are padded to a multiple of it
_SA_VEC = 16


def _sa_vec_codegen(context, builder, signature, args, per_lane):  # pragma: no cover - compiled by numba
    """The body of :func:`_sa_vec_one` and :func:`_sa_vec_lanes`: :func:`_sa_lane`'s float32 operations on ``_SA_VEC``
    lanes as explicit LLVM vector operations (the same IEEE products, sums and compare, no contraction: bit for bit
    the scalar lane's results)."""
    vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit = args
    t_vv, t_uu, t_msk, _, t_xb, _, t_g = signature.args[:7]
    f32, i32 = ir.FloatType(), ir.IntType(32)
    vf, vi = ir.VectorType(f32, _SA_VEC), ir.VectorType(i32, _SA_VEC)
    zeros = ir.Constant(vi, [0] * _SA_VEC)

    def ptr(aty, aval, i, vty):
        return vector_at(context, builder, aty, aval, i, vty)

    def k(i):
        return splat(builder, builder.extract_value(kc, i), vf)

    x = builder.load(ptr(t_xb, xb, ix, vf), align=4)
    gv = builder.load(ptr(t_g, g, idx, vf), align=4) if per_lane else splat(builder, g, vf)
    i_in = builder.fmul(x, gv)
    p_v, p_u, p_m = ptr(t_vv, vv, idx, vf), ptr(t_uu, uu, idx, vf), ptr(t_msk, msk, idx, vi)
    v0, u0 = builder.load(p_v, align=4), builder.load(p_u, align=4)
    w = builder.fadd(k(6), builder.fmul(k(0), builder.fsub(i_in, u0)))  # h (e - u + I)
    v1 = builder.fadd(builder.fmul(v0, builder.fadd(builder.fmul(k(4), v0), k(5))), w)
    v2 = builder.fadd(builder.fmul(v1, builder.fadd(builder.fmul(k(4), v1), k(5))), w)
    u1 = builder.fadd(builder.fmul(k(7), u0), builder.fmul(k(8), v2))
    s = builder.fcmp_ordered(">=", v2, splat(builder, v_peak, vf))
    builder.store(builder.select(s, splat(builder, c, vf), v2), p_v, align=4)
    builder.store(builder.select(s, builder.fadd(u1, splat(builder, d, vf)), u1), p_u, align=4)
    m = builder.load(p_m, align=4)
    builder.store(builder.or_(m, builder.select(s, splat(builder, bit, vi), zeros)), p_m, align=4)
    return context.get_dummy_value()


def _sa_vec_sig(vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit):
    return types.void(vv, uu, msk, types.intp, xb, types.intp, g, kc, c, d, v_peak, bit)


@intrinsic
def _sa_vec_one(typingctx, vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit):  # pragma: no cover - compiled by numba
    """``_SA_VEC`` float32 SA lanes from flat index ``idx`` of ``vv``, ``uu`` (float32) and ``msk`` (uint32) stepped by
    one 1 ms step with input ``xb[ix:ix + _SA_VEC] * g`` (one gain ``g`` for every lane): :func:`_sa_lane` as
    vectors. kc: the float32 constants tuple (:func:`_constants`); c, d, v_peak float32; bit uint32. The caller keeps
    every index in bounds (C-contiguous arrays)."""
    return _sa_vec_sig(vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit), partial(_sa_vec_codegen, per_lane=False)


@intrinsic
def _sa_vec_lanes(typingctx, vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit):  # pragma: no cover - numba
    """:func:`_sa_vec_one` with each lane's own gain, ``g[idx:idx + _SA_VEC]`` (a float32 array laid out as ``vv``)."""
    return _sa_vec_sig(vv, uu, msk, idx, xb, ix, g, kc, c, d, v_peak, bit), partial(_sa_vec_codegen, per_lane=True)

#: bytes of one SIMD register (AVX2): the pre-pass's explicit vectors (:func:`_norm_vec`)
_VEC_BYTES = 32


@intrinsic
def _norm_vec(typingctx, src, i_src, off, scl, i_ch, dst, i_dst):  # pragma: no cover - compiled by numba
    """``dst[i_dst + c] = (dst.dtype(src[i_src + c]) - off[i_ch + c]) * scl[i_ch + c]`` for the c of one SIMD
    register (``_VEC_BYTES`` of ``dst``'s dtype), as explicit LLVM vector operations, no overlap checks: the same
    IEEE conversion (integer to float: exact), difference and product as the scalar expression, bit for bit.
    ``src`` an integer array, the others of one float dtype, all 1-d C-contiguous; the caller keeps every index in
    bounds."""
    width = _VEC_BYTES * 8 // dst.dtype.bitwidth
    sig = types.void(src, types.intp, off, scl, types.intp, dst, types.intp)

    def codegen(context, builder, signature, args):
        a_src, a_is, a_off, a_scl, a_ic, a_dst, a_id = args
        t_src, _, t_off, t_scl, _, t_dst, _ = signature.args
        vf = ir.VectorType(context.get_value_type(t_dst.dtype), width)
        vi = ir.VectorType(context.get_value_type(t_src.dtype), width)

        def ptr(aty, aval, idx, vty):
            return vector_at(context, builder, aty, aval, idx, vty)

        raw = builder.load(ptr(t_src, a_src, a_is, vi), align=t_src.dtype.bitwidth // 8)
        x = builder.sitofp(raw, vf) if t_src.dtype.signed else builder.uitofp(raw, vf)
        al = t_dst.dtype.bitwidth // 8
        o = builder.load(ptr(t_off, a_off, a_ic, vf), align=al)
        sc = builder.load(ptr(t_scl, a_scl, a_ic, vf), align=al)
        builder.store(builder.fmul(builder.fsub(x, o), sc), ptr(t_dst, a_dst, a_id, vf), align=al)
        return context.get_dummy_value()
    return sig, codegen


def _constants_py(dtype_of, a, b):  # pragma: no cover - compiled by numba
    """kc (11,) in the dtype of ``dtype_of``: h, q, f, e, h q, 1 + h f, h e, 1 - a, a b, a, b (see _sa_step)."""
    kc = np.empty(11, dtype=dtype_of.dtype)
    h, q, f, e = 0.5, 0.04, 5.0, 140.0
    kc[0], kc[1], kc[2], kc[3] = h, q, f, e
    kc[4], kc[5], kc[6], kc[7], kc[8] = h * q, 1.0 + h * f, h * e, 1.0 - a, a * b
    kc[9], kc[10] = a, b
    return kc


_constants_arr = numba.njit(inline="always", cache=True)(_constants_py)


@numba.njit(inline="always", cache=True)
def _constants(dtype_of, a, b):  # pragma: no cover - compiled by numba
    """:func:`_constants_py`'s kc as a tuple: values, not an array the kernel's stores might alias (LLVM reloaded
    an array's constants inside the step loop)."""
    k = _constants_arr(dtype_of, a, b)
    return (k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8], k[9], k[10])


def _cast(v, like):  # pragma: no cover - replaced by the overload below inside numba
    """``v`` converted to the dtype of the array ``like``."""
    raise NotImplementedError


@overload(_cast, inline="always")
def _cast_impl(v, like):  # pragma: no cover - compiled by numba
    to = numba.np.numpy_support.as_dtype(like.dtype).type

    def cast(v, like):
        return to(v)
    return cast

@numba.njit(inline="always", fastmath=_FASTMATH, cache=True)
def _sa_lane(vv, uu, msk, p, j, i_in, kc, c, d, v_peak, bit, zero32):  # pragma: no cover - compiled by numba
    """One SA lane's step: v, u advanced by input ``i_in``, reset on a spike (selects, no branch), the spike as
    ``bit`` of its mask."""
    v2, u1 = _sa_step(vv[p, j], uu[p, j], i_in, kc)
    s = v2 >= v_peak
    vv[p, j] = c if s else v2
    uu[p, j] = u1 + d if s else u1
    msk[p, j] = msk[p, j] | (bit if s else zero32)

def _norm_row(xf, i_src, off, scl, dst, i_dst, n_ch):  # pragma: no cover - replaced by the overload below
    """``dst[i_dst + c] = (dst.dtype(xf[i_src + c]) - off[c]) * scl[c]`` for c < n_ch: one row of readings,
    normalised into the lanes' buffer. With integer readings whole SIMD registers up to ``off.size`` (n_ch rounded
    up to a register; the values past n_ch land on the lanes the next row's call writes, or on the buffer's
    padding), where the row has that many readings after it in ``xf``."""
    raise NotImplementedError


@overload(_norm_row, inline="always", jit_options={"fastmath": _FASTMATH})
def _norm_row_impl(xf, i_src, off, scl, dst, i_dst, n_ch):  # pragma: no cover - compiled by numba
    width = _VEC_BYTES * 8 // dst.dtype.bitwidth

    def loop(xf, i_src, off, scl, dst, i_dst, n_ch):
        for c in range(n_ch):
            dst[i_dst + c] = (_cast(xf[i_src + c], dst) - off[c]) * scl[c]

    if not isinstance(xf.dtype, types.Integer):
        return loop

    def vec(xf, i_src, off, scl, dst, i_dst, n_ch):
        n_pad = off.size
        if i_src + n_pad <= xf.size:
            for c in range(0, n_pad, width):
                _norm_vec(xf, i_src + c, off, scl, c, dst, i_dst + c)  # type: ignore[call-arg]
        else:
            for c in range(n_ch):
                dst[i_dst + c] = (_cast(xf[i_src + c], dst) - off[c]) * scl[c]
    return vec


def _sa_steps(vv, uu, msk, gg, p, n_l, n_lp, xb, ix, g0, kc, c, d, v_peak, bit, zero32, zero_sa):  # pragma: no cover
    """One step of population p's lanes (:func:`_sa_lane` each) with input ``xb[ix + j]`` times the one gain ``g0``
    (when not 0: a constant, not a load a lane) or each lane's ``gg[p, j]``. float32: ``_SA_VEC`` lanes at once
    (:func:`_sa_vec_one`), every lane of the padded ``n_lp``; float64: lane by lane, the ``n_l`` real ones."""
    raise NotImplementedError


@overload(_sa_steps, inline="always", jit_options={"fastmath": _FASTMATH})
def _sa_steps_impl(vv, uu, msk, gg, p, n_l, n_lp, xb, ix, g0, kc, c, d, v_peak, bit, zero32, zero_sa):  # pragma: no cover
    if vv.dtype == types.float32:
        def vec(vv, uu, msk, gg, p, n_l, n_lp, xb, ix, g0, kc, c, d, v_peak, bit, zero32, zero_sa):
            row = p * n_lp
            if g0 != zero_sa:
                for j in range(0, n_lp, _SA_VEC):
                    _sa_vec_one(vv, uu, msk, row + j, xb, ix + j, g0, kc, c, d, v_peak, bit)  # type: ignore[call-arg]
            else:
                for j in range(0, n_lp, _SA_VEC):
                    _sa_vec_lanes(vv, uu, msk, row + j, xb, ix + j, gg, kc, c, d, v_peak, bit)  # type: ignore[call-arg]
        return vec

    def lanes(vv, uu, msk, gg, p, n_l, n_lp, xb, ix, g0, kc, c, d, v_peak, bit, zero32, zero_sa):
        if g0 != zero_sa:
            for j in range(n_l):
                _sa_lane(vv, uu, msk, p, j, xb[ix + j] * g0, kc, c, d, v_peak, bit, zero32)
        else:
            for j in range(n_l):
                _sa_lane(vv, uu, msk, p, j, xb[ix + j] * gg[p, j], kc, c, d, v_peak, bit, zero32)
    return lanes


def _padded_py(a, width):  # pragma: no cover - compiled by numba
    """``a`` (n,) with zeros after it up to a multiple of ``width``."""
    out = np.zeros((a.size + width - 1) // width * width, dtype=a.dtype)
    out[:a.size] = a
    return out


_padded = numba.njit(inline="always", cache=True)(_padded_py)


def _fused_py(x, starts, order, off, scl, gains, ra, off_r, scl_r, k_ra, bq, fs_ra, rectify, izr, v, u, filt, fresh,
              counts, bits, block, a, b, c, d, v_peak, next_block):  # pragma: no cover - compiled by numba
    """Run the fused encoder over the trials ``order`` (see the module docstring).

    x (N, C) raw input rows (uint16 counts or float); starts (T+1,) int64 row starts; order (M,) trials to run,
    sorted by length; off, scl (C,) normalisation; gains (P_sa, T, C) SA input scale (k_SA * C); ra: run the RA
    population (index P_sa of counts and bits); off_r, scl_r (C,) the normalisation, k_ra, bq (7,) b0, b1, b2, a1,
    a2, zi0, zi1 of the low-pass, fs_ra (Hz) derivative scale and izr (5,) a, b, c, d, v_peak in the RA path's dtype;
    rectify; v, u (P_sa, T, C) SA neuron state (in/out); filt (5, T, C) the RA path's z1, z2, last filtered value, v,
    u (in/out); fresh (T,) uint8: start the filter at this trial's first sample (cleared); counts (P, T, C) int64
    (added to); bits (P, T * C, W) uint32 spike bitmaps (row t * C + ch; bit i of word w = a spike at sample
    32 w + i of this call; a word past a trial's end holds 0 or is not written), or (P, 0, 1) for counts
    only; block trials per SIMD block; next_block (1,) int64, 0 at the call's start: the blocks are claimed from
    it (:func:`~rigctl.encoding.llvm_ops.claim`), so every thread of a call runs this once. The SA arrays share the
    SA dtype (``off``'s), the RA ones the RA dtype (``filt``'s).

    Per block, time runs in chunks of at most 32 steps that never cross a 32-step word or a trial's end: a pre-pass
    normalises the chunk's readings into (32, lanes) buffers, then each population steps all lanes for the chunk
    (contiguous SIMD loops, spikes as mask bits); at a word's end the masks give the counts (popcount) and the
    bitmap words; at a trial's end its state is saved."""
    n_ch = x.shape[1]
    xf = x.reshape(x.size)  # (a view: x is C-contiguous)
    offp, sclp = _padded(off, _VEC_BYTES // off.itemsize), _padded(scl, _VEC_BYTES // off.itemsize)
    offp_r, sclp_r = _padded(off_r, _VEC_BYTES // off_r.itemsize), _padded(scl_r, _VEC_BYTES // off_r.itemsize)
    n_sa = gains.shape[0]
    n_pop = n_sa + (1 if ra else 0)
    n_run = order.shape[0]
    n_blocks = (n_run + block - 1) // block
    want_bits = bits.shape[1] > 0
    kc = _constants(off, a, b)
    kr = _constants(filt, izr[0], izr[1])
    zero = kr[0] - kr[0]
    zero32 = np.uint32(0)
    zero_sa = kc[0] - kc[0]
    cr, dr, vpr = izr[2], izr[3], izr[4]
    b0, b1, b2, a1, a2, zi0, zi1 = bq[0], bq[1], bq[2], bq[3], bq[4], bq[5], bq[6]
    while True:  # (every thread of a call runs this once, over the blocks it claims)
        bi: int = claim(next_block)  # type: ignore[call-arg]
        if bi >= n_blocks:
            break
        i0 = bi * block
        m = min(n_run, i0 + block) - i0
        n_l = m * n_ch
        n_lp = (n_l + _SA_VEC - 1) // _SA_VEC * _SA_VEC  # (SA lanes padded to whole vectors: idle lanes at rest)
        xb = np.zeros(WORD * n_l + offp.size + _SA_VEC, dtype=off.dtype)  # (+ the last row's and lanes' padding)
        xr = np.empty(WORD * n_l + offp_r.size if ra else 1, dtype=filt.dtype)
        vv = np.full((n_sa, n_lp), c, dtype=off.dtype)
        uu = np.zeros((n_sa, n_lp), dtype=off.dtype)
        gg = np.zeros((n_sa, n_lp), dtype=off.dtype)
        gg_one = np.empty(n_sa, dtype=off.dtype)
        vr = np.empty(n_l, dtype=filt.dtype)
        ur = np.empty(n_l, dtype=filt.dtype)
        z1 = np.empty(n_l, dtype=filt.dtype)
        z2 = np.empty(n_l, dtype=filt.dtype)
        yl = np.empty(n_l, dtype=filt.dtype)
        cnt = np.zeros((n_pop, n_l), dtype=np.int32)
        msk = np.zeros((n_pop, n_lp), dtype=np.uint32)
        lens = np.empty(m, dtype=np.int64)
        rs = np.empty(m, dtype=np.int64)
        vl = np.empty(n_l, dtype=np.uint32)
        msk2 = np.empty(n_l, dtype=np.uint32)
        row_of = np.empty(n_l, dtype=np.int64)
        for k in range(m):
            t = order[i0 + k]
            lens[k] = starts[t + 1] - starts[t]
            rs[k] = starts[t]
            for ch in range(n_ch):
                row_of[k * n_ch + ch] = t * n_ch + ch
            for ch in range(n_ch):
                j = k * n_ch + ch
                for p in range(n_sa):
                    vv[p, j] = v[p, t, ch]
                    uu[p, j] = u[p, t, ch]
                    gg[p, j] = gains[p, t, ch]
                vr[j] = filt[3, t, ch]
                ur[j] = filt[4, t, ch]
                if fresh[t]:  # the filter's steady state for the first sample (scipy's lfilter_zi * x[0])
                    yl[j] = x[starts[t], ch]  # (converted to the RA dtype)
                    x0 = (yl[j] - off_r[ch]) * scl_r[ch]
                    z1[j] = zi0 * x0
                    z2[j] = zi1 * x0
                    yl[j] = b0 * x0 + z1[j]  # what the first step computes: its derivative is exactly 0
                else:
                    z1[j] = filt[0, t, ch]
                    z2[j] = filt[1, t, ch]
                    yl[j] = filt[2, t, ch]
            fresh[t] = 0
        for p in range(n_sa):  # the block's one gain of population p, or 0 when its lanes' gains differ (or are 0)
            gg_one[p] = gg[p, 0]
            for j in range(n_l):
                if gg[p, j] != gg_one[p]:
                    gg_one[p] = zero_sa
        n_max = lens[m - 1]
        kk = 0  # the shortest trial still running
        n = 0
        while n < n_max:
            while lens[kk] <= n:
                kk += 1
            sh0 = n & (WORD - 1)
            mc = min(WORD - sh0, lens[kk] - n)
            for i in range(mc):  # pre-pass: the chunk's normalised readings (an ended trial's lanes: its first row)
                for k in range(m):  # (in lane order: a row's padding lands on the next row's lanes, written next)
                    row = rs[k] + n + i if n + i < lens[k] else rs[k]
                    q = i * n_l + k * n_ch  # xb, xr: (chunk step, lane) flat
                    _norm_row(xf, row * n_ch, offp, sclp, xb, q, n_ch)
                    if ra:
                        _norm_row(xf, row * n_ch, offp_r, sclp_r, xr, q, n_ch)
            for p in range(n_sa):
                g0 = gg_one[p]
                for i in range(mc):
                    bit = np.uint32(1 << (sh0 + i))  # (a uint32 select and or: a shift by a variable widened to 64 bits)
                    _sa_steps(vv, uu, msk, gg, p, n_l, n_lp, xb, i * n_l, g0, kc, c, d, v_peak, bit, zero32, zero_sa)
            if ra:
                for i in range(mc):
                    bit = np.uint32(1 << (sh0 + i))
                    for j in range(n_l):
                        xn = xr[i * n_l + j]
                        y = b0 * xn + z1[j]
                        z1[j] = b1 * xn - a1 * y + z2[j]
                        z2[j] = b2 * xn - a2 * y
                        dd = (y - yl[j]) * fs_ra
                        yl[j] = y
                        if rectify:
                            dd = max(dd, zero)
                        v2, u1 = _sa_step(vr[j], ur[j], k_ra * dd, kr)
                        s = v2 >= vpr
                        vr[j] = cr if s else v2
                        ur[j] = u1 + dr if s else u1
                        msk[n_sa, j] = msk[n_sa, j] | (bit if s else zero32)
            n += mc
            for k in range(kk, m):  # trials ending here: their final state
                if lens[k] == n:
                    t = order[i0 + k]
                    for ch in range(n_ch):
                        j = k * n_ch + ch
                        for p in range(n_sa):
                            v[p, t, ch] = vv[p, j]
                            u[p, t, ch] = uu[p, j]
                        filt[0, t, ch] = z1[j]
                        filt[1, t, ch] = z2[j]
                        filt[2, t, ch] = yl[j]
                        filt[3, t, ch] = vr[j]
                        filt[4, t, ch] = ur[j]
            if (n & (WORD - 1)) == 0 or n == n_max:  # a word is complete: counts and bitmap words
                w = (n - 1) // WORD
                for k in range(m):  # each lane's samples in the word (none: its trial ended before it)
                    left = lens[k] - w * WORD
                    valid = np.uint32(0) if left <= 0 else np.uint32(0xFFFFFFFF) >> np.uint32(WORD - min(left, WORD))
                    for ch in range(n_ch):
                        vl[k * n_ch + ch] = valid
                for p in range(n_pop):  # (one loop over the block's lanes: SIMD, no tail per trial)
                    for j in range(n_l):
                        mm = msk[p, j] & vl[j]
                        cnt[p, j] += popcount(mm)
                        msk[p, j] = 0
                        msk2[j] = mm
                    if want_bits:  # (a word past a trial's end: zeros, never read)
                        for j in range(n_l):
                            bits[p, row_of[j], w] = msk2[j]
        for k in range(m):
            t = order[i0 + k]
            for ch in range(n_ch):
                for p in range(n_pop):
                    counts[p, t, ch] += cnt[p, k * n_ch + ch]


#: one build for every input type (no ``parallel=True`` build: see the module docstring); more than a block of trials
#: runs on threads (:func:`on_threads`). numpy's error model: no zero-division checks (the kernel divides only by
#: constants), which ran the RA path ~10 % faster
_fused = numba.njit(fastmath=_FASTMATH, cache=True, nogil=True, error_model="numpy")(_fused_py)


#: the encoder's worker threads, started once per process and reused by every call (a pool started per call cost
#: two thread starts a call: the force fit's 100-odd kernel calls paid ~0.2 s of it on a 960-trial session); made
#: again in a forked child (threads do not survive a fork)
_POOL: dict[str, Any] = {"pool": None, "size": 0, "pid": 0}
_POOL_LOCK = threading.Lock()


def _pool(n_workers: int) -> ThreadPoolExecutor:
    """The process's encoder pool with at least ``n_workers`` threads (grown, never shrunk: idle threads cost
    nothing)."""
    with _POOL_LOCK:
        if _POOL["pool"] is None or _POOL["pid"] != os.getpid() or _POOL["size"] < n_workers:
            _POOL.update(pool=ThreadPoolExecutor(n_workers, thread_name_prefix="rigctl-encode-pool"), size=n_workers,
                         pid=os.getpid())  # (a smaller one left behind finishes its queue and idles)
        return _POOL["pool"]


def on_threads(run: Callable[[int, int], object], n: int, step: int) -> None:
    """``run(i, j)`` over the ranges ``[i, j)`` of ``step`` items that cover ``range(n)``: in this thread when one
    range covers it, else on ``numba.get_num_threads()`` threads (this one and the process's encoder pool's, at
    most one a range), each taking the next range when its last is done. ``run`` calls a ``nogil`` kernel on
    disjoint parts of the output. An exception in ``run`` is raised here once every thread has stopped."""
    todo = iter(range(0, n, step))
    n_threads = min(-(-n // step), numba.get_num_threads())
    if n_threads <= 1 or threading.current_thread().name.startswith("rigctl-encode-pool"):
        run(0, n)  # (a range run from the pool itself runs inline: a nested call never waits on its own pool)
        return
    lock = threading.Lock()

    def worker() -> None:
        while True:
            with lock:
                i = next(todo, None)
            if i is None:
                return
            run(i, min(i + step, n))

    futures = [_pool(n_threads - 1).submit(worker) for _ in range(n_threads - 1)]
    try:
        worker()
    finally:
        for f in futures:
            f.result()


def _claiming(kernel, args, i: int, j: int) -> None:
    """One thread's run of a kernel that claims its own work units (:func:`~rigctl.encoding.llvm_ops.claim`)."""
    kernel(*args)


def _on_claiming_threads(kernel, args: tuple[object, ...], n_units: int) -> None:
    """``kernel(*args)`` once on each of up to ``numba.get_num_threads()`` threads (:func:`on_threads`), at most one a
    unit: one dispatch a thread, where a range a call cost one each (~10-30 us of the GIL a block)."""
    on_threads(partial(_claiming, kernel, args), min(n_units, numba.get_num_threads()), 1)


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
              cutoff_hz: float = RA_CUTOFF_HZ, rectify: bool = True, fs: float = MODEL_RATE_HZ,
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
    lengths = np.ascontiguousarray(np.diff(starts))
    act = np.ones(n_trials, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    order = np.flatnonzero(act & (lengths > 0))
    order = order[np.argsort(lengths[order], kind="stable")]
    counts = np.zeros((n_pop, n_trials, n_ch), dtype=np.int64)
    n_words = (int(lengths.max(initial=0)) + WORD - 1) // WORD
    bits = np.empty((n_pop, n_trials * n_ch if want_times else 0, max(n_words, 1)), dtype=np.uint32)
    args = (off, scl, gains, bool(ra), off64.astype(rdt), scl64.astype(rdt), rdt.type(k_ra), bq, rdt.type(fs),
            bool(rectify), np.array([a, b, c, d, v_peak], dtype=rdt), state.v, state.u, state.filt, state.fresh, counts,
            bits, int(block), dt.type(a), dt.type(b), dt.type(c), dt.type(d), dt.type(v_peak), np.zeros(1, np.int64))
    _on_claiming_threads(_fused, (x, starts, order, *args), -(-order.size // int(block)))
    if not want_times:
        return FusedResult((), None, counts)
    n0a = np.array(np.broadcast_to(np.asarray(n0, np.int64), (n_trials,)))  # a copy: writable, one kernel signature
    ends = np.zeros((n_pop, n_trials + 1), np.int64)  # population p's trial t: out[ends[p, t]:ends[p, t + 1]]
    ends[:, 1:] = np.cumsum(counts.sum(axis=2).ravel()).reshape(n_pop, n_trials)
    ends[1:, 0] = ends[:-1, -1]
    out = np.empty(int(ends[-1, -1]), dtype=np.float64)  # (every population's times: one array, one decode round)
    _on_claiming_threads(decode_times, (bits, counts, lengths, n0a, 1.0 / float(fs), out, ends, int(block),
                                        np.zeros(1, np.int64)), n_pop * -(-n_trials // int(block)))
    trains = [SpikeTrains.from_counts(out[ends[p, 0]:ends[p, -1]], counts[p]) for p in range(n_pop)]
    return FusedResult(tuple(trains[:n_sa]), trains[n_sa] if ra else None, counts)


def kernels_cached() -> bool:
    """True when numba's on-disk cache holds the fused kernels (encoding starts at once); False when the first
    encoding of this installation must compile them first (seconds). Best effort: True when it cannot tell."""
    try:
        kernels: tuple[Any, ...] = (_fused, decode_times)
        return all(os.path.exists(k._cache._cache_file._index_path) for k in kernels)
    except AttributeError:  # another numba: do not claim a compile that may not happen
        return True
