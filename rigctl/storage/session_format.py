"""The session file's format shared by its writer and reader: schema version, the ``/plan`` table, trial status,
errors, attributes and opening the file (``docs/session-format.md``). Public names are re-exported by
:mod:`rigctl.storage.session`."""

from __future__ import annotations

import contextlib
import datetime as _dt
import enum
import errno
import json
import logging
import math
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.errors import describe_error, one_line
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage import journal
from rigctl.storage.h5objects import read_attrs

#: the newest session schema this rigctl reads and writes (docs/session-format.md): 5, schema 4 without the trials'
#: views (the dataset generator's: ~1 ms a trial less to write)
SCHEMA_VERSION = 5
#: the schema :meth:`SessionWriter.create` writes unless asked for another: 4, whose trial groups hold views of their
#: rows (plain h5py reads ``/trials/<id>/taxels``); a recorded session gains nothing from the faster schema 5
DEFAULT_SCHEMA_VERSION = 4
SESSION_KINDS = ("recorded", "simulated-dataset", "fabricslide", "imported")
#: variable-length UTF-8 string (h5py's ``string_dtype``): ``/plan`` texture labels of any length
VLEN_UTF8 = h5py.string_dtype("utf-8")
#: largest ``taxels`` chunk, bytes (one chunk holds up to 65,536 samples of every channel, fewer for wide sensors)
TAXEL_CHUNK_BYTES = 4 << 20

log = logging.getLogger("rigctl.storage.session")  # one logger for the whole format


class TrialStatus(enum.IntEnum):
    """Status of a plan row (stored as ``uint8`` in ``/plan['status']``; the mapping is in the ``status_enum`` attr)."""

    PENDING = 0
    COMPLETE = 1
    FAILED = 2


STATUS_ENUM = {s.name.lower(): int(s) for s in TrialStatus}

#: ``/plan`` row: one per planned trial, in protocol order. ``texture`` is a variable-length UTF-8 string (any
#: label of the session's texture set), ``profile`` fixed-length ASCII (bytes in HDF5).
PLAN_DTYPE = np.dtype(
    [
        ("trial_id", "<u4"),
        ("texture", VLEN_UTF8),
        ("speed_mm_s", "<f4"),  # constant speed; for a ramp the mean surface speed over the trial
        ("force_g", "<f4"),
        ("duration_s", "<f4"),
        ("profile", "S24"),  # profile name, "constant" unless the protocol names velocity profiles
        ("ramp_start_mm_s", "<f4"),  # NaN for a constant-speed trial
        ("ramp_end_mm_s", "<f4"),
        ("repeat", "<u4"),
        ("status", "u1"),
    ]
)
#: rows per ``/plan`` chunk: a status update rewrites one chunk in place (64 rows of ~70 B, about one 4 KiB page), not the
#: whole table, which keeps a commit's in-place writes (``rigctl.storage.journal``) short
PLAN_CHUNK_ROWS = 64
PLAN_FIELDS = tuple(n for n in PLAN_DTYPE.names or () if n != "status")



def taxels_description(layout: SensorLayout) -> dict[str, Any]:
    """Attributes of ``/trials``: what every trial's ``taxels`` hold (NWB TimeSeries terms), stored once per session.

    ``taxels_channels`` is ``layout.describe()`` (e.g. "0-8 top (type I), 9-17 bottom (type II); row-major 3x3, row
    0 leading edge; 1000 Hz, 10-bit"), ``taxels_channel_names`` one name per channel (``layout.channel_labels()``),
    ``taxels_unit`` "ADC counts", ``taxels_conversion`` and ``taxels_resolution`` 1.0 (one count),
    ``taxels_rate_hz`` and ``taxels_adc_bits`` from the layout.
    """
    return {
        "taxels_channels": layout.describe(),
        "taxels_channel_names": np.array(layout.channel_labels(), dtype=VLEN_UTF8),
        "taxels_unit": "ADC counts",
        "taxels_conversion": 1.0,
        "taxels_resolution": 1.0,
        "taxels_rate_hz": float(layout.sample_rate_hz),
        "taxels_adc_bits": int(layout.adc_bits),
        "taxels_starting_time_unit": "seconds since the session's created_utc",
    }


class SessionError(RuntimeError):
    """A session file cannot be created, opened or written as asked (wrong layout, trial already complete, ...), or
    what it holds is malformed (the message names the file, the trial and what is wrong)."""


class SessionLocked(SessionError):
    """Another writer holds the session file (one :class:`SessionWriter` per file at a time, across processes and
    within one). ``pid`` is the holder's process id when known."""

    def __init__(self, message: str, pid: int | None = None) -> None:
        super().__init__(message)
        self.pid = pid


