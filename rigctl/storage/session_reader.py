"""The session reader (:class:`SessionReader`): the header, trials one by one with their checks, and the encoder's
block read. :mod:`rigctl.storage.session` builds the public :class:`~rigctl.storage.session.Session` on it (the trial
validator, :mod:`rigctl.storage.validate`, checks a reader's trials, so the reader never imports it)."""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import h5py
import numpy as np
from h5py import h5a, h5d, h5g, h5s, h5t

from rigctl.core.sensor import PAPER_SENSOR
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage import h5objects, onboard_group, session_recording, trial_facts
from rigctl.storage.session_format import (
    SessionError,
    TrialStatus,
    _decode_rig_config,
    _one_line,
    _open_h5,
    _plan_to_str,
    _read_attrs,
    _reading,
    decode_events,
    trial_group_name,
)
from rigctl.storage.session_schema import (
    _read_session_header,
)

log = logging.getLogger("rigctl.storage.session")


class _HasId:
    """A low-level id where h5py's high-level helpers (``AttributeManager``) want an object with ``.id``."""

    def __init__(self, oid: Any) -> None:
        self.id = oid


#: what h5py raises on an object or attribute that does not open or read (a damaged group)
_GROUP_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError, OverflowError, IndexError, AttributeError)


def _plain(v: Any) -> Any:
    """An attribute value as :func:`_read_attrs` gives it (bytes decoded, numpy scalars as Python ones)."""
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    return v.item() if isinstance(v, np.generic) else v


_ABSENT = object()
_I8 = h5t.py_create(np.dtype("<i8"))


def _int_attr(gid: Any, name: bytes) -> Any:
    """A scalar integer attribute's value read with the low-level API (no dictionaries, no dtype built: ~10 us);
    :data:`_ABSENT` when the object has no such attribute; None when it is not a scalar integer (read it the slow
    way for the message)."""
    try:
        a = h5a.open(gid, name)
    except KeyError:
        return _ABSENT
    if a.get_type().get_class() != h5t.INTEGER:
        return None
    buf = np.empty((), dtype=np.int64)
    try:
        a.read(buf, mtype=_I8)
    except (TypeError, ValueError, OSError):  # not scalar
        return None
    return int(buf)


def _collect(wanted: set[bytes], into: list[bytes], name: bytes, *_: Any) -> None:
    """``h5a.iterate``'s callback for :meth:`Session.trial_table`: the attribute names wanted, as they come."""
    if name in wanted:
        into.append(name)


def as_count(value: Any) -> int | None:
    """``value`` as a count (an integer >= 0, or a float holding one), else None: what a ``n_samples``,
    ``dropped_frames`` or ``crc_errors`` attribute must be."""
    if isinstance(value, (bool, np.bool_)):
        return None
    a = np.asarray(value)
    if a.shape != () or a.dtype.kind not in "iuf":
        return None
    if a.dtype.kind == "f" and not (np.isfinite(a) and float(a).is_integer()):
        return None
    n = int(a)
    return n if n >= 0 else None


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


