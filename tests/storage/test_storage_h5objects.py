"""rigctl.storage.h5objects makes the same HDF5 objects as h5py's high-level API (types, values, filters)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from rigctl.storage import h5objects

VALUES = {
    "text": "ADC counts", "unicode": "µm → mm", "empty": "", "flag": True, "np_flag": np.bool_(False),
    "count": 3, "big": 2**40, "neg": -7, "real": 1.5, "nan": float("nan"), "f32": np.float32(0.25),
    "u32": np.uint32(7), "i16": np.int16(-3), "array": np.arange(4), "raw": b"bytes",
}


@pytest.mark.parametrize("level", ["high", "low"])
def test_attributes_read_back_like_the_high_level_ones(tmp_path, level):
    with h5py.File(tmp_path / "a.h5", "w") as f:
        fast, ref = f.create_group("fast"), f.create_group("ref")
        h5objects.set_attrs(fast if level == "high" else fast.id, VALUES)
        for k, v in VALUES.items():
            ref.attrs[k] = v
    with h5py.File(tmp_path / "a.h5", "r") as f:
        fast, ref = f["fast"].attrs, f["ref"].attrs
        assert sorted(fast) == sorted(ref) == sorted(VALUES)
        for k in VALUES:
            a, b = fast[k], ref[k]
            assert type(a) is type(b), k
            assert np.asarray(a).dtype == np.asarray(b).dtype, k
            assert f["fast"].attrs.get_id(k).get_type().equal(f["ref"].attrs.get_id(k).get_type()), k
            np.testing.assert_array_equal(a, b, err_msg=k)


def test_an_existing_attribute_is_not_overwritten(tmp_path):
    with h5py.File(tmp_path / "a.h5", "w") as f:
        g = f.create_group("g")
        h5objects.set_attrs(g, {"x": 1})
        with pytest.raises(OSError, match="already exists"):
            h5objects.set_attrs(g, {"x": 2})
        assert g.attrs["x"] == 1


@pytest.mark.parametrize("compression", [None, "gzip", "lzf"])
def test_datasets_hold_the_data_with_the_asked_filters(tmp_path, compression):
    rng = np.random.default_rng(0)
    data = {"taxels": rng.integers(0, 1024, (300, 18)).astype(np.uint16), "t": rng.random(300),
            "flags": rng.integers(0, 16, 300).astype(np.uint8), "empty": np.zeros(0)}
    with h5py.File(tmp_path / "d.h5", "w") as f:
        g = h5objects.create_group(f, "trial")
        for name, arr in data.items():
            chunks = (100,) + arr.shape[1:]
            ds = h5objects.create_dataset(g, name, arr, chunks=chunks, compression=compression)
            assert h5py.Dataset(ds).name == f"/trial/{name}"
    with h5py.File(tmp_path / "d.h5", "r") as f:
        for name, arr in data.items():
            ds = f["trial"][name]
            assert ds.dtype == arr.dtype and ds.shape == arr.shape
            np.testing.assert_array_equal(ds[()], arr)
            if arr.size:
                assert ds.chunks == (100,) + arr.shape[1:]
                assert ds.compression == compression
                assert ds.shuffle == (compression is not None)
            else:
                assert ds.chunks is None
    with h5py.File(tmp_path / "e.h5", "w") as f:
        with pytest.raises(ValueError, match="compression"):
            h5objects.create_dataset(f, "x", np.arange(3), chunks=(3,), compression="zstd")