class SessionWriteError(SessionError):
    """The disk refused a write (no space left, a read-only file system, ...). Nothing of the write in progress
    reached the file; every trial written before is intact. ``errno`` is the OS error number, ``intact`` the ids
    of the complete trials."""

    def __init__(self, message: str, errno_: int | None = None, intact: Sequence[int] = ()) -> None:
        super().__init__(message)
        self.errno = errno_
        self.intact = list(intact)


def _id_ranges(ids: Sequence[int]) -> str:
    """``[0, 1, 2, 3, 4, 7]`` -> ``"0-4, 7"``."""
    ids = sorted(int(i) for i in ids)
    parts, start = [], None
    for k, i in enumerate(ids):
        if start is None:
            start = i
        if k + 1 == len(ids) or ids[k + 1] != i + 1:
            parts.append(f"{start}" if start == i else f"{start}-{i}")
            start = None
    return ", ".join(parts)


def _os_error_text(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1)):
        return "no space left on device"
    if exc.errno == errno.EROFS:
        return "read-only file system"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    return exc.strerror or str(exc)




# ----------------------------------------------------------------------------------------------------------------
# Plan helpers
# ----------------------------------------------------------------------------------------------------------------
def _row_value(row: Any, name: str, default: Any = None) -> Any:
    if isinstance(row, Mapping):
        return row.get(name, default)
    if isinstance(row, np.void):
        return row[name] if name in (row.dtype.names or ()) else default
    return getattr(row, name, default)


def plan_array(rows: Iterable[Any]) -> np.ndarray:
    """Build a ``/plan`` table (:data:`PLAN_DTYPE`) from planned trials.

    Parameters
    ----------
    rows : iterable of objects with attributes (e.g. :class:`rigctl.acquisition.protocol.PlannedTrial`), mappings,
        or rows of a structured array, each with ``trial_id, texture, speed_mm_s, force_g, duration_s`` and
        optionally ``profile`` ("constant"), ``ramp_start_mm_s``/``ramp_end_mm_s`` (NaN), ``repeat`` (0),
        ``status`` (pending).

    Raises
    ------
    ValueError if a required field is missing or trial ids repeat.
    """
    rows = list(rows)
    out = np.zeros(len(rows), dtype=PLAN_DTYPE)
    for i, row in enumerate(rows):
        for name in ("trial_id", "texture", "speed_mm_s", "force_g", "duration_s"):
            if _row_value(row, name) is None:
                raise ValueError(f"plan row {i} has no {name!r}")
        tex = _row_value(row, "texture")
        out[i]["trial_id"] = int(_row_value(row, "trial_id"))
        out[i]["texture"] = _text(tex)
        out[i]["speed_mm_s"] = float(_row_value(row, "speed_mm_s"))
        out[i]["force_g"] = float(_row_value(row, "force_g"))
        out[i]["duration_s"] = float(_row_value(row, "duration_s"))
        prof = _row_value(row, "profile", "constant") or "constant"
        out[i]["profile"] = prof.encode() if isinstance(prof, str) else prof
        for name in ("ramp_start_mm_s", "ramp_end_mm_s"):
            v = _row_value(row, name, None)
            out[i][name] = math.nan if v is None else float(v)
        out[i]["repeat"] = int(_row_value(row, "repeat", 0) or 0)
        status = _row_value(row, "status", TrialStatus.PENDING)
        out[i]["status"] = STATUS_ENUM[status] if isinstance(status, str) else int(status)
    if len(np.unique(out["trial_id"])) != len(out):
        raise ValueError("trial ids in the plan must be unique")
    return out


def _text(v: Any) -> str:
    """A plan string field as str (bytes from HDF5 are UTF-8; numpy str scalars become plain str)."""
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def _plan_to_str(plan: np.ndarray) -> np.ndarray:
    """The ``/plan`` table (:data:`PLAN_DTYPE`, or the fixed-length ``S1`` texture of schema 1/2) with numpy str
    fields: ``texture`` as ``U<longest label>``, ``profile`` as ``U24``."""
    cols: dict[str, Any] = {}
    fields: list[tuple[str, Any]] = []
    for name in plan.dtype.names or ():
        col = plan[name]
        if col.dtype.kind in "SO":
            text = [_text(v) for v in col.tolist()]
            width = max([len(t) for t in text], default=1) or 1
            cols[name] = text
            fields.append((name, f"U{max(width, col.dtype.itemsize if col.dtype.kind == 'S' else 1)}"))
        else:
            cols[name] = col
            fields.append((name, col.dtype))
    out = np.zeros(plan.shape, dtype=fields)
    for name, col in cols.items():
        out[name] = col
    return out


