"""rigctl.core.buffers: a large buffer on base pages is an ordinary zero-filled array."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from rigctl.core.buffers import _MAPPED_BYTES, zeroed


@pytest.mark.parametrize("shape", [(0, 18), (3, 18), (_MAPPED_BYTES // 36 + 1, 18), _MAPPED_BYTES // 8 + 5])
def test_zeroed_is_a_writable_zero_array_of_the_shape_asked(shape):
    a = zeroed(shape, np.uint16 if isinstance(shape, tuple) else np.float64)
    want = np.zeros(shape, a.dtype)
    assert a.shape == want.shape and a.flags.c_contiguous and a.flags.writeable
    np.testing.assert_array_equal(a, want)
    a[...] = 7  # every byte writable
    view = a[1:]
    del a
    gc.collect()
    assert view.size == 0 or int(view.ravel()[-1]) == 7  # a view keeps the mapping alive


def test_zeroed_refuses_a_negative_dimension():
    with pytest.raises(ValueError, match="negative"):
        zeroed((-1, 18), np.uint16)
