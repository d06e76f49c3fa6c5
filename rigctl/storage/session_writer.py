"""The session writer (:class:`SessionWriter`): a new file made in memory and renamed into place, then one
crash-safe commit per trial (:mod:`rigctl.storage.journal`) under the one-writer lock. Re-exported by
:mod:`rigctl.storage.session`."""

from __future__ import annotations

import contextlib
import copy
import errno
import json
import logging
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.provenance import RESUMED_ATTR
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, texture_set_from_labels
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage import h5objects, journal, session_recording, sidecars, trial_facts, trial_seal
from rigctl.storage.onboard_group import ONBOARD_ATTR, write_onboard
from rigctl.storage.outputs import check_replaceable
from rigctl.storage.session_create import (
    _calibration_arrays,
    _check_no_journal,
    _new_file_image,
    _write_calibration,
    _write_new_file,
    _writer_lock,
)
from rigctl.storage.session_format import (
    DEFAULT_SCHEMA_VERSION,
    EVENTS_ATTR,
    PLAN_DTYPE,
    PLAN_FIELDS,
    SCHEMA_VERSION,
    SESSION_KINDS,
    TAXEL_CHUNK_BYTES,
    SessionError,
    SessionWriteError,
    TrialStatus,
    _attr_value,
    _check_plan_textures,
    _decode_rig_config,
    _id_ranges,
    _one_line,
    _open_h5,
    _os_error_text,
    _parse_utc,
    _plan_to_str,
    _reading,
    _row_value,
    _text,
    _utc_now,
    decode_events,
    plan_array,
    trial_group_name,
)
from rigctl.storage.session_schema import (
    _group_status,
    _read_session_header,
)

log = logging.getLogger("rigctl.storage.session")


