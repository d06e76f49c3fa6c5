"""Fast creation of HDF5 datasets and attributes, and reading of attributes, through h5py's low-level API.

The dataset generator writes tens of thousands of small trial groups; h5py's high-level ``create_dataset`` and
``attrs[...] =`` spend most of their time in Python checks (about 150 us per dataset and 60 us per attribute here),
the HDF5 library itself a third of that. These helpers make the same objects (same HDF5 types: what h5py's
high-level API would store for the value, read back identically by h5py) with the type and dataspace objects built
once. Values of other kinds fall back to the high-level API. :func:`read_attrs` reads an object's attributes as the
high-level API gives them, the scalar numbers, booleans and UTF-8 strings without building a numpy dtype for each
(h5py's ``attrs.items()`` spent ~60 us an attribute here, most of it there; a recorded trial's group has 45).
"""

from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator, Mapping
from typing import Any

import h5py
import numpy as np
from h5py import h5a, h5d, h5g, h5o, h5p, h5s, h5t, h5z
from h5py._objects import phil

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


class _CApi:
    """HDF5's own ``H5Acreate2`` / ``H5Awrite`` / ``H5Aclose``, from the libhdf5 h5py itself is linked to (looked up
    through h5py's ``h5a`` extension module, whose dependencies ``dlsym`` searches: the wheel's bundled library or the
    system's, whichever h5py uses), called under h5py's lock. h5py's low-level ``h5a.create`` + ``write`` spent about
    as long again as HDF5 itself on each attribute (making the Python ids, registering them, checking the buffer):
    18 attributes of a generated trial took ~0.6 ms, this ~0.25 ms, the file's bytes the same (test)."""

    def __init__(self) -> None:
        lib = ctypes.CDLL(h5a.__file__)
        self.create = lib.H5Acreate2
        self.create.restype = ctypes.c_int64
        self.create.argtypes = [ctypes.c_int64, ctypes.c_char_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                                ctypes.c_int64]
        self.write = lib.H5Awrite
        self.write.restype = ctypes.c_int
        self.write.argtypes = [ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p]
        self.close = lib.H5Aclose
        self.close.restype = ctypes.c_int
        self.close.argtypes = [ctypes.c_int64]
        # (type id, C value maker) per Python type, the file type also the memory type: h5py's memory type for a
        # str is its own Python-object type, converted by h5py; here the C string is handed over as it is stored
        text, flag, i8, f8 = (h5t.py_create(np.dtype(t), logical=True) for t in (_STR, bool, "<i8", "<f8"))
        self._keep = (_SCALAR, text, flag, i8, f8)  # (the ids stay open while these objects live)
        self.scalar = _SCALAR.id
        self.kinds: dict[type, tuple[int, Any]] = {
            str: (text.id, ctypes.c_char_p), bool: (flag.id, ctypes.c_int8), np.bool_: (flag.id, ctypes.c_int8),
            int: (i8.id, ctypes.c_int64), float: (f8.id, ctypes.c_double)}

    def value(self, value: Any) -> tuple[int, Any] | None:
        """(type id, C value) of ``value`` for the C calls, or None for a value h5py must store (another type, a
        str with a NUL or not encodable in UTF-8, an int outside int64)."""
        kind = self.kinds.get(type(value))
        if kind is None:
            return None
        tid, ctype = kind
        if ctype is ctypes.c_char_p:
            if "\0" in value:
                return None
            try:
                value = value.encode()
            except UnicodeEncodeError:
                return None
        elif ctype is ctypes.c_int64 and not -(1 << 63) <= value < (1 << 63):
            return None
        elif ctype is ctypes.c_int8:
            value = bool(value)  # (np.bool_ too)
        return tid, ctype(value)

    def set(self, oid: Any, name: bytes, tid: int, cvalue: Any) -> bool:
        """Create and write one scalar attribute of the object ``oid`` (a low-level id); False (nothing made) when
        HDF5 refuses to create it (h5py then says why), OSError when it refuses the write (the attribute is
        removed again: the object is as it was)."""
        attr = self.create(oid.id, name, tid, self.scalar, 0, 0)  # (0: H5P_DEFAULT, as h5a.create passes)
        if attr < 0:
            return False
        try:
            written = self.write(attr, tid, ctypes.byref(cvalue)) >= 0
        finally:
            self.close(attr)
        if not written:
            h5a.delete(oid, name)
            raise OSError(f"HDF5 could not write the attribute {name.decode()!r}")
        return True


_CAPI: list[_CApi | None] = []


def _capi() -> _CApi | None:
    """The C calls of :class:`_CApi`, looked up once; None where they cannot be (h5py's path is used then)."""
    if not _CAPI:
        try:
            _CAPI.append(_CApi())
        except (OSError, AttributeError):  # no shared library to load, or without these symbols
            _CAPI.append(None)
    return _CAPI[0]


def set_attrs(obj: Any, attrs: Mapping[str, Any]) -> None:
    """Create the attributes ``attrs`` on a new object (group or dataset, high-level or its low-level id) that
    has none of these names yet.

    Python ``str`` -> variable-length UTF-8 string, ``bool``/``np.bool_`` -> h5py's boolean enum, ``int`` ->
    int64, ``float`` -> float64, numpy scalars -> their dtype: the types h5py's ``obj.attrs[name] = value`` stores.
    Anything else (arrays, bytes) goes through ``obj.attrs``. Python's str, bool, int and float are written by
    HDF5's C calls directly (:class:`_CApi`), the rest through h5py's low-level API.

    Raises
    ------
    OSError (from HDF5: "attribute already exists") if an attribute of that name exists already.
    """
    oid = _lowlevel(obj)
    capi = _capi()
    with phil:
        for name, value in attrs.items():
            if capi is not None:
                fast = capi.value(value)
                if fast is not None and capi.set(oid, name.encode(), *fast):
                    continue
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


