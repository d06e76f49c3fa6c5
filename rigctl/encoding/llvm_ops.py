"""LLVM one-instruction operations the encoder's numba kernels share (:mod:`rigctl.encoding.fused`,
:mod:`rigctl.encoding.bitmaps`), and the two IR pieces their explicit-vector intrinsics build with (:func:`splat`,
:func:`vector_at`). numba's on-disk cache knows only the source file of the function it caches: a change here needs
those files' caches cleared (or their files touched), so nothing here is more than an instruction.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["popcount", "claim", "splat", "vector_at"]


@intrinsic
def _ctpop32(typingctx, m):  # pragma: no cover - compiled by numba
    """Set bits of a uint32 (LLVM's ctpop: one popcnt where the CPU has it)."""
    sig = types.uint32(types.uint32)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])
    return sig, codegen


@numba.njit(inline="always", cache=True)
def popcount(m):  # pragma: no cover - compiled by numba
    """Set bits of a uint32, int32."""
    return np.int32(_ctpop32(m))  # type: ignore[call-arg]


@intrinsic
def claim(typingctx, counter):  # pragma: no cover - compiled by numba
    """The next unit of work of a call shared by threads: ``counter[0]`` as it was, one added to it in the same
    atomic step (LLVM's ``atomicrmw add``, monotonic: each value goes to exactly one thread). ``counter``: int64 1-d
    array, 0 at the call's start."""
    sig = types.int64(counter)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        return builder.atomic_rmw("add", data, ir.Constant(ir.IntType(64), 1), "monotonic")
    return sig, codegen


def splat(builder: ir.IRBuilder, x: ir.Value, vty: ir.VectorType) -> ir.Value:
    """Codegen: the vector of type ``vty`` with ``x`` in every lane (an insert and a zero-mask shuffle)."""
    one = builder.insert_element(ir.Constant(vty, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(one, ir.Constant(vty, ir.Undefined),
                                  ir.Constant(ir.VectorType(ir.IntType(32), vty.count), [0] * vty.count))


def vector_at(context, builder: ir.IRBuilder, aty, aval: ir.Value, idx: ir.Value, vty: ir.VectorType) -> ir.Value:
    """Codegen: a pointer to a ``vty`` vector at flat element ``idx`` of the numba array ``aval`` (of type ``aty``,
    C-contiguous: element idx of its data, whatever its dimensions); no bounds check."""
    data = context.make_array(aty)(context, builder, aval).data
    return builder.bitcast(builder.gep(data, [idx]), vty.as_pointer())
