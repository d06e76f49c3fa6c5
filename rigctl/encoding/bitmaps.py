"""Spike bitmaps -> spike times (NWB: seconds from each trial's first sample), for the fused encoder
(:mod:`rigctl.encoding.fused`), which stores each train's spikes as bits of uint32 words (bit i of word w: a spike at
sample ``32 w + i``), and every word's count.

The times are ``(sample + n0) * dt`` (an exact integer sum below 2^53, then one product), written a word at a time
without a branch on the spikes: where the CPU compresses a word's bit numbers by the word in one instruction
(AVX-512 VBMI2's vpcompressb, ``HAS_COMPRESS``) by :func:`word_times`, else a byte at a time from a table of each
byte's set bits (:func:`_byte_times`). Both give the same numbers bit for bit (tests/encoding/test_enc_simd.py).
"""

from __future__ import annotations

import llvmlite.binding as llvm
import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import config
from numba.cpython.unsafe.numbers import trailing_zeros
from numba.extending import intrinsic, overload

from rigctl.encoding.llvm_ops import claim, popcount, splat, vector_at

__all__ = ["WORD", "HAS_COMPRESS", "word_times", "decode_times"]


#: samples a word of a spike bitmap: one bit each (uint32)
WORD = 32


def _bit_positions() -> np.ndarray:
    """For every byte value: the positions of its set bits, ascending, padded with 0 to 8 (float64: exact)."""
    pos = np.zeros((256, 8), np.float64)
    for v in range(256):
        bits = [i for i in range(8) if v >> i & 1]
        pos[v, :len(bits)] = bits
    return pos


_BYTE_POS = _bit_positions()


