"""HDF5 session files: one file per session, one group per trial, written trial by trial (h5py).

The layout is documented in ``docs/session-format.md``. The rules that make a session survive a crash:

- the file is open for writing only while one trial (or, for the dataset generator, one batch) is written:
  :meth:`SessionWriter.write_trial` opens it, writes the whole trial in one go, marks the trial ``complete`` in the
  ``/plan`` table last, flushes and closes it; between trials the file is closed and consistent;
- the default h5py/HDF5 file format is used (no SWMR), so a writer killed with the file closed leaves nothing
  flagged "already open", and plain ``h5py.File(path, "r")`` opens it;
- the ``/plan`` table holds every trial of the protocol with a status (pending / complete / failed), so an
  interrupted session is resumed from it (:meth:`SessionWriter.open`) and no trial is recorded twice.

Every session stores the sensor that recorded it (root attribute ``sensor_layout``: a
:class:`rigctl.core.sensor.SensorLayout` as JSON; it fixes the channel count, the rate and the ADC resolution of
every trial) and its texture set (``texture_set``: a :class:`rigctl.core.textures.TextureSet` as JSON; the plan's
labels are variable-length UTF-8 strings of that set, never truncated; codes are positions in the set). Files of
schema 1 and 2 (written before both attributes existed) open as the paper's sensor with the texture set of their
plan's labels (``docs/session-format.md``, "Older files").

Data flow: acquisition, the dataset generator and the importers write (:class:`SessionWriter`); encoding, analysis,
the GUI and ``rigctl info`` read (:func:`open_session`).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import enum
import errno
import io
import json
import logging
import math
import os
import time
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from h5py import h5a, h5d, h5g, h5s

from rigctl import __version__
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, texture_set_from_labels
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage import h5objects, journal

#: 3: root attributes ``sensor_layout`` and ``texture_set``, ``/plan`` texture as variable-length UTF-8
SCHEMA_VERSION = 3
SESSION_KINDS = ("recorded", "simulated-dataset", "fabricslide", "imported")
#: variable-length UTF-8 string (h5py's ``string_dtype``): ``/plan`` texture labels of any length
VLEN_UTF8 = h5py.string_dtype("utf-8")
#: largest ``taxels`` chunk, bytes (one chunk holds up to 65,536 samples of every channel, fewer for wide sensors)
TAXEL_CHUNK_BYTES = 4 << 20

log = logging.getLogger(__name__)


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
# Trial data
# ----------------------------------------------------------------------------------------------------------------
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
    out = {}
    for k, v in obj.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


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
    """An exception's message on one line, without HDF5's long parenthesised details."""
    text = " ".join(str(exc).split())
    return text if len(text) <= 160 else text[:157] + "..."


@contextlib.contextmanager
def _writing(path: Path, *, durable: bool = True, wait_s: float = 10.0) -> Iterator[h5py.File]:
    """Open ``path`` for writing through a :class:`rigctl.storage.journal.OverlayFile`: HDF5's writes stay in memory
    and are committed (journaled) to disk only after HDF5 has closed the file cleanly; on an exception nothing
    reaches the disk."""
    overlay = journal.OverlayFile(path, durable=durable, wait_s=wait_s)
    try:
        f = h5py.File(overlay, "r+")
        try:
            yield f
        finally:
            f.close()
        overlay.commit()
    finally:
        overlay.close()


def _writer_lock(path: Path) -> journal.WriterLock:
    """The writer lock of ``path`` (:class:`rigctl.storage.journal.WriterLock`). Raises SessionLocked if another
    writer holds it, SessionWriteError if the lock file cannot be made."""
    try:
        return journal.WriterLock(path)
    except journal.WriterLockHeld as exc:
        raise SessionLocked(str(exc), exc.pid) from None
    except OSError as exc:
        raise SessionWriteError(f"cannot write {path}: {_os_error_text(exc)} (making its lock file "
                                f"{journal.lock_path(path).name}); choose a writable place", exc.errno) from None


def _new_file_image(plan_arr: np.ndarray, *, layout: SensorLayout, textures: TextureSet, protocol_source: str,
                    protocol_name: str, protocol_format: str, rig_config: Mapping[str, Any] | None, kind: str,
                    calibration: Mapping[str, Any] | None, attrs: Mapping[str, Any] | None) -> bytes:
    """The bytes of a new session file (root attributes, ``/protocol``, ``/plan``, ``/trials``, ``/calibration``),
    built by HDF5 in memory: HDF5 never writes to a disk that may be full (at a few KiB free it can crash there)."""
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["session_id"] = str(uuid.uuid4())
        f.attrs["created_utc"] = _utc_now()
        f.attrs["rigctl_version"] = __version__
        f.attrs["kind"] = kind
        f.attrs["rig_config"] = json.dumps(dict(rig_config or {}), default=str)
        f.attrs["sensor_layout"] = layout.to_json()
        f.attrs["texture_set"] = textures.to_json()
        for k, v in (attrs or {}).items():
            f.attrs[k] = _attr_value(v)
        g = f.create_group("protocol")
        g.create_dataset("source", data=protocol_source, dtype=h5py.string_dtype("utf-8"))
        g.attrs["name"] = protocol_name
        g.attrs["format"] = protocol_format
        d = f.create_dataset("plan", data=plan_arr, maxshape=(None,), chunks=(PLAN_CHUNK_ROWS,))
        d.attrs["status_enum"] = json.dumps(STATUS_ENUM)
        trials = f.create_group("trials")
        trials.attrs.update(taxels_description(layout))
        if calibration:
            _write_calibration(f, calibration, layout.n_channels)
    return buf.getvalue()


def _write_new_file(path: Path, image: bytes) -> None:
    """Write ``image`` to ``<name>.creating``, fsync it and rename it to ``path`` (which appears complete or not at
    all). A journal of a file being replaced is deleted first (it must never be replayed onto the new one).

    Raises SessionWriteError (nothing left behind) if the disk refuses the bytes (no space, read-only).
    """
    tmp = path.with_name(path.name + ".creating")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0), 0o644)
        try:
            journal._pwrite(fd, image, 0)
            os.fsync(fd)
        finally:
            os.close(fd)
        journal.journal_path(path).unlink(missing_ok=True)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        free = ""
        with contextlib.suppress(OSError):
            st = os.statvfs(path.parent)
            free = f", {st.f_bavail * st.f_frsize / 1024:.0f} KiB free"
        raise SessionWriteError(f"{_os_error_text(exc)} creating {path} ({len(image) / 1024:.0f} KiB needed{free}): "
                                "nothing was written; free space or choose another --out", exc.errno) from None


# ----------------------------------------------------------------------------------------------------------------
# Writer
# ----------------------------------------------------------------------------------------------------------------
def _decode_rig_config(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """The ``rig_config`` root attribute (JSON) as a dict, ``{}`` when absent. Raises ValueError (or TypeError) when
    it is not a JSON object."""
    cfg = json.loads(attrs.get("rig_config", "{}") or "{}")
    if not isinstance(cfg, dict):
        raise ValueError("not a JSON object")
    return cfg


class SessionWriter:
    """Writes a session file trial by trial; the file is open only during each write.

    Create a new file with :meth:`create`, or reopen an interrupted one with :meth:`open` (resume). Then
    :meth:`write_trial` for each recorded trial (or :meth:`mark_failed`), and :meth:`close` (or use it as a context
    manager). From creation/opening to :meth:`close` the writer holds the file's writer lock (an exclusive
    ``flock`` on ``<name>.lock``, :class:`rigctl.storage.journal.WriterLock`): a second writer of the same file, in
    another process or in this one, is refused with :class:`SessionLocked`. HDF5 readers are not locked out between
    writes. The lock dies with the process; a writer that is garbage-collected without :meth:`close` releases it.

    Parameters
    ----------
    path : path of an existing session file (use :meth:`create` / :meth:`open`).
    compression : "gzip" (level 1, shuffle; readable by any HDF5 tool), "lzf" (h5py only) or None.
    durable : fsync the file and the journal at each commit (survives a power cut, not only a killed process).

    Attributes
    ----------
    layout : :class:`rigctl.core.sensor.SensorLayout`, the session's sensor (every trial written must match its
        channel count and rate).
    textures : :class:`rigctl.core.textures.TextureSet`, the session's texture set (every plan label is in it).

    Raises
    ------
    SessionLocked if another writer holds the file; SessionError if the file is not a session (or is malformed:
    see :func:`open_session`), has a newer schema, or is a schema-1/2 import with absent channels
    (``channel_present``: read it with :func:`open_session`; it cannot be appended to); SessionWriteError if the
    lock file cannot be made (a read-only folder).
    """

    def __init__(self, path: str | os.PathLike[str], *, compression: str | None = "gzip", durable: bool = True,
                 _lock: journal.WriterLock | None = None) -> None:
        self._lock = _lock
        self.path = Path(path)
        self.durable = durable
        #: how long a write waits for another process (a reader holding the HDF5 file lock) before FileBusy, s
        self.wait_s = 10.0
        try:
            if compression not in ("gzip", "lzf", None):
                raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
            self.compression = compression
            if self._lock is None:
                self._lock = _writer_lock(self.path)
            with _open_h5(self.path, "r") as f, _reading(self.path, "the session header"):
                contents = _read_session_header(f, self.path)
                self.attrs = contents.attrs
                self.protocol_source = contents.protocol_source
                self._plan = contents.raw_plan
                self.layout, present, self.textures = contents.layout, contents.present, contents.textures
                if present is not None:
                    raise SessionError(f"{self.path} is a schema-{self.attrs.get('schema_version')} import with "
                                       "absent channels (channel_present); it can be read, not appended to: import "
                                       "it again")
                for i, why in contents.unrecorded.items():  # marked complete, no recording: a resume records it
                    self._plan["status"][i] = TrialStatus.PENDING
                    log.warning("%s", why)
        except BaseException:
            self.close()
            raise
        self._created = _parse_utc(self.attrs.get("created_utc", ""))

    # -- lifetime -----------------------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        """True after :meth:`close`: the writer lock is released and nothing more can be written."""
        return self._lock is None or not self._lock.held

    def close(self) -> None:
        """Release the writer lock (idempotent). Every write is on disk already; nothing else happens."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort for writers nobody closed
        try:
            self.close()
        except Exception:
            pass

    @contextlib.contextmanager
    def _commit(self, action: str) -> Iterator[h5py.File]:
        """:func:`_writing` of this writer's file, with the disk's refusals (no space, read-only) turned into a
        :class:`SessionWriteError` that says what is intact and what to do. ``action`` names the write."""
        if self.closed:
            raise SessionError(f"{self.path}: this SessionWriter is closed (open it again to write)")
        before = self._plan["status"].copy()
        try:
            with _writing(self.path, durable=self.durable, wait_s=self.wait_s) as f:
                yield f
        except journal.FileBusy:
            raise
        except OSError as exc:
            self._plan["status"] = before  # nothing of this write reached the file
            done = self.completed_ids()
            intact = (f"trials {_id_ranges(done)} are intact" if done else "no trial was complete before")
            what = _os_error_text(exc)
            hint = ("free space and --resume" if what == "no space left on device" else
                    "make it writable (or copy it to a writable place) and --resume")
            raise SessionWriteError(f"{what} writing {self.path} ({action}): nothing of it was written; {intact}; "
                                    f"{hint}", exc.errno, done) from None

    # -- construction -------------------------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        plan: Iterable[Any] | np.ndarray,
        layout: SensorLayout = PAPER_SENSOR,
        textures: TextureSet | Mapping[str, Any] | None = None,
        protocol_source: str = "",
        protocol_name: str = "",
        protocol_format: str = "toml",
        rig_config: Mapping[str, Any] | None = None,
        kind: str = "recorded",
        calibration: Mapping[str, Any] | None = None,
        attrs: Mapping[str, Any] | None = None,
        overwrite: bool = False,
        compression: str | None = "gzip",
        durable: bool = True,
    ) -> "SessionWriter":
        """Create a new session file with its root attributes, ``/protocol`` and ``/plan``; return its writer.

        Parameters
        ----------
        path : output ``.h5`` file.
        plan : planned trials (see :func:`plan_array`), or a :data:`PLAN_DTYPE` array; may be empty (Python-script
            protocols append rows with :meth:`append_trial`).
        layout : the sensor (:class:`rigctl.core.sensor.SensorLayout`; default the paper's 3x3x2 @ 1 kHz, 10-bit),
            stored as the ``sensor_layout`` root attribute; every trial must match its channel count and rate.
        textures : the texture set (:class:`rigctl.core.textures.TextureSet`, or its ``to_dict`` form), stored as
            the ``texture_set`` root attribute. None: ``texture_set_from_labels`` of the plan's labels (the paper's
            A-P set when all are A-P; for an empty plan the paper's set). Plan labels are stored in the set's
            spelling (:meth:`TextureSet.resolve`).
        protocol_source : the protocol file's text (a resume refuses a different source).
        protocol_name, protocol_format : ``/protocol`` attrs; format is "toml" or "python".
        rig_config : JSON-able mapping stored as the ``rig_config`` root attribute.
        kind : "recorded" | "simulated-dataset" | "fabricslide" | "imported" (``rigctl import``).
        calibration : optional mapping; ``taxel_min``/``taxel_max`` ``(layout.n_channels,)`` arrays go to
            ``/calibration`` datasets, everything else to its attributes.
        attrs : extra root attributes.
        overwrite : replace an existing file (otherwise :class:`FileExistsError`).

        Raises
        ------
        FileExistsError, ValueError (bad kind, plan or calibration shape), TypeError (layout not a SensorLayout),
        rigctl.core.textures.TextureSetError (a plan label not in ``textures``). Nothing is created on any of them.
        """
        path = Path(path)
        if kind not in SESSION_KINDS:
            raise ValueError(f"kind must be one of {SESSION_KINDS}, got {kind!r}")
        if protocol_format not in ("toml", "python", "none"):
            raise ValueError(f"protocol_format must be 'toml', 'python' or 'none', got {protocol_format!r}")
        if not isinstance(layout, SensorLayout):
            raise TypeError(f"layout must be a rigctl.core.sensor.SensorLayout, got {type(layout).__name__}")
        plan_arr = plan.copy() if isinstance(plan, np.ndarray) and plan.dtype == PLAN_DTYPE else plan_array(plan)
        if textures is None:
            labels = [_text(t) for t in plan_arr["texture"].tolist()]
            textures = texture_set_from_labels(labels) if labels else PAPER_TEXTURES
        elif isinstance(textures, Mapping):
            textures = TextureSet.from_dict(textures)
        elif not isinstance(textures, TextureSet):
            raise TypeError(f"textures must be a rigctl.core.textures.TextureSet, got {type(textures).__name__}")
        _check_plan_textures(plan_arr, textures)
        reserved = sorted({"sensor_layout", "texture_set", "schema_version"} & set(attrs or {}))
        if reserved:
            raise ValueError(f"attrs must not set {reserved}: the layout/textures arguments and rigctl set them")
        if calibration:
            _calibration_arrays(calibration, layout.n_channels)  # refuse a wrong shape before creating anything
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; choose another --out, resume it, or remove it")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SessionWriteError(f"cannot create {path}: {_os_error_text(exc)} making its folder "
                                    f"({path.parent}); choose another --out", exc.errno) from None
        lock = _writer_lock(path)  # before anything is written: a file another writer holds is never replaced
        try:
            image = _new_file_image(
                plan_arr, layout=layout, textures=textures, protocol_source=protocol_source,
                protocol_name=protocol_name, protocol_format=protocol_format, rig_config=rig_config, kind=kind,
                calibration=calibration, attrs=attrs)
            _write_new_file(path, image)
            return cls(path, compression=compression, durable=durable, _lock=lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, protocol_source: str | None = None,
             compression: str | None = "gzip", durable: bool = True) -> "SessionWriter":
        """Reopen an interrupted session to resume it.

        Parameters
        ----------
        protocol_source : if given, must equal the stored ``/protocol/source`` text.

        Raises
        ------
        FileNotFoundError, SessionLocked (another writer holds the file), SessionError (not a session file, or the
        protocol source differs).
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist (nothing to resume)")
        writer = cls(path, compression=compression, durable=durable)
        if protocol_source is not None and protocol_source != writer.protocol_source:
            writer.close()
            raise SessionError(
                f"{path}: the protocol differs from the one this session was started with; "
                "resume with the same protocol file, or start a new session"
            )
        return writer

    # -- queries ------------------------------------------------------------------------------------------------
    @property
    def plan(self) -> np.ndarray:
        """The ``/plan`` table as last written by this writer, with numpy str fields (as :attr:`Session.plan`)."""
        return _plan_to_str(self._plan)

    @property
    def rig_config(self) -> dict[str, Any]:
        """The session's ``rig_config`` (as :attr:`Session.rig_config`; ``{}`` when none was stored). Raises
        :class:`SessionError` when the attribute is not a JSON object."""
        try:
            return _decode_rig_config(self.attrs)
        except (TypeError, ValueError) as exc:
            raise SessionError(f"{self.path}: the rig_config attribute is not a JSON object ({_one_line(exc)})") \
                from None

    def completed_ids(self) -> list[int]:
        """Trial ids whose status is complete."""
        return [int(t) for t in self._plan["trial_id"][self._plan["status"] == TrialStatus.COMPLETE]]

    def pending_ids(self) -> list[int]:
        """Trial ids not yet complete (pending or failed), in plan order."""
        return [int(t) for t in self._plan["trial_id"][self._plan["status"] != TrialStatus.COMPLETE]]

    def next_trial_id(self) -> int:
        """One more than the largest trial id in the plan (0 for an empty plan)."""
        return int(self._plan["trial_id"].max()) + 1 if len(self._plan) else 0

    def _row_index(self, trial_id: int) -> int:
        idx = np.flatnonzero(self._plan["trial_id"] == int(trial_id))
        if idx.size == 0:
            raise SessionError(f"trial {trial_id} is not in the plan of {self.path}")
        return int(idx[0])

    # -- writing ------------------------------------------------------------------------------------------------
    def write_trial(self, trial_id: int, data: TrialData) -> None:
        """Write one trial in one go, mark it complete in ``/plan``, commit it to disk (journaled) and close the file.

        Raises
        ------
        SessionError if the trial is not in the plan or is already complete (in this writer's plan or in the file's:
        no trial is recorded twice, a complete recording is never replaced), if ``data.layout`` differs from the
        session's :attr:`layout` in channel count or sample rate, or if the writer is closed.
        SessionWriteError (a SessionError) if the disk refuses the write (no space left, read-only): nothing of
        this trial was written, every trial written before is intact (the message names them).
        rigctl.storage.journal.FileBusy (an OSError) if another process or a :class:`Session` holds the file open
        for longer than :attr:`wait_s`; nothing was written then and the call can be repeated.
        """
        i = self._row_index(trial_id)
        if self._plan["status"][i] == TrialStatus.COMPLETE:
            raise SessionError(f"trial {trial_id} is already complete in {self.path}")
        self.write_trials([(trial_id, data)])

    def write_trials(self, items: Iterable[tuple[int, TrialData]]) -> int:
        """Write several trials during one opening of the file; returns how many.

        For the dataset generator, where opening the file per trial would dominate. Same checks as
        :meth:`write_trial`. The batch reaches the disk in one journaled commit when the last trial is written: a
        crash before that loses the whole batch (the file stays as it was), never part of a trial.
        """
        before = self._plan["status"].copy()
        written = []
        try:
            with self._commit("writing trials") as f:
                self._adopt_file_status(f)
                before = self._plan["status"].copy()
                for trial_id, data in items:
                    i = self._row_index(trial_id)
                    if self._plan["status"][i] == TrialStatus.COMPLETE:
                        raise SessionError(f"trial {trial_id} is already complete in {self.path}")
                    self._check_trial_layout(trial_id, data)
                    self._write_group(f, self._plan[i], data)
                    self._plan["status"][i] = TrialStatus.COMPLETE
                    written.append(i)
                if written:  # the plan's statuses last, in one write of the span they cover (only the status
                    lo, hi = min(written), max(written) + 1  # field: the labels' heap objects stay as they are)
                    f["plan"][lo:hi, "status"] = self._plan["status"][lo:hi]
        except journal.CommittedInterrupt:
            raise  # a Ctrl-C during the commit, which was completed first: the batch is on disk
        except BaseException:
            self._plan["status"] = before  # nothing of the batch reached the file
            raise
        return len(written)

    def append_trial(self, planned: Any, data: TrialData | None = None) -> int:
        """Append a row to ``/plan`` (for Python-script protocols) and, if ``data`` is given, write the trial.

        ``planned`` is a planned trial as in :func:`plan_array`; a ``trial_id`` of None takes :meth:`next_trial_id`.
        Returns the trial id.
        """
        row = plan_array([_with_id(planned, self.next_trial_id())])
        _check_plan_textures(row, self.textures)  # TextureSetError for a label outside the session's set
        if row["trial_id"][0] in self._plan["trial_id"]:
            raise SessionError(f"trial {int(row['trial_id'][0])} is already in the plan of {self.path}")
        if self._plan.dtype != PLAN_DTYPE:  # a schema-1/2 file: fixed-length labels
            width = self._plan.dtype["texture"].itemsize
            if len(row["texture"][0].encode()) > width:
                raise SessionError(f"{self.path} (schema {self.attrs.get('schema_version')}) stores texture labels of "
                                   f"at most {width} byte(s); {row['texture'][0]!r} does not fit")
            row = np.array([tuple(_text(v).encode() if isinstance(v, str) else v for v in row[0].tolist())],
                           dtype=self._plan.dtype)
        with self._commit("appending a plan row") as f:
            ds = f["plan"]
            if ds.shape != (len(self._plan),):
                raise SessionError(f"the plan of {self.path} has {ds.shape[0]} rows, this writer knows "
                                   f"{len(self._plan)}: another writer changed it; open the file again")
            ds.resize((len(self._plan) + 1,))
            ds[len(self._plan)] = row[0]
            f.flush()
        self._plan = np.concatenate([self._plan, row])
        row = row[0]
        if data is not None:
            self.write_trial(int(row["trial_id"]), data)
        return int(row["trial_id"])

    def mark_failed(self, trial_id: int, reason: str = "") -> None:
        """Mark a trial failed in ``/plan`` (it stays eligible for a resume) and store the reason.

        The reason goes to ``/trials/<id>`` attrs (``status`` = "failed", ``error``), a group without datasets.
        """
        i = self._row_index(trial_id)
        if self._plan["status"][i] == TrialStatus.COMPLETE:
            raise SessionError(f"trial {trial_id} is already complete in {self.path}")
        with self._commit(f"marking trial {trial_id} failed") as f:
            self._adopt_file_status(f)
            if self._plan["status"][i] == TrialStatus.COMPLETE:
                raise SessionError(f"trial {trial_id} is already complete in {self.path}")
            name = trial_group_name(trial_id)
            if name in f:
                self._refuse_complete_group(f[name], trial_id)
                del f[name]
            g = f.create_group(name)
            g.attrs["status"] = "failed"
            g.attrs["error"] = str(reason)
            g.attrs["failed_utc"] = _utc_now()
            f["plan"][i:i + 1, "status"] = np.array([TrialStatus.FAILED], dtype=self._plan.dtype["status"])
            f.flush()
        self._plan["status"][i] = TrialStatus.FAILED

    def set_calibration(self, calibration: Mapping[str, Any]) -> None:
        """Write (replace) the ``/calibration`` block.

        Raises ValueError if ``taxel_min``/``taxel_max`` are not ``(layout.n_channels,)``.
        """
        _calibration_arrays(calibration, self.layout.n_channels)
        with self._commit("writing the calibration") as f:
            _write_calibration(f, calibration, self.layout.n_channels)

    def _adopt_file_status(self, f: h5py.File) -> None:
        """Take the file's ``/plan`` statuses, not only this writer's memory, as the truth about what is complete: a
        trial the file holds complete (with its recording) is complete here too, so it is refused, never recorded
        twice. Raises SessionError if the file's plan is not the one this writer read (rows or ids differ)."""
        try:
            rows = f["plan"].fields(["trial_id", "status"])[()]
        except (KeyError, ValueError, OSError) as exc:
            raise SessionError(f"{self.path}: cannot read /plan ({_one_line(exc)})") from None
        if rows.shape != self._plan.shape or not np.array_equal(rows["trial_id"], self._plan["trial_id"]):
            raise SessionError(f"the plan of {self.path} is not the one this writer read (another writer changed "
                               "it); open the file again")
        newly = np.flatnonzero((rows["status"] == TrialStatus.COMPLETE) & (self._plan["status"] != TrialStatus.COMPLETE))
        if newly.size:
            trials = f["trials"]
            for i in newly:
                name = f"{int(self._plan['trial_id'][i]):06d}"
                if name in trials and _group_status(trials[name]) == "complete":
                    self._plan["status"][i] = TrialStatus.COMPLETE

    def _refuse_complete_group(self, group: h5py.Group, trial_id: int) -> None:
        """A trial's group is replaced only when it holds no complete recording (a failed attempt)."""
        if _group_status(group) == "complete":
            raise SessionError(f"trial {trial_id}: {self.path} already holds a complete recording of it; refusing "
                               "to overwrite it (no trial is recorded twice)")

    def _check_trial_layout(self, trial_id: int, data: TrialData) -> None:
        mine, theirs = self.layout, data.layout
        if theirs.n_channels != mine.n_channels or theirs.sample_rate_hz != mine.sample_rate_hz:
            raise SessionError(
                f"trial {trial_id}: its sensor ({theirs.shape_text}, {theirs.n_channels} channels at "
                f"{theirs.sample_rate_hz:g} Hz) differs from the session's ({mine.shape_text}, {mine.n_channels} "
                f"channels at {mine.sample_rate_hz:g} Hz) in {self.path}")

    def _write_group(self, f: h5py.File, row: np.void, data: TrialData) -> None:
        # h5objects: the same objects as h5py's high-level API, without its per-object Python overhead (the
        # dataset generator writes tens of thousands of trials)
        name = trial_group_name(int(row["trial_id"]))
        trials = f["trials"].id
        short = name.rsplit("/", 1)[1]
        if trials.links.exists(short.encode()):  # a failed earlier attempt (never a complete recording)
            self._refuse_complete_group(f[name], int(row["trial_id"]))
            del f[name]
        g = h5objects.create_group(trials, short)
        n = data.n_samples
        layout = self.layout
        n_ch = layout.n_channels
        chunk_rows = max(1, min(n, 65536, TAXEL_CHUNK_BYTES // (2 * n_ch)))
        comp = self.compression if n else None
        tax = h5objects.create_dataset(g, "taxels", data.taxels, chunks=(chunk_rows, n_ch), compression=comp)
        started = _parse_utc(str(data.attrs.get("started_utc", "")))
        starting_time = (started - self._created).total_seconds() if started and self._created else 0.0
        h5objects.set_attrs(tax, {"rate_hz": layout.sample_rate_hz, "unit": "ADC counts", "adc_bits": layout.adc_bits,
                                  "starting_time": starting_time})
        for key in ("seq", "flags", "host_time_s"):
            h5objects.create_dataset(g, key, getattr(data, key), chunks=(chunk_rows,), compression=comp)
        for key in ("force_g", "force_time_s", "speed_mm_s", "speed_time_s"):
            h5objects.create_dataset(g, key, getattr(data, key))
        attrs = {}
        for fld in PLAN_FIELDS:
            v = row[fld]
            attrs[fld] = _text(v) if isinstance(v, (bytes, str)) else v.item()
        for k, v in data.attrs.items():
            if k not in ("status", "trial_id"):
                attrs[k] = _attr_value(v)
        attrs.update(n_samples=n, dropped_frames=data.dropped_frames, crc_errors=data.crc_errors)
        attrs.setdefault("started_utc", "")
        attrs["status"] = "complete"
        h5objects.set_attrs(g, attrs)


def _with_id(planned: Any, default_id: int) -> Any:
    if _row_value(planned, "trial_id") is not None:
        return planned
    if isinstance(planned, Mapping):
        return {**planned, "trial_id": default_id}
    values = {n: _row_value(planned, n) for n in PLAN_DTYPE.names or ()}
    values["trial_id"] = default_id
    return {k: v for k, v in values.items() if v is not None}


def _calibration_arrays(calibration: Mapping[str, Any], n_channels: int) -> dict[str, Any]:
    """``taxel_min``/``taxel_max`` of ``calibration`` as float64 arrays. Raises ValueError unless ``(n_channels,)``."""
    out = {}
    for k in ("taxel_min", "taxel_max"):
        if k in calibration:
            arr = np.asarray(calibration[k], dtype=np.float64)
            if arr.shape != (n_channels,):
                raise ValueError(f"calibration {k} must have shape ({n_channels},) (one value per channel of the "
                                 f"session's sensor), got {arr.shape}")
            out[k] = arr
    return out


def _write_calibration(f: h5py.File, calibration: Mapping[str, Any], n_channels: int) -> None:
    arrays = _calibration_arrays(calibration, n_channels)
    if "calibration" in f:
        del f["calibration"]
    g = f.create_group("calibration")
    for k, v in calibration.items():
        if k in arrays:
            g.create_dataset(k, data=arrays[k]).attrs["unit"] = "ADC counts"
        else:
            g.attrs[k] = _attr_value(v)


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
        raise SessionError(f"{path}: cannot read {what} ({type(exc).__name__}: {_one_line(exc)}); the file is "
                           "damaged or not written by rigctl") from None


def _group_status(group: Any) -> str:
    """The ``status`` attribute of a trial group as str ("" when absent or unreadable)."""
    try:
        v = group.attrs.get("status", "")
    except _READ_ERRORS:
        return ""
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _check_file(f: h5py.File, path: Path) -> None:
    with _reading(path, "the file's top level"):
        missing = [k for k in ("plan", "trials", "protocol") if k not in f]
        has_version = "schema_version" in f.attrs
    _check_top(f, path, missing, has_version)


def _check_top(f: h5py.File, path: Path, missing: list[Any], has_version: bool) -> None:
    if missing or not has_version:
        raise SessionError(f"{path} is not a rigctl session file (missing {missing or ['schema_version']})")
    with _reading(path, "the schema_version attribute"):
        version = int(np.asarray(f.attrs["schema_version"]).reshape(-1)[0])
    if version > SCHEMA_VERSION:
        raise SessionError(f"{path} has schema_version {version}, newer than this rigctl ({SCHEMA_VERSION})")
    for name, kind in (("plan", h5py.Dataset), ("trials", h5py.Group), ("protocol", h5py.Group)):
        with _reading(path, f"/{name}"):
            ok = isinstance(f.get(name), kind)
        if not ok:
            raise SessionError(f"{path}: /{name} is not an HDF5 {kind.__name__.lower()}; not a rigctl session file")


#: ``/plan`` fields every reader relies on (schema 1-3)
_PLAN_REQUIRED = ("trial_id", "texture", "speed_mm_s", "force_g", "duration_s", "status")


def _check_plan(plan: np.ndarray, path: Path) -> None:
    """Refuse a ``/plan`` that cannot be read unambiguously: not a table of one row per trial, a required field
    missing, a trial id listed twice, a status outside ``status_enum``. Raises SessionError naming the problem."""
    names = plan.dtype.names or ()
    missing = [k for k in _PLAN_REQUIRED if k not in names]
    if plan.ndim != 1 or missing:
        raise SessionError(f"{path}: /plan is not a plan table ({'missing ' + ', '.join(missing) if missing else f'{plan.ndim}-d'})")
    for k in ("trial_id", "status"):
        if plan.dtype[k].kind not in "iu":
            raise SessionError(f"{path}: /plan field {k!r} is {plan.dtype[k]}, not an integer")
    ids = plan["trial_id"].astype(np.int64)
    if ids.size and ids.min() < 0:
        raise SessionError(f"{path}: /plan holds a negative trial id ({int(ids.min())})")
    uniq, counts = np.unique(ids, return_counts=True)
    if uniq.size != ids.size:
        dup = uniq[counts > 1]
        raise SessionError(f"{path}: /plan lists trial {int(dup[0])} {int(counts[counts > 1][0])} times"
                           f"{f' (and {dup.size - 1} more ids twice or more)' if dup.size > 1 else ''}; a trial id "
                           "must be unique (the file is damaged or was edited): refusing to read it")
    bad = ~np.isin(plan["status"], [int(st) for st in TrialStatus])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SessionError(f"{path}: /plan gives trial {int(ids[i])} the unknown status {int(plan['status'][i])} "
                           f"(known: {STATUS_ENUM})")


@dataclass
class _Header:
    """What :func:`_read_session_header` reads: everything but the trials."""

    attrs: dict[str, Any]
    protocol_source: str
    raw_plan: np.ndarray
    layout: SensorLayout
    present: np.ndarray | None
    textures: TextureSet
    #: plan row index -> warning, for rows marked complete whose ``/trials/<id>`` group does not exist
    unrecorded: dict[int, str]


def _read_session_header(f: h5py.File, path: Path) -> _Header:
    """Read and check a session's root attributes, ``/protocol/source`` and ``/plan`` (for the reader and the
    writer alike), and find the plan rows marked complete that have no recording.

    Raises SessionError for anything malformed (:func:`_check_file`, :func:`_check_plan`, unreadable attributes,
    a malformed ``sensor_layout`` / ``texture_set``).
    """
    _check_file(f, path)
    with _reading(path, "/plan"):
        raw_plan = f["plan"][()]
    _check_plan(raw_plan, path)
    with _reading(path, "the root attributes"):
        attrs = _read_attrs(f)
    with _reading(path, "/protocol/source"):
        source = _read_text(f["protocol/source"])
    with _reading(path, "the sensor layout / texture set"):
        layout, present, textures = _file_sensor(attrs, raw_plan, path)
    with _reading(path, "the /trials group"):
        recorded = set(f["trials"].keys())
    unrecorded = {}
    for i in np.flatnonzero(raw_plan["status"] == TrialStatus.COMPLETE):
        tid = int(raw_plan["trial_id"][i])
        if f"{tid:06d}" not in recorded:
            unrecorded[int(i)] = (f"{path}: trial {tid} is marked complete in /plan but has no recording "
                                  f"(/trials/{tid:06d} is missing); it is treated as pending (a --resume records it)")
    return _Header(attrs, source, raw_plan, layout, present, textures, unrecorded)


def _legacy_layout(attrs: Mapping[str, Any], present: np.ndarray) -> SensorLayout:
    """The sensor of a schema-1/2 file whose ``channel_present`` marks only some of its 18 columns as real (the
    FabricSlide import: 16 of 18): one row of the present channels, named ``channel<k+1>`` after their column
    (FabricSlide's ``channel1`` ... ``channel16``), 1 kHz, 10-bit (those files were always resampled to that)."""
    idx = np.flatnonzero(present)
    fabricslide = str(attrs.get("kind", "")) == "fabricslide"
    return SensorLayout.grid(
        1, len(idx), 1, sample_rate_hz=PAPER_SENSOR.sample_rate_hz, adc_bits=PAPER_SENSOR.adc_bits,
        layer_names=("taxels",), receptors=("",), channel_names=[f"channel{int(k) + 1}" for k in idx],
        name=(f"FabricSlide CPM-Finger ({len(idx)} taxels)" if fabricslide
              else f"{len(idx)} present channels of {len(present)}"))


def _file_layout(attrs: Mapping[str, Any]) -> tuple[SensorLayout, np.ndarray | None]:
    """``(layout, present)``: the file's sensor and, for a schema-1/2 file with absent channels, the indices of the
    stored columns that are real (else None).

    Schema 3: the ``sensor_layout`` attribute. Schema 1/2: the paper's sensor (all those files hold 18 columns at
    1 kHz, 10-bit), unless a ``channel_present`` root attribute marks some of the 18 columns absent (FabricSlide
    imports): then :func:`_legacy_layout` of the present ones, and readers drop the absent columns.
    """
    text = attrs.get("sensor_layout")
    if text:
        layout = SensorLayout.from_json(text)
        return (PAPER_SENSOR if layout == PAPER_SENSOR else layout), None
    present = attrs.get("channel_present")
    if present is not None:
        present = np.asarray(present).astype(bool).reshape(-1)
        if present.size == PAPER_SENSOR.n_channels and present.any() and not present.all():
            return _legacy_layout(attrs, present), np.flatnonzero(present)
    return PAPER_SENSOR, None


def _file_textures(attrs: Mapping[str, Any], plan: np.ndarray) -> TextureSet:
    """Schema 3: the ``texture_set`` attribute; schema 1/2: ``texture_set_from_labels`` of the plan's labels (the
    paper's A-P set when all are A-P or the plan is empty). The paper's set is returned as :data:`PAPER_TEXTURES`
    itself (as the paper's sensor as :data:`PAPER_SENSOR`), so identity checks downstream hold."""
    text = attrs.get("texture_set")
    if text:
        textures = TextureSet.from_json(text)
        return PAPER_TEXTURES if textures == PAPER_TEXTURES else textures
    labels = [t for t in (_text(v) for v in plan["texture"].tolist()) if t.strip()]
    return texture_set_from_labels(labels) if labels else PAPER_TEXTURES


def _file_sensor(attrs: Mapping[str, Any], plan: np.ndarray, path: Path
                 ) -> tuple[SensorLayout, np.ndarray | None, TextureSet]:
    """``(layout, present, textures)`` of a session file (:func:`_file_layout`, :func:`_file_textures`), for the
    reader and the writer alike. Raises SessionError for a malformed ``sensor_layout`` / ``texture_set``."""
    try:
        layout, present = _file_layout(attrs)
        return layout, present, _file_textures(attrs, plan)
    except ValueError as exc:  # LayoutError, TextureSetError
        raise SessionError(f"{path}: {exc}") from exc


# ----------------------------------------------------------------------------------------------------------------
# Reader
# ----------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TaxelBlock:
    """Taxels of many trials read at once (:meth:`Session.read_taxels`).

    data : (n_total_samples, n_channels) uint16 ADC counts, trial after trial (``data[starts[i]:starts[i+1]]``);
    starts : (n_trials + 1,) int64; dropped_frames : (n_trials,) int64 frames lost on the taxel link;
    has_speed_trace : (n_trials,) bool; speed_traces : list of ``(time_s, speed_mm_s)`` float64 arrays per trial,
    or None when not asked for.
    """

    data: np.ndarray
    starts: np.ndarray
    dropped_frames: np.ndarray
    has_speed_trace: np.ndarray
    speed_traces: list[Any] | None = None


class Session:
    """A session file opened read-only (use :func:`open_session`). Context manager; :meth:`close` when done.

    Attributes
    ----------
    path : Path
    attrs : dict of the root attributes (``schema_version``, ``session_id``, ``created_utc``, ``kind``, ...).
    rig_config : dict decoded from the ``rig_config`` JSON attribute.
    layout : :class:`rigctl.core.sensor.SensorLayout`, the sensor of every trial (``sensor_layout`` attribute; the
        paper's 3x3x2 @ 1 kHz for schema 1/2 files, see :func:`_file_layout` for their imports).
    textures : :class:`rigctl.core.textures.TextureSet` (``texture_set`` attribute; for schema 1/2 files the set of
        the plan's labels).
    plan : structured array with numpy str fields (``texture`` ``U<longest label>``, ``profile`` ``U24``), the other
        fields as :data:`PLAN_DTYPE`; one row per planned trial, ``status`` as :class:`TrialStatus` integers.
    protocol_source, protocol_name, protocol_format : str
    calibration : dict or None (``taxel_min``/``taxel_max`` as ``(layout.n_channels,)`` float64 arrays plus the
        block's attributes).
    problems : list of str, what was found wrong but read around (each also logged as a warning, one line naming
        the file and the trial): a trial marked complete in ``/plan`` without its recording is shown ``pending``
        in :attr:`plan` (a resume records it), a damaged trial skipped by :meth:`iter_trials`.

    Notes
    -----
    What is checked, and what happens when it is wrong (a user never gets silently wrong data):

    - the file as a whole (opening refuses it with SessionError): not HDF5 or truncated, not a session, a newer
      schema, a ``/plan`` that is not a table of unique trial ids with known statuses, unreadable attributes, a
      malformed ``sensor_layout`` / ``texture_set``, a calibration of another channel count;
    - one trial (reading it raises SessionError naming it; :meth:`iter_trials` skips it with a warning):
      ``taxels`` not ``(n, channels)`` integers, values above ``2**adc_bits - 1``, ``seq`` / ``flags`` /
      ``host_time_s`` not ``(n,)``, a trace and its times of different lengths, an ``n_samples`` attribute that
      disagrees with the data.

    Raises
    ------
    SessionError (see above), rigctl.storage.journal.FileBusy (a writer holds the HDF5 lock for long).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._f = _open_h5(self.path, "r")
        self.problems: list[str] = []
        self._checked: dict[int, int] = {}  # trial id -> its sample count, for trials whose recording passed
        try:
            with _reading(self.path, "the session header"):  # what the checks below did not foresee
                self._read_header()
        except BaseException:
            self._f.close()
            raise

    def _read_header(self) -> None:
        """The header (:func:`_read_session_header`) as attributes; the plan with unrecorded trials pending."""
        f = self._f
        header = _read_session_header(f, self.path)
        self.attrs = header.attrs
        self.layout, self._present, self.textures = header.layout, header.present, header.textures
        raw_plan = header.raw_plan
        for i, why in header.unrecorded.items():
            raw_plan["status"][i] = TrialStatus.PENDING
            self._problem(why)
        self.plan = _plan_to_str(raw_plan)
        self._complete = set(self.completed_ids())
        self.protocol_source = header.protocol_source
        try:
            self.rig_config = _decode_rig_config(self.attrs)
        except (TypeError, ValueError) as exc:
            self.rig_config = {}
            self._problem(f"{self.path}: the rig_config attribute is not a JSON object ({_one_line(exc)}); "
                          "ignored")
        with _reading(self.path, "the /protocol attributes"):
            pattrs = _read_attrs(f["protocol"])
        self.protocol_name = str(pattrs.get("name", ""))
        self.protocol_format = str(pattrs.get("format", ""))
        self.calibration = self._read_calibration()

    def _problem(self, message: str) -> None:
        self.problems.append(message)
        log.warning("%s", message)

    def _read_calibration(self) -> dict[str, Any] | None:
        f = self._f
        if "calibration" not in f:
            return None
        with _reading(self.path, "/calibration"):
            cal = _read_attrs(f["calibration"])
            n_stored = PAPER_SENSOR.n_channels if self._present is not None else self.layout.n_channels
            for k in f["calibration"]:
                cal[k] = f["calibration"][k][()]
                if k in ("taxel_min", "taxel_max"):
                    arr = np.asarray(cal[k])
                    if arr.shape != (n_stored,) or arr.dtype.kind not in "iuf":
                        raise SessionError(f"{self.path}: /calibration/{k} is {arr.dtype} {arr.shape}, not "
                                           f"({n_stored},) numbers (one per channel of the sensor)")
                    cal[k] = arr.astype(np.float64)
                    if self._present is not None:
                        cal[k] = cal[k][self._present]
        return cal

    @property
    def kind(self) -> str:
        return str(self.attrs.get("kind", ""))

    def __len__(self) -> int:
        return len(self.plan)

    def completed_ids(self) -> list[int]:
        """Trial ids whose plan status is complete (and whose group exists), in plan order."""
        ids = self.plan["trial_id"][self.plan["status"] == TrialStatus.COMPLETE]
        return [int(t) for t in ids]

    def failed_ids(self) -> list[int]:
        return [int(t) for t in self.plan["trial_id"][self.plan["status"] == TrialStatus.FAILED]]

    def _group(self, trial_id: int) -> h5py.Group | None:
        name = trial_group_name(trial_id)
        with _reading(self.path, f"trial {trial_id} ({name})"):
            g = self._f.get(name)
            if g is not None and not isinstance(g, h5py.Group):
                raise SessionError(f"{self.path}: trial {trial_id}: {name} is not a group; the file is damaged")
            return g

    def _damaged(self, trial_id: int, what: str) -> SessionError:
        return SessionError(f"{self.path}: trial {trial_id} is damaged: {what}; its data are not used")

    def _check_recording(self, trial_id: int, g: Any, attrs: Mapping[str, Any]) -> int:
        """Check a recorded trial's datasets against each other and the sensor without reading them (shapes, types,
        ``n_samples``); returns the sample count. Raises SessionError naming the trial and the problem."""
        if trial_id in self._checked:
            return self._checked[trial_id]
        n_stored = PAPER_SENSOR.n_channels if self._present is not None else self.layout.n_channels
        with _reading(self.path, f"trial {trial_id}"):
            ds = {}
            for k in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s",
                      "speed_time_s"):
                d = g.get(k)
                if not isinstance(d, h5py.Dataset):
                    raise self._damaged(trial_id, f"{k} is missing" if d is None else f"{k} is not a dataset")
                ds[k] = d
            tax = ds["taxels"]
            if tax.ndim != 2 or tax.shape[1] != n_stored:
                raise self._damaged(trial_id, f"taxels are {tax.shape}, not (samples, {n_stored}) for the sensor "
                                              f"{self.layout.shape_text}")
            if tax.dtype.kind not in "iu":
                raise self._damaged(trial_id, f"taxels are {tax.dtype}, not integer ADC counts (uint16)")
            n = int(tax.shape[0])
            for k in ("seq", "flags", "host_time_s"):
                if ds[k].shape != (n,):
                    raise self._damaged(trial_id, f"{k} is {ds[k].shape}, not ({n},) like taxels")
            for k in ("seq", "flags"):
                if ds[k].dtype.kind not in "iu":
                    raise self._damaged(trial_id, f"{k} is {ds[k].dtype}, not integers")
            for v, t in (("force_g", "force_time_s"), ("speed_mm_s", "speed_time_s")):
                if ds[v].ndim != 1 or ds[v].shape != ds[t].shape:
                    raise self._damaged(trial_id, f"{v} {ds[v].shape} and {t} {ds[t].shape} are not one trace")
            for k in ("host_time_s", "force_g", "force_time_s", "speed_mm_s", "speed_time_s"):
                if ds[k].dtype.kind not in "iuf":
                    raise self._damaged(trial_id, f"{k} is {ds[k].dtype}, not numbers")
            if "n_samples" in attrs:
                try:
                    said = int(attrs["n_samples"])
                except (TypeError, ValueError):
                    said = None
                if said != n:
                    raise self._damaged(trial_id, f"its n_samples attribute says {attrs['n_samples']!r}, its taxels "
                                                  f"hold {n} samples")
            for k in ("dropped_frames", "crc_errors"):
                try:
                    ok = int(attrs.get(k, 0)) >= 0
                except (TypeError, ValueError):
                    ok = False
                if not ok:
                    raise self._damaged(trial_id, f"its {k} attribute is {attrs.get(k)!r}, not a count")
        self._checked[trial_id] = n
        return n

    def trial_attrs(self, trial_id: int) -> dict[str, Any]:
        """The attributes of ``/trials/<id>`` (setpoints, texture, status, n_samples, dropped_frames, ...).

        Raises
        ------
        KeyError if the trial has no group; SessionError if it holds a recording that is damaged (see the class
        docstring: shapes, types, an ``n_samples`` that disagrees with the data).
        """
        g = self._group(trial_id)
        if g is None:
            if int(trial_id) in self._complete:  # listed under /trials at opening, yet it does not open
                raise self._damaged(trial_id, "its group cannot be opened")
            raise KeyError(f"trial {trial_id} has not been recorded in {self.path}")
        with _reading(self.path, f"the attributes of trial {trial_id}"):
            attrs = _read_attrs(g)
        with _reading(self.path, f"trial {trial_id}"):
            has_data = "taxels" in g
        if has_data or attrs.get("status") == "complete" or int(trial_id) in self._complete:
            self._check_recording(trial_id, g, attrs)
        return attrs

    def trial(self, trial_id: int) -> TrialData:
        """Read one recorded trial: a :class:`TrialData` with the session's :attr:`layout` (``taxels``
        ``(n, layout.n_channels)`` uint16 ADC counts at ``layout.sample_rate_hz``).

        Raises
        ------
        KeyError if the trial was not recorded (or failed); SessionError naming the trial if its recording is
        damaged (see the class docstring).
        """
        g = self._group(trial_id)
        with _reading(self.path, f"trial {trial_id}"):
            has_data = g is not None and "taxels" in g
        if not has_data:
            if int(trial_id) in self._complete:
                raise self._damaged(trial_id, "it is marked complete but holds no taxels")
            raise KeyError(f"trial {trial_id} has no recorded data in {self.path}")
        with _reading(self.path, f"the attributes of trial {trial_id}"):
            attrs = _read_attrs(g)
        self._check_recording(trial_id, g, attrs)
        with _reading(self.path, f"the data of trial {trial_id}"):
            assert g is not None  # has_data above
            arrays = {k: g[k][()] for k in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s",
                                            "speed_mm_s", "speed_time_s")}
        taxels = arrays.pop("taxels")
        if self._present is not None:  # a schema-1/2 import: only the real columns
            taxels = taxels[:, self._present]
        if taxels.size:
            lo, hi = int(taxels.min()), int(taxels.max())
            if lo < 0 or hi > self.layout.adc_max:
                bad = np.flatnonzero(((taxels < 0) | (taxels > self.layout.adc_max)).any(axis=1))
                raise self._damaged(trial_id, f"taxels hold {hi if hi > self.layout.adc_max else lo} (sample "
                                              f"{int(bad[0])}), outside the sensor's {self.layout.adc_bits}-bit "
                                              f"range 0..{self.layout.adc_max}")
        try:
            return TrialData(taxels=taxels, **arrays, dropped_frames=int(attrs.get("dropped_frames", 0)),
                             crc_errors=int(attrs.get("crc_errors", 0)), attrs=attrs, layout=self.layout)
        except (TypeError, ValueError) as exc:  # what the checks above did not foresee
            raise self._damaged(trial_id, _one_line(exc)) from None

    def read_taxels(self, ids: Sequence[int], *, traces: bool = False) -> TaxelBlock:
        """Read the taxels of many complete trials at once into one flat array (the encoder's read path).

        Only what an encoder needs, through h5py's low-level API: per trial one group and one dataset open and one
        read straight into its rows of a preallocated array (no :class:`TrialData`, no attribute dictionaries,
        no copies); the shape, type and ADC-range checks of :meth:`trial` are made on the block.

        Parameters
        ----------
        ids : sequence of int
            Trial ids (recorded trials), in the order wanted.
        traces : bool
            Also read each trial's measured speed trace (``speed_time_s``, ``speed_mm_s``).

        Returns
        -------
        TaxelBlock
            ``data`` (n_total_samples, n_channels) uint16 ADC counts, trial after trial; ``starts``
            (n_trials + 1,) int64 row starts; ``dropped_frames`` (n_trials,) int64; ``has_speed_trace`` (n_trials,)
            bool; ``speed_traces`` (list of (time_s, mm_s) or None).

        Raises
        ------
        KeyError if a trial has no recorded data; SessionError naming the trial if its taxels are damaged
        (shape, type, values outside the sensor's ADC range).
        """
        n_stored = PAPER_SENSOR.n_channels if self._present is not None else self.layout.n_channels
        fid = self._f.id
        dsets, lengths = [], np.zeros(len(ids), dtype=np.int64)
        dropped = np.zeros(len(ids), dtype=np.int64)
        has_trace = np.zeros(len(ids), dtype=bool)
        speed_traces: list[Any] | None = [] if traces else None
        missing = None
        with _reading(self.path, "trials' taxels"):
            tg = h5g.open(fid, b"/trials") if fid.links.exists(b"trials") else None
            for i, tid in enumerate(ids):
                name = trial_group_name(tid).rpartition("/")[2].encode()
                gid = h5g.open(tg, name) if tg is not None and tg.links.exists(name) else None
                if gid is None or not gid.links.exists(b"taxels"):
                    if int(tid) in self._complete:
                        raise self._damaged(int(tid), "it is marked complete but holds no taxels")
                    missing = int(tid)
                    break
                ds = h5d.open(gid, b"taxels")
                shape = ds.shape
                if len(shape) != 2 or shape[1] != n_stored or ds.dtype.kind not in "iu":
                    raise self._damaged(int(tid), f"taxels are {shape} {ds.dtype}, not (samples, {n_stored}) "
                                                  f"integer ADC counts for the sensor {self.layout.shape_text}")
                lengths[i] = shape[0]
                dsets.append(ds)
                if h5a.exists(gid, b"dropped_frames"):
                    a = h5a.open(gid, b"dropped_frames")
                    buf = np.zeros((), dtype=a.dtype)
                    a.read(buf)
                    dropped[i] = int(buf)
                if gid.links.exists(b"speed_mm_s"):
                    sp = h5d.open(gid, b"speed_mm_s")
                    has_trace[i] = sp.shape[0] > 0
                    if traces:
                        st = h5d.open(gid, b"speed_time_s")
                        v = np.empty(sp.shape, dtype=np.float64)
                        t = np.empty(st.shape, dtype=np.float64)
                        if v.size:
                            sp.read(h5s.ALL, h5s.ALL, v)
                        if t.size:
                            st.read(h5s.ALL, h5s.ALL, t)
                        speed_traces.append((t, v))  # type: ignore[union-attr]  # a list with traces
                elif traces:
                    speed_traces.append((np.zeros(0), np.zeros(0)))  # type: ignore[union-attr]
        if missing is not None:
            raise KeyError(f"trial {missing} has no recorded data in {self.path}")
        with _reading(self.path, "trials' taxels"):
            starts = np.zeros(len(ids) + 1, dtype=np.int64)
            np.cumsum(lengths, out=starts[1:])
            data = np.empty((int(starts[-1]), n_stored), dtype=np.uint16)
            for i, ds in enumerate(dsets):
                if lengths[i]:
                    ds.read(h5s.ALL, h5s.ALL, data[starts[i]:starts[i + 1]])
        if self._present is not None:  # a schema-1/2 import: only the real columns
            data = np.ascontiguousarray(data[:, self._present])
        if data.size:
            hi = int(data.max())
            if hi > self.layout.adc_max:
                row = int(np.flatnonzero((data > self.layout.adc_max).any(axis=1))[0])
                k = int(np.searchsorted(starts, row, side="right") - 1)
                raise self._damaged(int(ids[k]), f"taxels hold {hi} (sample {row - starts[k]}), outside the "
                                                 f"sensor's {self.layout.adc_bits}-bit range 0..{self.layout.adc_max}")
        return TaxelBlock(data, starts, dropped, has_trace, speed_traces)

    def iter_trials(self, ids: Sequence[int] | None = None) -> Iterator[TrialData]:
        """Yield :class:`TrialData` of the usable complete trials (the trial validator's,
        :func:`rigctl.storage.validate.usable_trials`: excluded ones are listed in :attr:`problems`), or of ``ids``,
        in plan order. A damaged trial is skipped with a warning naming it (also added to :attr:`problems`)."""
        if ids is None:
            from rigctl.storage.validate import usable_trials

            ids = usable_trials(self).ids
        for trial_id in ids:
            try:
                yield self.trial(trial_id)
            except SessionError as exc:
                self._problem(f"{exc} (skipped)")

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self._f.close()
        except Exception:
            pass


def open_session(path: str | os.PathLike[str]) -> Session:
    """Open a session file read-only (:class:`Session`, which says what it checks).

    Raises
    ------
    FileNotFoundError; SessionError (not HDF5, not a session file, a newer schema, a malformed plan or header);
    rigctl.storage.journal.FileBusy (an OSError: a writer holds the file for long).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    return Session(path)