def _check_plan_textures(plan: np.ndarray, textures: TextureSet) -> None:
    """Put every plan label in the set's spelling (:meth:`TextureSet.resolve`), in place.

    Raises
    ------
    TextureSetError for a label that is not in the set (the message names the set's labels).
    """
    known: dict[str, str] = {}
    for i, v in enumerate(plan["texture"].tolist()):
        label = _text(v)
        if label not in known:
            known[label] = textures.resolve(label)
        if known[label] != label or not isinstance(v, str):
            plan["texture"][i] = known[label]


def trial_group_name(trial_id: int) -> str:
    """``/trials/<trial_id:06d>``."""
    return f"/trials/{int(trial_id):06d}"


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _parse_utc(text: str) -> _dt.datetime | None:
    try:
        return _dt.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        return None


def _attr_value(value: Any) -> Any:
    """Convert a Python value into something h5py stores as an attribute (dicts/lists of mixed types -> JSON)."""
    if value is None:
        return "null"
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, float, str, np.integer, np.floating)):
        return value
    if isinstance(value, enum.Enum):
        return value.name.lower()
    if isinstance(value, (list, tuple, np.ndarray)):
        arr = np.asarray(value)
        if arr.dtype.kind in "biuf":
            return arr
    return json.dumps(value, default=str)


def _read_attrs(obj: Any) -> dict[str, Any]:
    return read_attrs(obj)


def _open_h5(path: Path, mode: str, *, wait_s: float = 10.0) -> h5py.File:
    """Open ``path`` with h5py, retrying while another process holds the HDF5 file lock (e.g. a writer).

    Raises
    ------
    FileNotFoundError; rigctl.storage.journal.FileBusy (an OSError) if the file stays locked for ``wait_s``;
    SessionError if HDF5 cannot open it (not HDF5, truncated, damaged).
    """
    try:
        journal.recover(path, wait_s=wait_s)  # finish a commit a killed writer left half done
    except PermissionError:
        pass
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return h5py.File(path, mode)
        except FileNotFoundError:
            raise
        except (OSError, ValueError, RuntimeError) as exc:
            locked = isinstance(exc, BlockingIOError) or "unable to lock file" in str(exc).lower()
            if locked and time.monotonic() <= deadline:
                time.sleep(0.05)
                continue
            if locked:
                raise journal.FileBusy(f"{path} is held by another process (a writer, or a reader with the HDF5 "
                                       f"file lock) for more than {wait_s:g} s") from None
            if not path.exists():
                raise FileNotFoundError(f"{path} does not exist") from None
            raise SessionError(f"{path} is not a readable HDF5 file ({_one_line(exc)})") from None


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line, cut at 160 characters (HDF5's messages run long)."""
    return one_line(exc, 160)


def _decode_rig_config(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """The ``rig_config`` root attribute (JSON) as a dict, ``{}`` when absent. Raises ValueError (or TypeError) when
    it is not a JSON object."""
    cfg = json.loads(attrs.get("rig_config", "{}") or "{}")
    if not isinstance(cfg, dict):
        raise ValueError("not a JSON object")
    return cfg



def _read_text(ds: Any) -> str:
    v = ds[()]
    return v.decode() if isinstance(v, bytes) else str(v)


#: the errors h5py, numpy and json raise on a malformed file (what :func:`_reading` turns into SessionError)
_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, IndexError, AttributeError, RuntimeError, OverflowError)


@contextlib.contextmanager
def _reading(path: Path, what: str) -> Iterator[None]:
    """Turn what h5py/numpy/json raise on a malformed file while reading ``what`` into one SessionError naming the
    file and ``what`` (SessionError and FileBusy pass through)."""
    try:
        yield
    except (SessionError, journal.FileBusy):
        raise
    except _READ_ERRORS as exc:
        raise SessionError(f"{path}: cannot read {what} ({describe_error(exc, 160)}); the file is "
                           "damaged or not written by rigctl") from None


#: the root attribute holding the session's event log (a JSON list of objects: the safety policy's latches and
#: acknowledgements, docs/session-format.md)
EVENTS_ATTR = "events"


def decode_events(attrs: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The event log (:data:`EVENTS_ATTR`) of a session's root attributes, oldest first ([] when none)."""
    text = attrs.get(EVENTS_ATTR)
    if text is None:
        return []
    try:
        events = json.loads(text if isinstance(text, str) else bytes(text).decode())
    except ValueError:
        raise SessionError(f"the {EVENTS_ATTR} attribute is not JSON") from None
    return [e for e in events if isinstance(e, dict)] if isinstance(events, list) else []
