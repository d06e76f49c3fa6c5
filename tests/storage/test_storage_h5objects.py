"""rigctl.storage.h5objects makes the same HDF5 objects as h5py's high-level API (types, values, filters) and reads
attributes as it does."""

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


def _as_h5py_reads(obj) -> dict:
    """``obj.attrs.items()`` with bytes decoded and numpy scalars made Python ones: what read_attrs must give."""
    out = {}
    for k, v in obj.attrs.items():
        out[k] = v.decode() if isinstance(v, bytes) else v.item() if isinstance(v, np.generic) else v
    return out


def test_read_attrs_gives_what_h5py_gives(tmp_path):
    """The fast readings (scalar numbers of every width, h5py's booleans, UTF-8 strings) and the h5py ones (ASCII
    and fixed-length strings, arrays, an empty attribute, another enum, a uint64 beyond int64) agree with h5py's
    ``attrs.items()`` in value, Python type and order, on a group, a dataset and the file's root."""
    other_enum = h5py.enum_dtype({"RED": 0, "GREEN": 1}, basetype="u1")
    with h5py.File(tmp_path / "a.h5", "w") as f:
        g, ds = f.create_group("g"), f.create_dataset("d", data=np.zeros(3))
        for obj in (f, g, ds):
            h5objects.set_attrs(obj, VALUES)
            obj.attrs["u64_big"] = np.uint64(2**63 + 5)
            obj.attrs["u8"] = np.uint8(200)
            obj.attrs.create("ascii", np.array(b"plain", dtype=h5py.string_dtype("ascii")))
            obj.attrs.create("fixed", np.array(b"fixed", dtype="S8"))
            obj.attrs["nothing"] = h5py.Empty("f8")
            obj.attrs.create("colour", 1, dtype=other_enum)
            obj.attrs["strings"] = ["a", "bc"]
            obj.attrs["f16"] = np.float16(0.5)
    with h5py.File(tmp_path / "a.h5", "r") as f:
        for obj in (f, f["g"], f["d"]):
            got, want = h5objects.read_attrs(obj), _as_h5py_reads(obj)
            assert list(got) == list(want) and len(got) == len(VALUES) + 8
            for k in want:
                assert type(got[k]) is type(want[k]), (obj.name, k, got[k], want[k])
                assert repr(got[k]) == repr(want[k]), (obj.name, k)


def test_a_members_attribute_read_through_its_group_is_read_attrs_value(tmp_path):
    """member_attr (an attribute opened by the member's name through its group, as Session.trial_counts reads
    each trial's started_utc) gives read_attrs's value and type for every kind of attribute, fast or h5py's, of a
    group and a dataset member; None for an attribute the member does not have; h5py's error for a member that is
    not there (what Session's readers turn into SessionError)."""
    with h5py.File(tmp_path / "a.h5", "w") as f:
        for obj in (f.create_group("t/trial_00001"), f.create_dataset("t/d", data=np.zeros(2))):
            h5objects.set_attrs(obj, VALUES)
            obj.attrs.create("ascii", np.array(b"plain", dtype=h5py.string_dtype("ascii")))
            obj.attrs.create("fixed", np.array(b"fixed", dtype="S8"))
            obj.attrs["nothing"] = h5py.Empty("f8")
    with h5py.File(tmp_path / "a.h5", "r") as f:
        group = f["t"].id
        for member in ("trial_00001", "d"):
            want = h5objects.read_attrs(f["t"][member])
            for k in want:
                got = h5objects.member_attr(group, member.encode(), k.encode())
                assert type(got) is type(want[k]) and repr(got) == repr(want[k]), (member, k)
            assert h5objects.member_attr(group, member.encode(), b"started_utc") is None
        with pytest.raises((KeyError, RuntimeError)):
            h5objects.member_attr(group, b"trial_00002", b"text")


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


def _visit(f, names):
    for name in names:
        h5py.h5a.exists(h5py.h5g.open(f.id, name.encode()), b"status")


def test_a_bounded_metadata_cache_keeps_no_more_than_its_size_and_is_restored(tmp_path):
    """Issue 57 item 5: a cached object header keeps its decoded attributes (~20 kB for a generated trial group,
    the cache counting ~0.6 kB): visiting 24,000 trial groups kept 0.48 GB. Inside the context the cache holds at
    most its size; the file's own configuration comes back on exit."""
    names = [f"g{i}" for i in range(400)]
    with h5py.File(tmp_path / "many.h5", "w") as f:
        for name in names:
            h5objects.set_attrs(f.create_group(name), {k: v for k, v in VALUES.items() if k != "array"} |
                                {"status": "complete"})
    with h5py.File(tmp_path / "many.h5", "r") as f:
        before = f.id.get_mdc_config().max_size
        _visit(f, names)
        assert f.id.get_mdc_size()[2] > 64 * 1024  # unbounded, every header visited stays
    with h5py.File(tmp_path / "many.h5", "r") as f:
        with h5objects.bounded_metadata_cache(f, 64 * 1024):
            _visit(f, names)
            assert f.id.get_mdc_size()[2] <= 64 * 1024
        assert f.id.get_mdc_config().max_size == before



def _file_bytes(values: dict, monkeypatch, *, c_calls: bool) -> bytes:
    import io

    with monkeypatch.context() as m:
        if not c_calls:
            m.setattr(h5objects, "_capi", lambda: None)
        buf = io.BytesIO()
        with h5py.File(buf, "w") as f:
            for i in range(3):
                h5objects.set_attrs(f.create_group(f"g{i}").id, values)
        return buf.getvalue()


def test_the_c_calls_write_the_bytes_h5pys_calls_write(monkeypatch):
    """Issue 57 item 6: Python's str, bool, int and float attributes go to HDF5's C calls directly (h5py's per-call
    work cost as much as HDF5's own: ~0.35 ms of a generated trial's 18 attributes). The file is byte for byte the
    one h5py's low-level calls make, for those values and for the ones left to h5py (an int beyond int64, numpy
    scalars, arrays, bytes); the C calls are really used; what h5py refuses (a str with a NUL, one not encodable in
    UTF-8) is refused with the same error."""
    values = {**VALUES, "huge": 2**64 - 1, "int64_low": -2**63, "int64_high": 2**63 - 1, "bool_int": 1,
              "inf": float("inf")}
    capi = h5objects._capi()
    assert capi is not None  # this platform's h5py has its libhdf5 to call
    calls = []
    with monkeypatch.context() as m:
        m.setattr(capi, "set", lambda *a, _set=capi.set: calls.append(a[1].decode()) or _set(*a))
        fast = _file_bytes(values, monkeypatch, c_calls=True)
    assert sorted(set(calls)) == sorted({"text", "unicode", "empty", "flag", "np_flag", "count", "big", "neg",
                                         "real", "nan", "int64_low", "int64_high", "bool_int", "inf"})
    assert fast == _file_bytes(values, monkeypatch, c_calls=False)
    for bad, error in (("a\0b", ValueError), ("\udc80", UnicodeEncodeError)):
        for c_calls in (True, False):
            with pytest.raises(error):
                _file_bytes({"bad": bad}, monkeypatch, c_calls=c_calls)