@intrinsic
def _byte_times(typingctx, out, pos, lut, byte, base, dt):  # pragma: no cover - compiled by numba
    """``out[pos + k] = (base + lut[byte, k]) * dt`` for k < 8, as explicit vector operations (a sum and a product;
    the sum of integer values below 2^53 is exact, so the same numbers as ``(sample) * dt`` of the integer
    sample). ``out`` float64 with at least 8 slots from ``pos``; ``lut`` (256, 8) float64."""
    sig = types.void(out, types.intp, lut, types.intp, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        a_out, a_pos, a_lut, a_byte, a_base, a_dt = args
        t_out, _, t_lut = signature.args[:3]
        vd = ir.VectorType(ir.DoubleType(), 8)
        lut_p = builder.gep(context.make_array(t_lut)(context, builder, a_lut).data,
                            [builder.mul(a_byte, ir.Constant(a_byte.type, 8))])
        k = builder.load(builder.bitcast(lut_p, vd.as_pointer()), align=8)
        t = builder.fmul(builder.fadd(splat(builder, a_base, vd), k), splat(builder, a_dt, vd))
        builder.store(t, vector_at(context, builder, t_out, a_out, a_pos, vd), align=8)
        return context.get_dummy_value()
    return sig, codegen


def _target_has(feature: str) -> bool:
    """True when numba compiles for a CPU with ``feature`` (LLVM's name, e.g. ``avx512vbmi2``): the features numba was
    told to target (``NUMBA_CPU_FEATURES``; ``NUMBA_CPU_NAME=generic``: none), else this machine's, as numba's
    codegen chooses them."""
    told: str | None = getattr(config, "CPU_FEATURES", None)
    features = told if told is not None else llvm.get_host_cpu_features().flatten()
    return f"+{feature}" in features.split(",")


#: the target compresses bytes by a mask in one instruction (AVX-512 VBMI2's vpcompressb): :func:`word_times`
HAS_COMPRESS = _target_has("avx512vbmi2")


@intrinsic
def word_times(typingctx, out, pos, word, base, dt):  # pragma: no cover - compiled by numba
    """``out[pos + k] = (base + b_k) * dt`` for the set bits ``b_0 < b_1 < ...`` of the uint32 ``word``: the bit
    numbers compressed by the word as a mask (one vpcompressb where ``HAS_COMPRESS``), the first 16 widened to
    float64, summed with ``base`` (exact: integers below 2^53) and multiplied by ``dt``, 16 slots written whatever
    the word holds; the next 16 too when it holds more than 16. The same numbers as ``(base + b) * dt`` bit by bit.
    ``out`` float64, 1-d, C-contiguous, with at least 32 slots from ``pos``; base, dt float64."""
    sig = types.void(out, types.intp, types.uint32, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        a_out, a_pos, a_word, a_base, a_dt = args
        i8, i32, f64 = ir.IntType(8), ir.IntType(32), ir.DoubleType()
        v32i8, v16d = ir.VectorType(i8, 32), ir.VectorType(f64, 16)
        mod = builder.module
        fn_ty = ir.FunctionType(v32i8, [v32i8, ir.VectorType(ir.IntType(1), 32), v32i8])
        name = "llvm.experimental.vector.compress.v32i8"
        compress = mod.globals.get(name) or ir.Function(mod, fn_ty, name=name)
        packed = builder.call(compress, [ir.Constant(v32i8, list(range(32))),
                                         builder.bitcast(a_word, ir.VectorType(ir.IntType(1), 32)),
                                         ir.Constant(v32i8, [0] * 32)])
        undef = ir.Constant(v32i8, ir.Undefined)
        base_v, dt_v = splat(builder, a_base, v16d), splat(builder, a_dt, v16d)

        def store(half, at):
            b = builder.shuffle_vector(packed, undef, ir.Constant(ir.VectorType(i32, 16), list(range(16 * half,
                                                                                                  16 * half + 16))))
            t = builder.fmul(builder.fadd(base_v, builder.uitofp(b, v16d)), dt_v)
            builder.store(t, vector_at(context, builder, signature.args[0], a_out, at, v16d), align=8)
        store(0, a_pos)
        n = builder.ctpop(a_word)
        with builder.if_then(builder.icmp_unsigned(">", n, ir.Constant(i32, 16)), likely=False):
            store(1, builder.add(a_pos, ir.Constant(a_pos.type, 16)))
        return context.get_dummy_value()
    return sig, codegen


def _word(out, pos, mm, base, dt):  # pragma: no cover - replaced by the overload below inside numba
    """``out[pos + k] = (base + b_k) * dt`` for the set bits b_k of ``mm``, ascending; writes up to 32 slots."""
    raise NotImplementedError


@overload(_word, inline="always")
def _word_impl(out, pos, mm, base, dt):  # pragma: no cover - compiled by numba
    if HAS_COMPRESS:
        def compressed(out, pos, mm, base, dt):
            word_times(out, pos, mm, np.float64(base), dt)  # type: ignore[call-arg]
        return compressed

    def by_bytes(out, pos, mm, base, dt):  # (each byte's position from the word's lower bytes: one add a word)
        lo = np.uint32(0)
        for i in range(4):
            byte = (mm >> np.uint32(8 * i)) & np.uint32(0xFF)
            _byte_times(out, pos + popcount(mm & lo), _BYTE_POS, byte, np.float64(base + 8 * i), dt)  # type: ignore[call-arg]
            lo = (lo << np.uint32(8)) | np.uint32(0xFF)
    return by_bytes


def _times_py(bits, counts, lens, n0, dt, out, ends, step, counter):  # pragma: no cover - compiled by numba
    """Flat spike times from the spike bitmaps of P populations, trial-major then train within each: row r = t * C + ch
    of ``bits[p]`` (P, T * C, W) holds the words of a trial of ``lens[t]`` samples; time = (sample + n0[t]) * dt;
    population p's trial t goes to ``out[ends[p, t]:ends[p, t + 1]]``. The work is ``step`` trials of one population
    at a time, each claimed from ``counter`` (:func:`~rigctl.encoding.llvm_ops.claim`): every thread of a call runs
    this once, over the units it claims.

    A word is decoded whole where the CPU compresses its bit numbers by the word in one instruction
    (:func:`word_times`: 16 times written whatever the word holds), else a byte at a time from a table of each byte's
    set bits, eight times written at once (:func:`_byte_times`); the position moved on by the word's count: no branch
    on the spikes (a loop over a word's set bits mispredicted its end about once a word, 0-14 spikes a word: most of
    this pass's time). The slots past a word's own spikes take values the next words overwrite, so this runs where
    32 slots of the unit's part of ``out`` are left; its last words bit by bit (another thread may be writing past
    them)."""
    n_pop, n_trials, n_ch = counts.shape
    per_pop = (n_trials + step - 1) // step
    while True:
        unit: int = claim(counter)  # type: ignore[call-arg]
        if unit >= n_pop * per_pop:
            return
        p = unit // per_pop
        i = unit % per_pop * step
        j = min(n_trials, i + step)
        pos = ends[p, i]
        end = ends[p, j]
        for t in range(i, j):
            n_words = (lens[t] + WORD - 1) // WORD
            for ch in range(n_ch):
                if counts[p, t, ch] == 0:
                    continue
                r = t * n_ch + ch
                for w in range(n_words):
                    mm = bits[p, r, w]
                    base = np.int64(w * WORD) + n0[t]
                    if pos + WORD <= end:
                        _word(out, pos, mm, base, dt)
                        pos += popcount(mm)
                    else:
                        while mm:
                            out[pos] = (base + trailing_zeros(mm)) * dt
                            pos += 1
                            mm = mm & (mm - np.uint32(1))


#: (:func:`_times_py`) released GIL: the threads of a call run it side by side
decode_times = numba.njit(cache=True, nogil=True)(_times_py)