@contextlib.contextmanager
def _writing(path: Path, *, durable: bool = True, wait_s: float = 10.0) -> Iterator[h5py.File]:
    """Open ``path`` for writing through a :class:`rigctl.storage.journal.OverlayFile`: HDF5's writes stay in memory
    and are committed (journaled) to disk only after HDF5 has closed the file cleanly; on an exception nothing
    reaches the disk."""
    overlay = journal.OverlayFile(path, durable=durable, wait_s=wait_s)
    stamp = None
    try:
        f = h5py.File(overlay, "r+", rdcc_nbytes=0)  # no chunk cache: an append to an uncompressed chunk writes
        # only its own rows (not the whole chunk again, which the journal would copy)
        try:
            # schema 4's trial facts stay only if nobody wrote since the last commit (stat under the lock)
            stamp = trial_facts.begin_commit(f, trial_facts.mtime_ns(path))
            yield f
            trial_seal.store_root(f)  # the result-changing root attributes as this commit leaves them
        finally:
            f.close()
        try:
            overlay.commit()
        except journal.CommittedInterrupt:  # on disk all the same
            trial_facts.seal(path, stamp)
            raise
        trial_facts.seal(path, stamp)  # under the lock: no other writer comes between
    finally:
        overlay.close()


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
        #: the file :meth:`create` made (removed by :meth:`discard`); the session it replaces at the first commit
        self._created_file: sidecars.Sidecar | None = None
        self._replaces: Path | None = None
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
                self._flat = session_recording.is_flat(f)
                #: schema 4: each trial's group gets views of its rows (schema 5: none, the index says where they are)
                self._views = self._flat and session_recording.has_views(contents.attrs)
                #: a batch's per-sample arrays, each trial copied once (schema 4 and 5)
                self._batch = session_recording.BatchArrays(contents.layout.n_channels)
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
        self._rows_of: tuple[np.ndarray, int, dict[int, int]] | None = None  # (plan, its length, trial id -> row)

    # -- lifetime -----------------------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        """True after :meth:`close`: the writer lock is released and nothing more can be written."""
        return self._lock is None or not self._lock.held

    def close(self) -> None:
        """Release the writer lock (idempotent). Every write is on disk already; a new session that was to replace
        another (``overwrite``) and has committed nothing is removed, the old one kept."""
        lock, self._lock = self._lock, None
        if self._created_file is not None:
            if self._replaces is not None:
                self._created_file.remove()
            self._created_file.close()
        if lock is not None:
            lock.release()

    def discard(self) -> None:
        """Remove the file :meth:`create` made (only if its name still holds it: an import written whole or not at
        all), then :meth:`close`; a session it was to replace stays unless it was replaced already."""
        if self._created_file is not None:
            self._created_file.remove(committed_too=True)
        self.close()

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
            if self._replaces is not None and self._created_file is not None:  # the new session holds a commit:
                self._created_file.commit_to(self._replaces.name)  # it replaces the old one (renameat, atomic)
                self.path, self._replaces = self._replaces, None
        except journal.FileBusy:
            raise
        except OSError as exc:
            self._plan["status"] = before  # nothing of this write reached the file
            done = self.completed_ids()
            intact = (f"trials {_id_ranges(done)} are intact" if done else "no trial was complete before")
            if exc.errno == errno.ELOOP:  # a link at the session's name (journal.open_in_place): refused as it is
                raise SessionWriteError(f"{exc.strerror or exc}; {intact}", exc.errno, done) from None
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
        schema_version: int = DEFAULT_SCHEMA_VERSION,
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
        attrs : extra root attributes; without a ``provenance`` one, the writing process's
            (:func:`rigctl.core.provenance.software_provenance`: versions, git state, host, command line) is stored.
        overwrite : replace an existing file (otherwise :class:`FileExistsError`).
        schema_version : 4 (:data:`DEFAULT_SCHEMA_VERSION`: the trials' data back to back in ``/recording``, read in
            large blocks, each trial's group holding views of its rows for plain h5py), 5 (:data:`SCHEMA_VERSION`:
            the same without the views, which cost ~1 ms a trial to make: the dataset generator's, read through
            :class:`Session` or ``/recording/index``), or 3 (one group of datasets per trial, as rigctl wrote before;
            for tools that need it and for tests of old files). A file keeps its layout: a resume writes what it
            holds.

        Raises
        ------
        FileExistsError, ValueError (bad kind, plan or calibration shape), TypeError (layout not a SensorLayout),
        rigctl.core.textures.TextureSetError (a plan label not in ``textures``). Nothing is created on any of them.
        """
        path = Path(path)
        if kind not in SESSION_KINDS:
            raise ValueError(f"kind must be one of {SESSION_KINDS}, got {kind!r}")
        if schema_version not in (3, 4, SCHEMA_VERSION):
            raise ValueError(f"schema_version must be 3, 4 or {SCHEMA_VERSION}, got {schema_version!r}")
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
            if overwrite:  # only a session is replaced: never a device, a link leading out, another program's file
                check_replaceable(path, kind="session")
            _check_no_journal(path)
            image = _new_file_image(
                plan_arr, layout=layout, textures=textures, protocol_source=protocol_source,
                protocol_name=protocol_name, protocol_format=protocol_format, rig_config=rig_config, kind=kind,
                calibration=calibration, attrs=attrs, schema_version=schema_version, compression=compression)
            # --overwrite: the old session stays until the new one's first commit (kept aside until then)
            side = _write_new_file(path, image, keep_aside=os.path.lexists(path))
            return cls._of_new_file(side, path, lock, compression=compression, durable=durable)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _of_new_file(cls, side: sidecars.Sidecar, path: Path, lock: journal.WriterLock, **kw: Any) -> "SessionWriter":
        """The writer of the file :meth:`create` made (``side``); kept aside from ``path`` (an old session there),
        it replaces that session at its first commit (:meth:`_commit`)."""
        try:
            writer = cls(side.path, _lock=lock, **kw)
            writer._created_file = side
            writer._replaces = path if side.path != path else None
            return writer
        except BaseException:  # (a Ctrl-C or SIGTERM too) the file made here is removed
            side.remove(committed_too=True)
            side.close()
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
        """The plan row of ``trial_id`` (its first): a dict made once per plan array (a search of the 24,000-row
        plan per trial cost ~45 us of the dataset generator's writer)."""
        plan = self._plan
        rows = self._rows_of
        if rows is None or rows[0] is not plan or rows[1] != len(plan):
            ids = plan["trial_id"].tolist()
            rows = (plan, len(plan), {t: i for i, t in reversed(list(enumerate(ids)))})
            self._rows_of = rows
        i = rows[2].get(int(trial_id))
        if i is None:
            raise SessionError(f"trial {trial_id} is not in the plan of {self.path}")
        return i

    # -- writing ------------------------------------------------------------------------------------------------
    def write_trial(self, trial_id: int, data: TrialData, *, labels: Mapping[str, Any] | None = None) -> None:
        """Write one trial in one go, mark it complete in ``/plan``, commit it to disk (journaled) and close the file.

        ``labels``: the condition the trial was recorded under where it is not the planned one (``texture`` str,
        ``speed_mm_s`` mm/s, ``force_g`` g; a replayed trial's source, :func:`rigctl.acquisition.labels.
        recorded_labels`): stored in its ``/plan`` row, the planned values kept as the trial attributes
        ``planned_<field>``. ValueError for another field.

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
        self.write_trials([(trial_id, data)], labels={trial_id: labels} if labels else None)

    def write_trials(self, items: Iterable[tuple[int, TrialData] | tuple[int, TrialData, np.ndarray | None]], *,
                     labels: Mapping[int, Mapping[str, Any]] | None = None) -> int:
        """Write several trials during one opening of the file; returns how many.

        For the dataset generator, where opening the file per trial would dominate. Same checks as
        :meth:`write_trial`. The batch reaches the disk in one journaled commit when the last trial is written: a
        crash before that loses the whole batch (the file stays as it was), never part of a trial. Each trial is
        taken whole as ``items`` yields it (its arrays copied): a caller may reuse them for the next trial.
        ``labels``: trial id -> its recorded condition, as :meth:`write_trial`'s. An item may carry a third
        element, the trial's :func:`rigctl.storage.trial_facts.sample_facts` computed from these very arrays by the
        process that made them (the dataset generator's render workers): its facts row is taken from it instead of
        computed here (its fingerprint checked: ValueError, nothing of the batch written, if it is another trial's).
        """
        for tid, asked in (labels or {}).items():
            unknown = set(asked) - set(RELABEL_FIELDS)
            if unknown:
                raise ValueError(f"trial {tid}: only {', '.join(RELABEL_FIELDS)} can be relabelled, not "
                                 f"{', '.join(sorted(unknown))}")
        before = self._plan.copy()
        written, relabelled = [], []
        try:
            with self._commit("writing trials") as f:
                self._adopt_file_status(f)
                before = self._plan.copy()
                views: list[tuple[Any, int, TrialData]] = []  # schema 4: written to /recording after the groups
                known: list[np.ndarray | None] = []  # the views' sample facts handed over with them (or None)
                trials = f["trials"].id  # (looked up once a batch: ~50 us a lookup)
                self._batch.clear()
                for item in items:
                    trial_id, data = item[0], item[1]
                    i = self._row_index(trial_id)
                    if self._plan["status"][i] == TrialStatus.COMPLETE:
                        raise SessionError(f"trial {trial_id} is already complete in {self.path}")
                    self._check_trial_layout(trial_id, data)
                    lab = labels.get(int(trial_id)) if labels else None
                    if lab:
                        data = copy.copy(data)
                        data.attrs = {**data.attrs, **{f"planned_{k}": _plan_value(self._plan[i][k]) for k in lab}}
                        for k, v in lab.items():
                            self._plan[i][k] = v
                        relabelled.append(i)
                    self._write_group(f, self._plan[i], data, views, trials)
                    if self._flat:
                        known.append(item[2] if len(item) > 2 else None)
                    self._plan["status"][i] = TrialStatus.COMPLETE
                    written.append(i)
                for i in relabelled:  # the recorded condition in the plan row (before its status, below)
                    f["plan"][i] = self._plan[i]
                if views:
                    taxels, rows = session_recording.append_trials(f, views, views=self._views,
                                                                   stacked=self._batch.stacked())
                    trial_facts.append(f, rows, [d for _, _, d in views], known)
                    trial_seal.append(f, rows, [d for _, _, d in views],
                                      [self._plan[self._row_index(tid)] for _, tid, _ in views])
                    for tax, (_, _, data) in zip(taxels, views):
                        self._taxels_attrs(tax, data)
                if written:  # the plan's statuses last, in one write of the span they cover (only the status
                    lo, hi = min(written), max(written) + 1  # field: the labels' heap objects stay as they are)
                    f["plan"][lo:hi, "status"] = self._plan["status"][lo:hi]
        except journal.CommittedInterrupt:
            raise  # a Ctrl-C during the commit, which was completed first: the batch is on disk
        except BaseException:
            self._plan = before  # nothing of the batch reached the file
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

    def note_resume(self, provenance: Mapping[str, Any]) -> None:
        """Record that this run resumes the session: ``provenance`` (this run's, e.g.
        :func:`rigctl.acquisition.provenance.session_provenance`) appended to the :data:`RESUMED_ATTR` root attribute
        with the time and how many trials were complete before it. One crash-safe commit.

        Raises SessionWriteError (disk full, read-only) as every commit does."""
        entry = {"resumed_utc": _utc_now(), "complete_trials_before": len(self.completed_ids()),
                 "provenance": dict(provenance)}
        with self._commit("noting the resume") as f:
            text = f.attrs.get(RESUMED_ATTR)
            runs = json.loads(_text(text)) if text is not None else []
            f.attrs[RESUMED_ATTR] = json.dumps([*runs, entry], default=str, sort_keys=True)  # as provenance_json

    def log_event(self, kind: str, **fields: Any) -> dict[str, Any]:
        """Append an entry to the session's event log (the :data:`EVENTS_ATTR` root attribute, a JSON list): ``kind``
        (e.g. ``"latched"``, ``"acknowledged"``: the safety policy's, docs/safety.md), the time (``at_utc``, unless
        given) and ``fields`` (JSON-able). One crash-safe commit; returns the entry.

        Raises SessionWriteError (disk full, read-only) as every commit does."""
        return self.log_events([(kind, fields)])[0]

    def log_events(self, events: Sequence[tuple[str, Mapping[str, Any]]]) -> list[dict[str, Any]]:
        """Append several entries to the event log as :meth:`log_event` does each (``(kind, fields)`` pairs, in that
        order), in one crash-safe commit (all or none of them); returns the entries (none: no commit).

        Raises SessionWriteError (disk full, read-only) as every commit does."""
        entries = [{"kind": str(kind), "at_utc": _utc_now(), **fields} for kind, fields in events]
        if not entries:
            return []
        kinds = sorted({e["kind"] for e in entries})
        action = f"logging a {kinds[0]} event" if len(entries) == 1 else f"logging {len(entries)} {'/'.join(kinds)} events"
        with self._commit(action) as f:
            text = f.attrs.get(EVENTS_ATTR)
            logged = json.loads(_text(text)) if text is not None else []
            text = json.dumps([*logged, *entries], default=str, sort_keys=True)
            f.attrs[EVENTS_ATTR] = text
        self.attrs = {**self.attrs, EVENTS_ATTR: text}
        return entries

    def events(self) -> list[dict[str, Any]]:
        """The session's event log, oldest first (:meth:`log_event`)."""
        return decode_events(self.attrs)

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

    def _write_group(self, f: h5py.File, row: np.void, data: TrialData, views: list[tuple[Any, int, TrialData]],
                     trials: Any) -> None:
        """Make the trial's group with its attributes and (schema 1-3) its datasets; schema 4: add (group, trial id,
        data) to ``views``, written to the recording arrays for the whole batch at once."""
        # h5objects: the same objects as h5py's high-level API, without its per-object Python overhead (the
        # dataset generator writes tens of thousands of trials)
        name = trial_group_name(int(row["trial_id"]))  # in ``trials``, the low-level id of f["trials"]
        short = name.rsplit("/", 1)[1]
        if trials.links.exists(short.encode()):  # a failed earlier attempt (never a complete recording)
            self._refuse_complete_group(f[name], int(row["trial_id"]))
            del f[name]
        g = h5objects.create_group(trials, short)
        n = data.n_samples
        layout = self.layout
        n_ch = layout.n_channels
        if self._flat:  # schema 4: the data go to /recording, the group holds views of them
            views.append((g, int(row["trial_id"]), _snapshot(data, self._batch)))
        else:
            chunk_rows = max(1, min(n, session_recording.sample_chunk_rows(n_ch, TAXEL_CHUNK_BYTES)))
            comp = self.compression if n else None
            tax = h5objects.create_dataset(g, "taxels", data.taxels, chunks=(chunk_rows, n_ch), compression=comp)
            for key in ("seq", "flags", "host_time_s"):
                h5objects.create_dataset(g, key, getattr(data, key), chunks=(chunk_rows,), compression=comp)
            for key in ("force_g", "force_time_s", "speed_mm_s", "speed_time_s"):
                h5objects.create_dataset(g, key, getattr(data, key))
            self._taxels_attrs(tax, data)
        if data.position_mm.size:  # the handheld rig's tracker position: plain datasets in the group (both schemas)
            for key in ("position_mm", "position_time_s"):
                h5objects.create_dataset(g, key, getattr(data, key))
        if data.onboard is not None:  # a scan the taxel board encoded itself: its record instead of raw taxels
            write_onboard(g, data.onboard)
        attrs = {}
        for fld in PLAN_FIELDS:
            v = row[fld]
            attrs[fld] = _text(v) if isinstance(v, (bytes, str)) else v.item()
        for k, v in data.attrs.items():
            if k not in ("status", "trial_id"):
                attrs[k] = _attr_value(v)
        attrs.update(n_samples=n, dropped_frames=data.dropped_frames, crc_errors=data.crc_errors)
        if data.onboard is not None:
            attrs[ONBOARD_ATTR] = True
        attrs.setdefault("started_utc", "")
        attrs["status"] = "complete"
        h5objects.set_attrs(g, attrs)

    def _taxels_attrs(self, tax: Any, data: TrialData) -> None:
        """The attributes of a trial's ``taxels`` (NWB TimeSeries terms; ``starting_time`` s from the session's
        ``created_utc`` to the trial's ``started_utc``)."""
        started = _parse_utc(str(data.attrs.get("started_utc", "")))
        starting_time = (started - self._created).total_seconds() if started and self._created else 0.0
        layout = self.layout
        h5objects.set_attrs(tax, {"rate_hz": layout.sample_rate_hz, "unit": "ADC counts", "adc_bits": layout.adc_bits,
                                  "starting_time": starting_time})


#: the /plan fields a trial's recorded condition may replace (:meth:`SessionWriter.write_trial` ``labels``)
RELABEL_FIELDS = ("texture", "speed_mm_s", "force_g")


def _plan_value(v: Any) -> Any:
    """A /plan field's value as a Python str or number (a trial attribute)."""
    return _text(v) if isinstance(v, (bytes, str)) else v.item()


def _snapshot(data: TrialData, batch: session_recording.BatchArrays) -> TrialData:
    """A copy of ``data`` whose arrays are its own: a batch's recording arrays are written after its last trial is
    taken, and a caller may reuse a trial's buffers for the next one (the dataset generator's shared-memory slots).
    The per-sample arrays are copied once, into ``batch`` (their views; the batch is written from there)."""
    snap = copy.copy(data)  # no __post_init__: the arrays were checked when ``data`` was made
    for name, array in batch.take(data).items():
        setattr(snap, name, array)
    for name in ("force_g", "force_time_s", "speed_mm_s", "speed_time_s", "position_mm", "position_time_s"):
        setattr(snap, name, np.array(getattr(data, name), copy=True))
    snap.attrs = dict(data.attrs)
    return snap


def _with_id(planned: Any, default_id: int) -> Any:
    if _row_value(planned, "trial_id") is not None:
        return planned
    if isinstance(planned, Mapping):
        return {**planned, "trial_id": default_id}
    values = {n: _row_value(planned, n) for n in PLAN_DTYPE.names or ()}
    values["trial_id"] = default_id
    return {k: v for k, v in values.items() if v is not None}
