"""A large buffer allocated once and filled once (the counts the trial validator keeps for the encoder): on the
system's base pages.

numpy asks Linux for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every array of 4 MB or more. On a
machine whose free memory is fragmented (a page cache of the sessions just read), the first touch of a large fresh
array then waits for the kernel to compact memory into 2 MB pages: the validator's ~1 GB of kept counts cost 2.6
CPU-s to fill at paper size, 0.8 on the base pages of an anonymous mapping. Not for buffers made and freed block
after block: there the huge pages freed by one block serve the next at once, 512 times fewer faults (80 blocks of 36
MB: 0.4 CPU-s with numpy's arrays, 2.1 on base pages).
"""

from __future__ import annotations

import mmap

import numpy as np
import numpy.typing as npt

__all__ = ["zeroed"]

#: below this, numpy's own allocation (no huge pages asked for, the allocator's reuse)
_MAPPED_BYTES = 4 << 20


def zeroed(shape: int | tuple[int, ...], dtype: npt.DTypeLike) -> np.ndarray:
    """A zero-filled C-contiguous array of ``shape`` and ``dtype`` (as ``np.zeros``), on base pages when it is
    :data:`_MAPPED_BYTES` or larger (an anonymous memory mapping, freed with the last array viewing it).

    Raises ValueError for a negative dimension (as numpy), MemoryError when the mapping is refused."""
    dt = np.dtype(dtype)
    dims = (shape,) if isinstance(shape, int) else tuple(shape)
    count = int(np.prod(dims, dtype=np.int64))
    if count < 0 or any(d < 0 for d in dims):
        raise ValueError(f"negative dimensions are not allowed: {dims}")
    if count * dt.itemsize < _MAPPED_BYTES:
        return np.zeros(dims, dtype=dt)
    try:
        buf = mmap.mmap(-1, count * dt.itemsize)
    except OSError as exc:
        raise MemoryError(f"cannot map {count * dt.itemsize} bytes: {exc}") from exc
    return np.frombuffer(buf, dtype=dt, count=count).reshape(dims)