class SessionReader:
    """A session file opened read-only (use :func:`rigctl.storage.session.open_session`, whose
    :class:`~rigctl.storage.session.Session` adds the trial validator's choice of trials). Context manager;
    :meth:`close` when done.

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
        self._mtime_ns = trial_facts.mtime_ns(self.path)  # under the HDF5 lock: the seal of the trial facts
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
        self._flat = session_recording.is_flat(f)
        self._views = self._flat and session_recording.has_views(self.attrs)  # schema 4's (5 has none)
        self._index: dict[int, np.void] | None = None
        self._index_dups: dict[int, int] = {}
        self._rows: tuple[int, tuple[int, int]] | None = None  # _array_rows, read once
        self._tg: Any = None
        self._facts: dict[int, np.void] | None = None
        #: the trial validator's reports (rigctl.storage.validate), computed once per open session
        self.trial_reports: dict[str, Any] = {}

    def recording_index(self) -> dict[int, np.void]:
        """Schema 4: trial id -> its row of ``/recording/index`` (:data:`rigctl.storage.session_recording.INDEX_DTYPE`:
        where its samples and traces are in the recording arrays, ``dropped_frames``, ``crc_errors``), read once;
        ``{}`` for older files (one group of datasets per trial). Raises SessionError for an unreadable index."""
        if self._index is None:
            if not self._flat:
                self._index = {}
            else:
                with _reading(self.path, "/recording/index"):
                    idx = session_recording.read_index(self._f)
                    if idx.dtype != session_recording.INDEX_DTYPE:
                        raise SessionError(f"{self.path}: /recording/index is {idx.dtype}, not the documented "
                                           "table; the file is damaged")
                # built aside and set whole: threads reading one open session at once may both build it, and
                # neither sees the other's half-built table (trials listed "twice": a damaged index)
                index: dict[int, np.void] = {}
                dups: dict[int, int] = {}
                for r in idx:
                    tid = int(r["trial_id"])
                    if tid in index:
                        dups[tid] = dups.get(tid, 1) + 1
                    index[tid] = r
                self._index_dups, self._index = dups, index
        return self._index

    def trusted_facts(self) -> dict[int, np.void]:
        """Schema 4: trial id -> its ``/recording/facts`` row (:data:`rigctl.storage.trial_facts.FACTS_DTYPE`: what
        the writer found in its samples) while the file is sealed (nobody wrote to it after rigctl's last commit:
        :mod:`rigctl.storage.trial_facts`), read once; ``{}`` otherwise (older files, edited files)."""
        if self._facts is None:
            self._facts = trial_facts.trusted_facts(self._f, self.attrs, self._mtime_ns) if self._flat else {}
        return self._facts

    def index_rows(self, ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Schema 4: ``(rows, have)``: the ``/recording/index`` rows of ``ids`` (:data:`INDEX_DTYPE`, zeros where
        a trial has none) and whether each has one."""
        index = self.recording_index()
        rows = np.zeros(len(ids), dtype=session_recording.INDEX_DTYPE)
        have = np.zeros(len(ids), dtype=bool)
        for i, tid in enumerate(ids):
            r = index.get(int(tid))
            if r is not None:
                rows[i], have[i] = r, True
        return rows, have

    def index_duplicates(self) -> dict[int, int]:
        """Schema 4: trial id -> how many rows ``/recording/index`` gives it, for ids listed more than once (a
        damaged or edited index: which rows hold the trial is ambiguous, so the validator excludes it)."""
        self.recording_index()
        return dict(self._index_dups)

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

    @property
    def events(self) -> list[dict[str, Any]]:
        """The session's event log, oldest first (root attribute ``events``: the safety policy's ``latched`` and
        ``acknowledged`` entries, docs/session-format.md); [] when none."""
        return decode_events(self.attrs)

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

    def _trials_gid(self) -> Any:
        """The low-level id of ``/trials`` (opened once)."""
        if self._tg is None:
            with _reading(self.path, "the /trials group"):
                self._tg = h5g.open(self._f.id, b"/trials")
        return self._tg

    def flat_group_problem(self, trial_id: int, row: np.void) -> str | None:
        """Schema 4, 5: what is wrong with a complete trial's group against its ``/recording/index`` row ``row``, or
        None. Read: the group (it must open), its ``n_samples``, ``dropped_frames`` and ``crc_errors`` attributes
        (counts agreeing with the index) and (schema 4: 5 has none) its ``taxels`` view ((n, channels) integers, n =
        the index's). The other views are not opened (every rigctl reader takes the data from the recording arrays;
        one view costs ~0.1 ms to open). Costs one group open, three attribute reads and one dataset open."""
        name = trial_group_name(trial_id).rpartition("/")[2].encode()
        tg = self._trials_gid()
        try:
            gid = h5g.open(tg, name)
        except _GROUP_ERRORS as exc:
            return f"its group /trials/{name.decode()} cannot be opened ({_one_line(exc)})"
        if not isinstance(gid, h5g.GroupID):
            return f"/trials/{name.decode()} is not a group"
        n = int(row["n_samples"])
        for attr, said in (("n_samples", n), ("dropped_frames", int(row["dropped_frames"])),
                           ("crc_errors", int(row["crc_errors"]))):
            try:
                count = _int_attr(gid, attr.encode())  # the fast path: a scalar integer (~10 us)
                if count == said:
                    continue
                if count is _ABSENT:
                    continue
                value = _plain(h5py.AttributeManager(_HasId(gid))[attr])
            except _GROUP_ERRORS as exc:
                return f"its {attr} attribute cannot be read ({_one_line(exc)})"
            count = as_count(value)
            if attr == "n_samples" and count != n:
                return f"its n_samples attribute says {value!r}, /recording/index gives it {n} samples"
            if count is None:
                return f"its {attr} attribute is {value!r}, not a count"
            if count != said:
                return f"its {attr} attribute says {count}, /recording/index says {said}"
        return self._view_problem(gid, n) if self._views else None

    def _view_problem(self, gid: Any, n: int) -> str | None:
        """What is wrong with a schema-4 group's ``taxels`` view for ``n`` samples, or None."""
        try:
            if not gid.links.exists(b"taxels"):
                return "taxels is missing"
            ds = h5d.open(gid, b"taxels")
            shape, kind = ds.shape, ds.dtype.kind
        except _GROUP_ERRORS as exc:
            return f"taxels cannot be opened as a dataset ({_one_line(exc)})"
        n_ch = self.layout.n_channels
        if len(shape) != 2 or shape[1] != n_ch:
            return f"taxels are {shape}, not (samples, {n_ch}) for the sensor {self.layout.shape_text}"
        if kind not in "iu":
            return f"taxels are {ds.dtype}, not integer ADC counts (uint16)"
        if shape[0] != n:
            return f"its taxels view holds {shape[0]} samples, /recording/index gives it {n}"
        return None

    def trial_table(self, ids: Sequence[int], names: Sequence[str]) -> list[dict[str, Any]]:
        """The attributes ``names`` of many trials' groups, one dict per id in the order of ``ids`` holding the
        names each group has (values as :meth:`trial_attrs` gives them: str, Python numbers, arrays), in one pass
        without opening any dataset (``rigctl info``'s columns: ~0.03 ms a trial when the group has none of them).
        Tolerant: a group that does not open or an attribute that does not read is left out of its dict (the trial
        validator names damage; this only reads what is there). Raises SessionError if ``/trials`` does not open."""
        tg = self._trials_gid()
        wanted = {n.encode() for n in names}
        out: list[dict[str, Any]] = []
        for tid in ids:
            row: dict[str, Any] = {}
            out.append(row)
            try:
                gid = h5g.open(tg, trial_group_name(int(tid)).rpartition("/")[2].encode())
                have: list[bytes] = []
                h5a.iterate(gid, functools.partial(_collect, wanted, have))
                mgr = h5py.AttributeManager(_HasId(gid))
            except _GROUP_ERRORS:
                continue
            for a in have:
                try:
                    row[a.decode()] = _plain(mgr[a.decode()])
                except _GROUP_ERRORS:
                    pass
        return out

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
        if self._flat:
            if int(trial_id) in self._complete:
                why = self._flat_problem(int(trial_id))
                if why:
                    raise self._damaged(trial_id, why)
        elif has_data or attrs.get("status") == "complete" or int(trial_id) in self._complete:
            self._check_recording(trial_id, g, attrs)
        return attrs

    def _flat_problem(self, trial_id: int) -> str | None:
        """Schema 4: what is wrong with a complete trial without reading its data (its index row: missing,
        listed twice, rows outside the arrays; its group: :meth:`flat_group_problem`), or None."""
        row = self.recording_index().get(trial_id)
        if trial_id in self._index_dups:
            return f"/recording/index lists it {self._index_dups[trial_id]} times"
        why = self.index_problem(row, *self._array_rows())
        if why is None and row is not None:
            why = self.flat_group_problem(trial_id, row)
        return why

    def _flat_trial(self, trial_id: int) -> TrialData:
        """:meth:`trial` of a schema-4 file: the checks of :meth:`_flat_problem`, then its rows of the recording
        arrays (not its group's views) and its group's attributes."""
        tid = int(trial_id)
        g = self._group(tid)
        if tid not in self._complete and (g is None or tid not in self.recording_index()):
            raise KeyError(f"trial {tid} has no recorded data in {self.path}")
        why = self._flat_problem(tid)
        if why:
            raise self._damaged(tid, why)
        assert g is not None  # _flat_problem opened it
        with _reading(self.path, f"the attributes of trial {tid}"):
            attrs = _read_attrs(g)
        row = self.recording_index()[tid]
        rec = self._f[session_recording.GROUP]
        arrays: dict[str, np.ndarray] = {}
        with _reading(self.path, f"the data of trial {tid}"):
            for name, dt in session_recording.SAMPLE_ARRAYS:
                n = int(row["n_samples"])
                shape = (n, self.layout.n_channels) if name == "taxels" else (n,)
                arrays[name] = np.empty(shape, dtype=dt)
                session_recording.read_rows(rec[name], np.array([row["sample_start"]]), np.array([n]),
                                            arrays[name])
            for value, times, prefix in session_recording.TRACES:
                for name in (value, times):
                    arrays[name] = np.empty(int(row[f"n_{prefix}"]), dtype=np.float64)
                    session_recording.read_rows(rec[name], np.array([row[f"{prefix}_start"]]),
                                                np.array([row[f"n_{prefix}"]]), arrays[name])
            for name in ("position_mm", "position_time_s"):  # handheld trials: plain datasets of the group
                if name in g:
                    arrays[name] = np.asarray(g[name][()], np.float64)
            onboard = onboard_group.read_onboard(g)  # a scan the taxel board encoded itself
        taxels = arrays.pop("taxels")
        self._check_block_range([tid], taxels, np.array([0, len(taxels)]))
        try:
            return TrialData(taxels=taxels, **arrays, dropped_frames=int(row["dropped_frames"]),
                             crc_errors=int(row["crc_errors"]), attrs=attrs, layout=self.layout, onboard=onboard)
        except (TypeError, ValueError) as exc:  # what the checks above did not foresee
            raise self._damaged(tid, _one_line(exc)) from None

    def trial(self, trial_id: int) -> TrialData:
        """Read one recorded trial: a :class:`TrialData` with the session's :attr:`layout` (``taxels``
        ``(n, layout.n_channels)`` uint16 ADC counts at ``layout.sample_rate_hz``).

        Raises
        ------
        KeyError if the trial was not recorded (or failed); SessionError naming the trial if its recording is
        damaged (see the class docstring).
        """
        if self._flat:
            return self._flat_trial(trial_id)
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
                                            "speed_mm_s", "speed_time_s", "position_mm", "position_time_s")
                      if k in g or k not in ("position_mm", "position_time_s")}  # position: handheld trials only
            onboard = onboard_group.read_onboard(g)
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
                             crc_errors=int(attrs.get("crc_errors", 0)), attrs=attrs, layout=self.layout, onboard=onboard)
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
        if self._flat:
            return self._read_flat(ids, traces)
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
        self._check_block_range(ids, data, starts)
        return TaxelBlock(data, starts, dropped, has_trace, speed_traces)

    def _index_rows(self, ids: Sequence[int]) -> np.ndarray:
        """The ``/recording/index`` rows of ``ids`` (schema 4), in that order. Raises KeyError for a trial that was
        not recorded, SessionError for one marked complete that has no row or whose rows are outside the arrays."""
        index = self.recording_index()
        n_rows, trace_rows = self._array_rows()
        rows = np.zeros(len(ids), dtype=session_recording.INDEX_DTYPE)
        for i, tid in enumerate(ids):
            r = index.get(int(tid))
            if r is None and int(tid) not in self._complete:
                raise KeyError(f"trial {tid} has no recorded data in {self.path}")
            why = self.index_problem(r, n_rows, trace_rows)
            if int(tid) in self._index_dups:
                why = f"/recording/index lists it {self._index_dups[int(tid)]} times"
            if why:
                raise self._damaged(int(tid), why)
            rows[i] = r
        return rows

    def _array_rows(self) -> tuple[int, tuple[int, int]]:
        """Rows of the per-sample recording arrays (the shortest of them: a row outside one is not recorded), and of
        the force and the speed trace arrays (the shorter of each value/times pair); read once (read-only file)."""
        if self._rows is None:
            with _reading(self.path, "the recording arrays"):
                rec = self._f[session_recording.GROUP]
                force, speed = (min(int(rec[v].shape[0]), int(rec[t].shape[0])) for v, t, _ in session_recording.TRACES)
                self._rows = min(int(rec[n].shape[0]) for n, _ in session_recording.SAMPLE_ARRAYS), (force, speed)
        return self._rows

    @staticmethod
    def index_problem(row: np.void | None, n_rows: int, trace_rows: tuple[int, int] | None = None) -> str | None:
        """What is wrong with a complete trial's ``/recording/index`` row (None: missing), or None: its samples
        outside the ``n_rows`` recorded, or (given ``trace_rows``, the force and speed arrays' rows) its traces."""
        if row is None:
            return "it is marked complete but /recording/index has no row for it"
        start, n = int(row["sample_start"]), int(row["n_samples"])
        if start < 0 or n < 0 or start + n > n_rows:
            return f"/recording/index puts its samples at rows {start}+{n}, outside the {n_rows} recorded"
        for (_, _, prefix), rows in zip(session_recording.TRACES, trace_rows or ()):
            start, n = int(row[f"{prefix}_start"]), int(row[f"n_{prefix}"])
            if start < 0 or n < 0 or start + n > rows:
                return (f"/recording/index puts its {prefix} trace at rows {start}+{n}, outside the {rows} "
                        "recorded")
        return None

    def _read_flat(self, ids: Sequence[int], traces: bool) -> TaxelBlock:
        """:meth:`read_taxels` of a schema-4 file: the index once, then one read per run of trials stored one
        after another in ``/recording/taxels``."""
        rows = self._index_rows(ids)
        lengths = rows["n_samples"].astype(np.int64)
        starts = np.zeros(len(ids) + 1, dtype=np.int64)
        np.cumsum(lengths, out=starts[1:])
        rec = self._f[session_recording.GROUP]
        with _reading(self.path, "trials' taxels"):
            data = np.empty((int(starts[-1]), self.layout.n_channels), dtype=np.uint16)
            session_recording.read_rows(rec["taxels"], rows["sample_start"], lengths, data)
            speed_traces = None
            if traces:
                speed_traces = []
                n_sp = rows["n_speed"].astype(np.int64)
                pos = np.concatenate([[0], np.cumsum(n_sp)])
                vs = np.empty(int(pos[-1]), dtype=np.float64)
                ts = np.empty(int(pos[-1]), dtype=np.float64)
                session_recording.read_rows(rec["speed_mm_s"], rows["speed_start"], n_sp, vs)
                session_recording.read_rows(rec["speed_time_s"], rows["speed_start"], n_sp, ts)
                speed_traces = [(ts[pos[i]:pos[i + 1]], vs[pos[i]:pos[i + 1]]) for i in range(len(ids))]
        self._check_block_range(ids, data, starts)
        return TaxelBlock(data, starts, rows["dropped_frames"].astype(np.int64), rows["n_speed"] > 0, speed_traces)

    def trial_counts(self, ids: Sequence[int]) -> list[dict[str, Any]]:
        """``n_samples``, ``dropped_frames``, ``crc_errors`` and ``started_utc`` of many recorded trials (the trials
        table of an export), in the order of ``ids``: schema 4 from ``/recording/index`` and one attribute read per
        trial; older files from :meth:`trial_attrs`.

        Raises KeyError if a trial has no recorded data; SessionError naming a damaged trial.
        """
        if not self._flat:
            return [{k: a.get(k, d) for k, d in (("n_samples", 0), ("dropped_frames", 0), ("crc_errors", 0),
                                                 ("started_utc", ""))} for a in map(self.trial_attrs, ids)]
        rows = self._index_rows(ids)
        out = []
        with _reading(self.path, "trials' started_utc"), h5objects.bounded_metadata_cache(self._f):
            tg = h5g.open(self._f.id, b"/trials")
            for tid, r in zip(ids, rows):  # (by name through /trials: no id made for each group)
                started = h5objects.member_attr(tg, trial_group_name(int(tid)).rpartition("/")[2].encode(),
                                                b"started_utc")
                out.append({"n_samples": int(r["n_samples"]), "dropped_frames": int(r["dropped_frames"]),
                            "crc_errors": int(r["crc_errors"]), "started_utc": "" if started is None else str(started)})
        return out

    def read_traces(self, ids: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """The load-cell and speed traces of many recorded trials: ``(force_time_s, force_g, speed_time_s,
        speed_mm_s)`` float64 arrays per trial, in the order of ``ids`` (schema 4: one read per run of trials of each
        recording array; older files: :meth:`trial` per trial).

        Raises KeyError if a trial has no recorded data; SessionError naming a damaged trial.
        """
        if not self._flat:
            out = []
            for tid in ids:
                tr = self.trial(int(tid))
                out.append((tr.force_time_s, tr.force_g, tr.speed_time_s, tr.speed_mm_s))
            return out
        rows = self._index_rows(ids)
        rec = self._f[session_recording.GROUP]
        arrays = []
        with _reading(self.path, "trials' traces"):
            for value, times, prefix in session_recording.TRACES:
                n = rows[f"n_{prefix}"].astype(np.int64)
                pos = np.concatenate([[0], np.cumsum(n)])
                for name in (times, value):
                    buf = np.empty(int(pos[-1]), dtype=np.float64)
                    session_recording.read_rows(rec[name], rows[f"{prefix}_start"], n, buf)
                    arrays.append([buf[pos[i]:pos[i + 1]] for i in range(len(ids))])
        return list(zip(*arrays)) if ids else []

    def _check_block_range(self, ids: Sequence[int], data: np.ndarray, starts: np.ndarray) -> None:
        """Raise SessionError naming the first trial of a block whose counts exceed the sensor's ADC range."""
        if data.size:
            hi = int(data.max())
            if hi > self.layout.adc_max:
                row = int(np.flatnonzero((data > self.layout.adc_max).any(axis=1))[0])
                k = int(np.searchsorted(starts, row, side="right") - 1)
                raise self._damaged(int(ids[k]), f"taxels hold {hi} (sample {row - starts[k]}), outside the "
                                                 f"sensor's {self.layout.adc_bits}-bit range 0..{self.layout.adc_max}")

    def iter_trials(self, ids: Sequence[int]) -> Iterator[TrialData]:
        """Yield :class:`TrialData` of the trials ``ids``, in that order (``Session.iter_trials()``: the usable
        ones). A damaged trial is skipped with a warning naming it (also added to :attr:`problems`)."""
        for trial_id in ids:
            try:
                yield self.trial(trial_id)
            except SessionError as exc:
                self._problem(f"{exc} (skipped)")

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self._f.close()
        except Exception:
            pass
