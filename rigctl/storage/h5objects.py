"""Fast creation of HDF5 datasets and attributes through h5py's low-level API.

The dataset generator writes tens of thousands of small trial groups; h5py's high-level ``create_dataset`` and
``attrs[...] =`` spend most of their time in Python checks (about 150 us per dataset and 60 us per attribute here),
the HDF5 library itself a third of that. These helpers make the same objects (same HDF5 types: what h5py's
high-level API would store for the value, read back identically by h5py) with the type and dataspace objects built
once. Values of other kinds fall back to the high-level API.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np
from h5py import h5a, h5d, h5g, h5p, h5s, h5t, h5z

_SCALAR = h5s.create(h5s.SCALAR)
_STR = h5py.string_dtype("utf-8")
_TIDS: dict[np.dtype[Any], tuple[Any, Any]] = {}


def _tids(dtype: np.dtype[Any]) -> tuple[Any, Any]:
    """(file type, memory type) for ``dtype``, as h5py's attribute code picks them (logical / bit-for-bit)."""
    tids = _TIDS.get(dtype)
    if tids is None:
        tids = _TIDS[dtype] = (h5t.py_create(dtype, logical=True), h5t.py_create(dtype))
    return tids


def _lowlevel(obj: Any) -> Any:
    return obj.id if isinstance(obj, h5py.HLObject) else obj


class _HasId:
    def __init__(self, oid: Any) -> None:
        self.id = oid


def set_attrs(obj: Any, attrs: Mapping[str, Any]) -> None:
    """Create the attributes ``attrs`` on a new object (group or dataset, high-level or its low-level id) that
    has none of these names yet.

    Python ``str`` -> variable-length UTF-8 string, ``bool``/``np.bool_`` -> h5py's boolean enum, ``int`` ->
    int64, ``float`` -> float64, numpy scalars -> their dtype: the types h5py's ``obj.attrs[name] = value`` stores.
    Anything else (arrays, bytes) goes through ``obj.attrs``.

    Raises
    ------
    OSError (from HDF5: "attribute already exists") if an attribute of that name exists already.
    """
    oid = _lowlevel(obj)
    for name, value in attrs.items():
        if isinstance(value, str):
            arr = np.array(value, dtype=_STR)
        elif isinstance(value, (bool, np.bool_, int, float, np.integer, np.floating)):
            arr = np.asarray(value)
        else:
            h5py.AttributeManager(_HasId(oid))[name] = value  # what h5py's obj.attrs[name] = value does
            continue
        ftype, mtype = _tids(arr.dtype)
        attr = h5a.create(oid, name.encode(), ftype, _SCALAR)
        attr.write(arr, mtype=mtype)


def create_group(parent: Any, name: str) -> h5g.GroupID:
    """Create the group ``name`` (one path component) in ``parent`` (``h5py.Group`` or its low-level id); returns
    the new group's low-level id (``h5py.Group(gid)`` for the high-level API)."""
    return h5g.create(_lowlevel(parent), name.encode())


_DCPLS: dict[tuple[Any, ...], Any] = {}


def _dcpl(chunks: tuple[int, ...] | None, compression: str | None) -> Any:
    key = (chunks, compression)
    dcpl = _DCPLS.get(key)
    if dcpl is None:
        dcpl = h5p.create(h5p.DATASET_CREATE)
        dcpl.set_obj_track_times(False)
        if chunks is not None:
            dcpl.set_chunk(chunks)
            if compression is not None:
                dcpl.set_shuffle()
                if compression == "gzip":
                    dcpl.set_deflate(1)
                else:
                    dcpl.set_filter(h5z.FILTER_LZF, h5z.FLAG_OPTIONAL)
        if len(_DCPLS) > 256:
            _DCPLS.clear()
        _DCPLS[key] = dcpl
    return dcpl


def create_dataset(group: Any, name: str, data: np.ndarray[Any, Any], *, chunks: tuple[int, ...] | None = None,
                   compression: str | None = None) -> h5d.DatasetID:
    """Create dataset ``name`` in ``group`` holding ``data`` (any shape, a numeric dtype), written at once.

    ``group`` is an ``h5py.Group`` or its low-level id. ``chunks`` (a chunk shape) is required for
    ``compression`` ("gzip": level 1 with shuffle; "lzf": with shuffle); an empty ``data`` is stored contiguous
    and uncompressed. No timestamps are stored (as h5py's default). Returns the low-level dataset id (wrap it in
    ``h5py.Dataset`` for the high-level API; :func:`set_attrs` takes it as it is).

    Raises
    ------
    ValueError for an unknown compression.
    """
    if compression not in ("gzip", "lzf", None):
        raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
    data = np.ascontiguousarray(data)
    dcpl = (_dcpl(tuple(int(c) for c in chunks), compression) if data.size and chunks is not None
            else _dcpl(None, None))
    space = h5s.create_simple(data.shape)
    ftype, mtype = _tids(data.dtype)
    dsid = h5d.create(_lowlevel(group), name.encode(), ftype, space, dcpl=dcpl)
    if data.size:
        dsid.write(h5s.ALL, h5s.ALL, data, mtype=mtype)
    return dsid
