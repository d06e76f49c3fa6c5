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
import json
import math
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import h5py
import numpy as np

from rigctl import __version__
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, TextureSetError, texture_set_from_labels
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage import h5objects, journal

#: 3: root attributes ``sensor_layout`` and ``texture_set``, ``/plan`` texture as variable-length UTF-8
SCHEMA_VERSION = 3
SESSION_KINDS = ("recorded", "simulated-dataset", "fabricslide", "imported")
#: variable-length UTF-8 string (h5py's ``string_dtype``): ``/plan`` texture labels of any length
VLEN_UTF8 = h5py.string_dtype("utf-8")
#: largest ``taxels`` chunk, bytes (one chunk holds up to 65,536 samples of every channel, fewer for wide sensors)
TAXEL_CHUNK_BYTES = 4 << 20


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
PLAN_FIELDS = tuple(n for n in PLAN_DTYPE.names if n != "status")



def taxels_description(layout: SensorLayout) -> dict:
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
    """A session file cannot be created, opened or written as asked (wrong layout, trial already complete, ...)."""


# ----------------------------------------------------------------------------------------------------------------
# Trial data
# ----------------------------------------------------------------------------------------------------------------
# ----------------------------------------------------------------------------------------------------------------
# Plan helpers
# ----------------------------------------------------------------------------------------------------------------
def _row_value(row: Any, name: str, default=None):
    if isinstance(row, Mapping):
        return row.get(name, default)
    if isinstance(row, np.void):
        return row[name] if name in row.dtype.names else default
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
    cols, fields = {}, []
    for name in plan.dtype.names:
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
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _parse_utc(text: str) -> _dt.datetime | None:
    try:
        return _dt.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        return None


def _attr_value(value: Any):
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


def _read_attrs(obj) -> dict:
    out = {}
    for k, v in obj.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


def _open_h5(path: Path, mode: str, *, wait_s: float = 10.0) -> h5py.File:
    """Open ``path`` with h5py, retrying while another process holds the HDF5 file lock (e.g. a writer)."""
    try:
        journal.recover(path, wait_s=wait_s)  # finish a commit a killed writer left half done
    except PermissionError:
        pass
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return h5py.File(path, mode)
        except (BlockingIOError, OSError) as exc:
            locked = isinstance(exc, BlockingIOError) or "lock" in str(exc).lower()
            if not locked or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


@contextlib.contextmanager
def _writing(path: Path, *, durable: bool = True, wait_s: float = 10.0):
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