_F8, _I8 = h5t.NATIVE_DOUBLE, h5t.NATIVE_INT64
_BOOL = h5t.py_create(np.dtype(bool))
_VLEN_UTF8 = h5t.py_create(_STR)


def _fast_value(oid: Any, name: bytes, obj_name: bytes = b".") -> Any:
    """The value of the attribute ``name`` (of ``oid``'s member ``obj_name``) when it is a scalar integer (int64 or
    narrower), float, h5py boolean or variable-length UTF-8 string, as Python's int, float, bool or str;
    :data:`_OTHER` otherwise."""
    attr = h5a.open(oid, name, obj_name=obj_name)
    if attr.get_space().get_simple_extent_type() != h5s.SCALAR:
        return _OTHER
    tid = attr.get_type()
    cls = tid.get_class()
    if cls == h5t.FLOAT:
        buf = np.empty((), np.float64)
        attr.read(buf, mtype=_F8)
        return float(buf)
    if cls == h5t.INTEGER and (tid.get_size() < 8 or tid.get_sign() == h5t.SGN_2):
        ibuf = np.empty((), np.int64)
        attr.read(ibuf, mtype=_I8)
        return int(ibuf)
    if cls == h5t.ENUM and tid.get_nmembers() == 2 and tid.get_super().get_size() == 1 and \
            [(tid.get_member_name(i), tid.get_member_value(i)) for i in (0, 1)] == [(b"FALSE", 0), (b"TRUE", 1)]:
        bbuf = np.empty((), np.bool_)
        attr.read(bbuf, mtype=_BOOL)
        return bool(bbuf)
    if cls == h5t.STRING and tid.is_variable_str() and tid.get_cset() == h5t.CSET_UTF8:
        obuf = np.empty((), object)
        attr.read(obuf, mtype=_VLEN_UTF8)
        raw = obuf[()]
        return raw.decode() if isinstance(raw, bytes) else raw
    return _OTHER


_OTHER = object()


def member_attr(group: h5g.GroupID, member: bytes, name: bytes) -> Any:
    """The attribute ``name`` of the object ``member`` of ``group`` (low-level ids and names), as
    :func:`read_attrs` gives it (bytes decoded, numpy scalars made Python ones), or None when it has none. The
    attribute is opened through the group by the member's name (``H5Aopen_by_name``): no id is made for the member
    (reading one attribute of each of 24,000 trial groups: 0.55x the CPU of opening each group and reading its
    ``attrs``, measured).

    Raises
    ------
    What h5py raises for a member or attribute that cannot be read (KeyError, OSError, ...: a damaged file).
    """
    if not h5a.exists(group, name, obj_name=member):
        return None
    value = _fast_value(group, name, member)
    if value is _OTHER:
        value = _plain(h5py.AttributeManager(_HasId(h5o.open(group, member)))[name.decode()])
    return value


def _plain(value: Any) -> Any:
    """An attribute's value as h5py read it, with bytes decoded and numpy scalars made Python ones (arrays as
    they are): what :func:`read_attrs` and :func:`member_attr` give where :func:`_fast_value` cannot."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def read_attrs(obj: h5py.HLObject) -> dict[str, Any]:
    """The attributes of ``obj`` (an h5py group, dataset or file), in h5py's order, as ``obj.attrs.items()`` gives
    them with bytes decoded and numpy scalars made Python ones (str, int, float, bool; arrays stay numpy arrays).

    Raises
    ------
    What h5py raises for an attribute that cannot be read (OSError, KeyError, ...: a damaged file).
    """
    mgr = obj.attrs
    oid = obj["/"].id if isinstance(obj, h5py.File) else obj.id
    out: dict[str, Any] = {}
    for name in mgr:
        try:
            value = _fast_value(oid, name.encode())
        except Exception:  # noqa: BLE001 - anything unusual: h5py's own reading below says what
            value = _OTHER
        if value is _OTHER:
            value = _plain(mgr[name])
        out[name] = value
    return out


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


#: the metadata cache's fixed size while many objects are visited (:func:`bounded_metadata_cache`)
VISIT_CACHE_BYTES = 1 << 20


@contextlib.contextmanager
def bounded_metadata_cache(file: Any, nbytes: int | None = None) -> Iterator[None]:
    """Hold the HDF5 metadata cache of ``file`` (an ``h5py.File`` or its low-level id) at a fixed ``nbytes``
    (default :data:`VISIT_CACHE_BYTES`) while
    many objects are visited one after another (each trial group's attributes of a paper-size session), its
    configuration restored on exit.

    HDF5 sizes its cache (adaptively up to 32 MiB) by the objects' bytes on disk, but a cached object header also
    keeps its decoded messages: a generated trial group's header (~0.6 kB on disk, 18 attributes) held ~20 kB of
    memory once its attributes were read, so reading one attribute of each of 24,000 trial groups kept 0.48 GB until
    the file was closed (measured; with 1 MiB: 25 MB, and faster). Objects visited again are read again.
    """
    fid = _lowlevel(file)
    before = fid.get_mdc_config()
    small = fid.get_mdc_config()
    small.set_initial_size = True
    small.initial_size = small.min_size = small.max_size = int(VISIT_CACHE_BYTES if nbytes is None else nbytes)
    small.incr_mode = small.decr_mode = small.flash_incr_mode = 0  # H5C_incr__off, H5C_decr__off, H5C_flash_incr__off
    fid.set_mdc_config(small)
    try:
        yield
    finally:
        fid.set_mdc_config(before)