# ----------------------------------------------------------------------------------------------------------------
# Writer
# ----------------------------------------------------------------------------------------------------------------
class SessionWriter:
    """Writes a session file trial by trial; the file is open only during each write.

    Create a new file with :meth:`create`, or reopen an interrupted one with :meth:`open` (resume). Then
    :meth:`write_trial` for each recorded trial (or :meth:`mark_failed`).

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
    SessionError if the file is not a session, has a newer schema, or is a schema-1/2 import with absent channels
    (``channel_present``: read it with :func:`open_session`; it cannot be appended to).
    """

    def __init__(self, path: str | os.PathLike, *, compression: str | None = "gzip", durable: bool = True):
        self.path = Path(path)
        self.durable = durable
        #: how long a write waits for another process (a reader holding the HDF5 file lock) before FileBusy, s
        self.wait_s = 10.0
        if compression not in ("gzip", "lzf", None):
            raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
        self.compression = compression
        with _open_h5(self.path, "r") as f:
            _check_file(f, self.path)
            self.attrs = _read_attrs(f)
            self.protocol_source = _read_text(f["protocol/source"])
            self._plan = f["plan"][()]
            self.layout, present, self.textures = _file_sensor(self.attrs, self._plan, self.path)
            if present is not None:
                raise SessionError(f"{self.path} is a schema-{self.attrs.get('schema_version')} import with absent "
                                   "channels (channel_present); it can be read, not appended to: import it again")
        self._created = _parse_utc(self.attrs.get("created_utc", ""))

    # -- construction -------------------------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        *,
        plan: Iterable[Any] | np.ndarray,
        layout: SensorLayout = PAPER_SENSOR,
        textures: TextureSet | Mapping | None = None,
        protocol_source: str = "",
        protocol_name: str = "",
        protocol_format: str = "toml",
        rig_config: Mapping | None = None,
        kind: str = "recorded",
        calibration: Mapping | None = None,
        attrs: Mapping | None = None,
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
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".creating")
        with h5py.File(tmp, "w") as f:
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
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        stale = journal.journal_path(path)
        if stale.exists():  # a journal of the file being replaced must never be replayed onto the new one
            stale.unlink()
        os.replace(tmp, path)  # the session file appears complete or not at all
        return cls(path, compression=compression, durable=durable)

    @classmethod
    def open(cls, path: str | os.PathLike, *, protocol_source: str | None = None,
             compression: str | None = "gzip", durable: bool = True) -> "SessionWriter":
        """Reopen an interrupted session to resume it.

        Parameters
        ----------
        protocol_source : if given, must equal the stored ``/protocol/source`` text.

        Raises
        ------
        FileNotFoundError, SessionError (not a session file, or the protocol source differs).
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path} does not exist (nothing to resume)")
        writer = cls(path, compression=compression, durable=durable)
        if protocol_source is not None and protocol_source != writer.protocol_source:
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
        SessionError if the trial is not in the plan or is already complete (no trial is recorded twice), or if
        ``data.layout`` differs from the session's :attr:`layout` in channel count or sample rate.
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
            with _writing(self.path, durable=self.durable, wait_s=self.wait_s) as f:
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
        with _writing(self.path, durable=self.durable, wait_s=self.wait_s) as f:
            ds = f["plan"]
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
        with _writing(self.path, durable=self.durable, wait_s=self.wait_s) as f:
            name = trial_group_name(trial_id)
            if name in f:
                del f[name]
            g = f.create_group(name)
            g.attrs["status"] = "failed"
            g.attrs["error"] = str(reason)
            g.attrs["failed_utc"] = _utc_now()
            self._plan["status"][i] = TrialStatus.FAILED
            f["plan"][i:i + 1, "status"] = self._plan["status"][i:i + 1]
            f.flush()

    def set_calibration(self, calibration: Mapping) -> None:
        """Write (replace) the ``/calibration`` block.

        Raises ValueError if ``taxel_min``/``taxel_max`` are not ``(layout.n_channels,)``.
        """
        _calibration_arrays(calibration, self.layout.n_channels)
        with _writing(self.path, durable=self.durable, wait_s=self.wait_s) as f:
            _write_calibration(f, calibration, self.layout.n_channels)

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
        if trials.links.exists(short.encode()):  # a failed (or half-written) earlier attempt
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
    values = {n: _row_value(planned, n) for n in PLAN_DTYPE.names}
    values["trial_id"] = default_id
    return {k: v for k, v in values.items() if v is not None}


def _calibration_arrays(calibration: Mapping, n_channels: int) -> dict:
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


def _write_calibration(f: h5py.File, calibration: Mapping, n_channels: int) -> None:
    arrays = _calibration_arrays(calibration, n_channels)
    if "calibration" in f:
        del f["calibration"]
    g = f.create_group("calibration")
    for k, v in calibration.items():
        if k in arrays:
            g.create_dataset(k, data=arrays[k]).attrs["unit"] = "ADC counts"
        else:
            g.attrs[k] = _attr_value(v)


def _read_text(ds) -> str:
    v = ds[()]
    return v.decode() if isinstance(v, bytes) else str(v)


def _check_file(f: h5py.File, path: Path) -> None:
    missing = [k for k in ("plan", "trials", "protocol") if k not in f]
    if missing or "schema_version" not in f.attrs:
        raise SessionError(f"{path} is not a rigctl session file (missing {missing or ['schema_version']})")
    if int(f.attrs["schema_version"]) > SCHEMA_VERSION:
        raise SessionError(
            f"{path} has schema_version {int(f.attrs['schema_version'])}, newer than this rigctl ({SCHEMA_VERSION})"
        )


def _legacy_layout(attrs: Mapping, present: np.ndarray) -> SensorLayout:
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


def _file_layout(attrs: Mapping) -> tuple[SensorLayout, np.ndarray | None]:
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


def _file_textures(attrs: Mapping, plan: np.ndarray) -> TextureSet:
    """Schema 3: the ``texture_set`` attribute; schema 1/2: ``texture_set_from_labels`` of the plan's labels (the
    paper's A-P set when all are A-P or the plan is empty). The paper's set is returned as :data:`PAPER_TEXTURES`
    itself (as the paper's sensor as :data:`PAPER_SENSOR`), so identity checks downstream hold."""
    text = attrs.get("texture_set")
    if text:
        textures = TextureSet.from_json(text)
        return PAPER_TEXTURES if textures == PAPER_TEXTURES else textures
    labels = [t for t in (_text(v) for v in plan["texture"].tolist()) if t.strip()]
    return texture_set_from_labels(labels) if labels else PAPER_TEXTURES


def _file_sensor(attrs: Mapping, plan: np.ndarray, path: Path
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

    Raises
    ------
    SessionError (not a session file, a newer schema, a malformed ``sensor_layout`` / ``texture_set``).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._f = _open_h5(self.path, "r")
        try:
            _check_file(self._f, self.path)
            f = self._f
            self.attrs = _read_attrs(f)
            raw_plan = f["plan"][()]
            self.layout, self._present, self.textures = _file_sensor(self.attrs, raw_plan, self.path)
        except Exception:
            self._f.close()
            raise
        self.rig_config = json.loads(self.attrs.get("rig_config", "{}") or "{}")
        self.plan = _plan_to_str(raw_plan)
        self.protocol_source = _read_text(f["protocol/source"])
        self.protocol_name = str(_read_attrs(f["protocol"]).get("name", ""))
        self.protocol_format = str(_read_attrs(f["protocol"]).get("format", ""))
        self.calibration = None
        if "calibration" in f:
            cal = _read_attrs(f["calibration"])
            for k in f["calibration"]:
                cal[k] = f["calibration"][k][()]
                if self._present is not None and k in ("taxel_min", "taxel_max"):
                    cal[k] = cal[k][self._present]
            self.calibration = cal

    @property
    def kind(self) -> str:
        return str(self.attrs.get("kind", ""))

    def __len__(self) -> int:
        return len(self.plan)

    def completed_ids(self) -> list[int]:
        """Trial ids whose plan status is complete (and whose group exists), in plan order."""
        ids = self.plan["trial_id"][self.plan["status"] == TrialStatus.COMPLETE]
        return [int(t) for t in ids if trial_group_name(int(t)) in self._f]

    def failed_ids(self) -> list[int]:
        return [int(t) for t in self.plan["trial_id"][self.plan["status"] == TrialStatus.FAILED]]

    def trial_attrs(self, trial_id: int) -> dict:
        """The attributes of ``/trials/<id>`` (setpoints, texture, status, dropped_frames, ...).

        Raises KeyError if the trial has no group.
        """
        name = trial_group_name(trial_id)
        if name not in self._f:
            raise KeyError(f"trial {trial_id} has not been recorded in {self.path}")
        return _read_attrs(self._f[name])

    def trial(self, trial_id: int) -> TrialData:
        """Read one recorded trial: a :class:`TrialData` with the session's :attr:`layout` (``taxels``
        ``(n, layout.n_channels)`` uint16 at ``layout.sample_rate_hz``).

        Raises
        ------
        KeyError if the trial was not recorded (or failed).
        """
        name = trial_group_name(trial_id)
        if name not in self._f or "taxels" not in self._f[name]:
            raise KeyError(f"trial {trial_id} has no recorded data in {self.path}")
        g = self._f[name]
        attrs = _read_attrs(g)
        taxels = g["taxels"][()]
        if self._present is not None:  # a schema-1/2 import: only the real columns
            taxels = taxels[:, self._present]
        return TrialData(
            taxels=taxels,
            seq=g["seq"][()],
            flags=g["flags"][()],
            host_time_s=g["host_time_s"][()],
            force_g=g["force_g"][()],
            force_time_s=g["force_time_s"][()],
            speed_mm_s=g["speed_mm_s"][()],
            speed_time_s=g["speed_time_s"][()],
            dropped_frames=int(attrs.get("dropped_frames", 0)),
            crc_errors=int(attrs.get("crc_errors", 0)),
            attrs=attrs,
            layout=self.layout,
        )

    def iter_trials(self, ids: Sequence[int] | None = None) -> Iterator[TrialData]:
        """Yield :class:`TrialData` of the complete trials (or of ``ids``), in plan order."""
        for trial_id in self.completed_ids() if ids is None else ids:
            yield self.trial(trial_id)

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # pragma: no cover - best effort
        try:
            self._f.close()
        except Exception:
            pass


def open_session(path: str | os.PathLike) -> Session:
    """Open a session file read-only.

    Raises
    ------
    FileNotFoundError, SessionError (not a session file or a newer schema), OSError (not HDF5).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    return Session(path)
