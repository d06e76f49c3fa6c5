"""The headless run queue: protocol runs recorded one after another on one open rig, the queue kept in a small JSON
file so it survives a restart (``rigctl serve`` is a thin HTTP face on it; the GUI or a script can use it directly).

One run owns the rig at a time (a second one waits, ``queued``); each is a :class:`rigctl.operations.ProtocolRun`
(its pause / resume / abort), so the queue holds no rig logic. A run cut by a crash or a kill (the file says it was
``running`` or ``paused``) is queued again at the front when the queue is reopened, and continues its session file
with the session's own resume (no trial recorded twice, none lost: each finished trial is in the file the moment it
is reported); a stopped or failed run is continued the same way on request (:meth:`RunQueue.resume`).
:meth:`RunQueue.stop` is STOP: the drum to rest at once, the current run paused (resumable by one
:meth:`RunQueue.resume`, which lets the queue go on), the queue held until then or :meth:`RunQueue.release`.

Run states: ``queued``, ``running``, ``pausing``, ``paused``, ``aborting``, ``done`` (every planned trial complete),
``stopped`` (ended early: aborted, a lost link; resumable), ``failed`` (an error before or while recording),
``aborted`` (taken off the queue before it started).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import logging
import os
import queue
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rigctl.acquisition.protocol import ProtocolError, parse_protocol
from rigctl.acquisition.runner import TrialEvent
from rigctl.acquisition.safety import Acknowledgement, Latch
from rigctl.core.errors import describe_error
from rigctl.core.progress import ProgressEvent
from rigctl.operations._control import RigControl
from rigctl.operations._monitor import RigEvent
from rigctl.operations._rules import RUN_STATES
from rigctl.operations._run import ProtocolRun
from rigctl.storage.journal import WriterLock, WriterLockHeld
from rigctl.storage.outputs import OutputError, OutputLocked, check_output, opened_in_folder, place_in_folder
from rigctl.storage.session import SessionLocked
from rigctl.storage.sidecars import write_small_file

__all__ = ["QueueError", "QueuedRun", "RunQueue", "RUN_QUEUE_STATES", "lock_queue_file", "read_queue_file"]

log = logging.getLogger(__name__)

#: the run states (one vocabulary on every face: :data:`rigctl.operations.RUN_STATES`; the old name kept)
RUN_QUEUE_STATES = RUN_STATES
#: states of a run that has not ended
ACTIVE = ("queued", "running", "pausing", "paused", "aborting")
#: the queue file's format version
QUEUE_FORMAT = 1
#: how long a run waits for its session file's writer lock (held by another writer, or by the journal helper of a
#: killed one finishing its last commit) before it fails, s; and how often it tries
LOCKED_WAIT_S = 60.0
LOCKED_POLL_S = 0.5
#: the longest protocol text a run takes, characters (the queue file holds it, rewritten at every change)
MAX_PROTOCOL_CHARS = 1_000_000
#: ended runs the queue file keeps (the oldest beyond are dropped from it; their session files stay)
MAX_ENDED_RUNS = 500
#: a run's progress (trials done) is written to the queue file at most this often; its state changes at once, s
PROGRESS_SAVE_S = 10.0


#: the largest queue file read, bytes (a queue of thousands of runs is a few MB; --queue /dev/zero is refused)
MAX_QUEUE_BYTES = 64 << 20


def read_queue_file(path: str | os.PathLike[str]) -> list[QueuedRun]:
    """The runs of the queue file ``path`` ([] if it does not exist), read before the rig opens.

    Raises QueueError (one line) for anything but a regular file (a device, a FIFO: never written over), a file
    larger than :data:`MAX_QUEUE_BYTES`, or a file that is not a run queue (a session, another program's file)."""
    p = Path(path)
    if not os.path.lexists(p):
        return []
    try:
        import stat

        if not stat.S_ISREG(os.stat(p).st_mode):
            raise QueueError(f"{p} is not a regular file (a device, a FIFO or a folder): give a run queue file "
                             "(--queue)")
        with open(p, "rb") as fh:
            raw = fh.read(MAX_QUEUE_BYTES + 1)
        if len(raw) > MAX_QUEUE_BYTES:
            raise ValueError(f"larger than {MAX_QUEUE_BYTES >> 20} MB")
        doc = json.loads(raw.decode("utf-8"))
        return [QueuedRun(**r) for r in doc["runs"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, QueueError):
            raise
        why = "not UTF-8 text" if isinstance(exc, UnicodeDecodeError) else exc
        raise QueueError(f"{p}: not a run queue file ({why}); move it away or give another --queue") from None


class QueueError(ValueError):
    """A request the queue refuses (unknown run, a protocol that does not load, an output that exists, a control
    that does not apply to the run's state); the message says why in one line. ``status`` is the HTTP status the
    server answers with."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def lock_queue_file(queue_file: str | os.PathLike[str]) -> WriterLock:
    """The lock that makes one server (one :class:`RunQueue`) per queue file: an exclusive lock on the queue file's
    ``.lock`` sidecar (:class:`rigctl.storage.journal.WriterLock`; the kernel drops it when its holder dies), held
    until released. Raises QueueError (409) naming the holder's pid when another one holds it."""
    path = Path(queue_file)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return WriterLock(path)
    except WriterLockHeld as exc:
        who = f"pid {exc.pid}" if exc.pid else "another process"
        raise QueueError(f"the queue {path} is served already ({who}): one server per queue file; stop it, or "
                         "give this one another --queue", 409) from None
    except OSError as exc:
        raise QueueError(f"the queue {path} cannot be locked ({exc.strerror or exc})") from None


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


@dataclasses.dataclass
class QueuedRun:
    """One run of the queue, as the queue file and ``GET /runs/{id}`` show it."""

    id: str
    protocol_name: str
    protocol_source: str
    out: str
    overwrite: bool = False
    state: str = "queued"
    trials_done: int = 0
    trials_total: int = 0
    errors: list[str] = dataclasses.field(default_factory=list)
    created_utc: str = ""
    started_utc: str | None = None
    ended_utc: str | None = None
    #: times the run was started (a crash and a restart make it 2)
    starts: int = 0
    summary: list[str] = dataclasses.field(default_factory=list)
    #: why the run is paused (or why it ended, resumable), in words: the latched fault that holds it, its
    #: acknowledgement waiting for the start, a STOP or a pause; "" while it runs
    cause: str = ""
    #: the latched fault the run ended or paused on (:meth:`rigctl.acquisition.safety.Latch.to_dict`), until an
    #: operator acknowledges it: a restarted server holds the queue while one is kept here
    latch: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def public(self) -> dict[str, Any]:
        """Without the protocol's text (``GET /runs``)."""
        d = self.to_dict()
        d.pop("protocol_source")
        return d


class RunQueue:
    """Runs recorded one after another on ``control`` (an open :class:`rigctl.operations.RigControl`).

    Parameters
    ----------
    control : the open rig.
    queue_file : the JSON file the queue lives in (created; read back when it exists: runs cut by a crash resume).
    lsl : publish every run on LSL through one :class:`rigctl.operations.LslPublisher` (opened here: a missing
        pylsl is :class:`rigctl.core.lsl.LslUnavailable` at once); ``lsl_wait_s``: each run waits up to this long
        for a consumer of the marker stream before its ``run_start`` (``serve --lsl-wait``).
    protocols : () -> {name: protocol file} of the protocols a run may name (default the built-in ones,
        :func:`rigctl.acquisition.builtin.builtin_protocols`).
    data_dir : when given (``rigctl serve --data-dir``), a run's ``out`` is a relative name inside this folder
        (:func:`rigctl.storage.outputs.place_in_folder`: absolute paths, ``..``, NUL, names resolving outside it and
        subfolders that are symlinks refused, 422; missing subfolders made), checked again as the run starts (a
        subfolder replaced by a symlink meanwhile fails the run, nothing written); created if missing.
    file_lock : the queue file's lock (:func:`lock_queue_file`) when the caller took it already (``rigctl serve``
        takes it before it opens the rig); else taken here (QueueError, 409, when another queue holds it).
        Released by :meth:`close`.

    :meth:`start` starts the worker thread; :meth:`close` ends it (a run in progress is stopped cleanly and stays
    queued to resume at the next start).
    """

    def __init__(self, control: RigControl, queue_file: str | os.PathLike[str], *, lsl: bool = False,
                 protocols: Callable[[], dict[str, Any]] | None = None,
                 data_dir: str | os.PathLike[str] | None = None, lsl_wait_s: float = 0.0,
                 file_lock: WriterLock | None = None) -> None:
        self.control = control
        self.path = Path(queue_file)
        self.data_dir = None if data_dir is None else Path(data_dir).expanduser().resolve()
        if self.data_dir is not None:
            try:
                self.data_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise QueueError(f"the data folder {self.data_dir} cannot be made ({exc.strerror or exc})") \
                    from None
        #: one LSL publisher for every run (the same streams to LabRecorder from run to run), or None
        self.lsl: Any = None
        if lsl:
            from rigctl.operations._lsl import LslPublisher

            self.lsl = LslPublisher(control, wait_s=lsl_wait_s)
        self._protocols = protocols
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self.runs: dict[str, QueuedRun] = {}
        self.current: ProtocolRun | None = None
        self.current_id: str | None = None
        #: the current run's trial: the last trial event's trial_id, texture, speed_mm_s, force_g, attempt, kind
        self.current_trial: dict[str, Any] | None = None
        #: STOP holds the queue: no further run starts until release()
        self.held = False
        self._closing = False
        #: (the descriptor path of the running run's folder, its name) while a run records (:meth:`_shown`)
        self._alias: tuple[str, str] | None = None
        self._thread: threading.Thread | None = None
        self._subscribers: list[queue.Queue[dict[str, Any] | None]] = []
        self._streams_ended = False
        self._unsubscribe_rig: Callable[[], None] | None = None
        self._saved_t = 0.0  # time.monotonic() of the last write of the queue file
        self._file_lock = file_lock if file_lock is not None else lock_queue_file(self.path)
        try:
            self._load()
        except BaseException:
            self._file_lock.release()
            raise

    # ----------------------------------------------------------------------------------------------- the file
    def _load(self) -> None:
        if not self.path.exists():
            return
        runs = read_queue_file(self.path)
        cut = [r for r in runs if r.state in ACTIVE and r.state != "queued"]
        for r in cut:  # cut by a crash: first in line again, resumed from its session file
            r.state = "queued"
            r.errors.append(f"interrupted (the server ended while it ran); resumed at {_utc_now()}")
        order = cut + [r for r in runs if r not in cut]
        self.runs = {r.id: r for r in order}
        if any(r.state in ACTIVE for r in order):  # a restart of the server is no start (docs/safety.md): a run it
            # finds to do, cut by the restart or queued before it, waits for POST /queue/release
            self.held = True
            for r in order:
                if r.state in ACTIVE and r.latch is None:
                    r.cause = "the server restarted: nothing moves until POST /queue/release"
        for r in order:  # a run that paused or ended on a latch nobody acknowledged: the latch and the queue held
            if r.latch is not None and r.state in ACTIVE + ("stopped",):
                try:
                    latch = Latch(**r.latch)
                except TypeError:
                    continue
                self.control.keep_latch(latch)
                self.held = True
                r.cause = (f"latched before the server restarted: {latch.describe()} (POST /ack, then POST "
                           "/queue/release)")
        self._save()

    def _prune(self) -> None:
        """Drop the oldest ended runs beyond :data:`MAX_ENDED_RUNS` (a queue file that grows forever is rewritten,
        whole, at every change)."""
        ended = [r for r in self.runs.values() if r.state not in ACTIVE]
        for r in ended[:max(0, len(ended) - MAX_ENDED_RUNS)]:
            del self.runs[r.id]

    def _save(self) -> None:
        self._prune()
        self._saved_t = time.monotonic()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        doc = {"format": QUEUE_FORMAT, "runs": [r.to_dict() for r in self.runs.values()]}
        write_small_file(self.path, json.dumps(doc, indent=1).encode())  # a sidecar of a random name, renamed

    # ----------------------------------------------------------------------------------------------- events
    def subscribe(self) -> "queue.Queue[dict[str, Any] | None]":
        """A queue receiving every event from now on (``{"type": "progress" | "trial" | "run" | "stop", ...}``);
        None when the feed ends (:meth:`end_streams`)."""
        q: queue.Queue[dict[str, Any] | None] = queue.Queue(maxsize=10_000)
        with self._lock:
            if self._streams_ended:  # subscribed while the server shuts down: the feed ends at once
                q.put_nowait(None)
            else:
                self._subscribers.append(q)
        return q

    def unsubscribe(self, q: "queue.Queue[dict[str, Any] | None]") -> None:
        with self._lock:
            if q in self._subscribers:
                self._subscribers.remove(q)

    def end_streams(self) -> int:
        """End every subscriber's feed (a None each; the server's event streams close at once: a shutting-down
        server does not wait for its clients). Returns how many were open."""
        with self._lock:
            self._streams_ended = True
            subs, self._subscribers = list(self._subscribers), []
        for q in subs:
            with contextlib.suppress(queue.Empty):
                if q.full():
                    q.get_nowait()
            with contextlib.suppress(queue.Full):
                q.put_nowait(None)
        return len(subs)

    def _emit(self, event: dict[str, Any]) -> None:
        with self._lock:
            subs = list(self._subscribers)
        for q in subs:
            try:
                q.put_nowait(event)
            except queue.Full:  # a client that stopped reading loses events, never the run
                pass

    # ----------------------------------------------------------------------------------------------- requests
    def _load_protocol(self, name: str | None, toml: str | None) -> Any:
        if (name is None) == (toml is None):
            raise QueueError("give a protocol by name or as TOML text (one of them)")
        try:
            if toml is not None:
                return parse_protocol(toml)
            from rigctl.acquisition.builtin import builtin_protocols
            from rigctl.acquisition.protocol import load_protocol

            # by name only (a network client never names a file of this host)
            known = self._protocols() if self._protocols is not None else builtin_protocols()
            path = known.get(str(name).removesuffix(".toml"))
            if path is None:
                raise QueueError(f"no built-in protocol named {name!r}; known: {', '.join(known)}", 404)
            return load_protocol(path)
        except ProtocolError as exc:
            raise QueueError(f"protocol: {exc}") from None

    def submit(self, out: str | os.PathLike[str], *, protocol: str | None = None, toml: str | None = None,
               overwrite: bool = False) -> QueuedRun:
        """Queue a run of a built-in ``protocol`` (by name) or of ``toml`` text into the session file ``out``.

        Raises QueueError: the protocol does not load (or is a Python script: not over the queue; over
        :data:`MAX_PROTOCOL_CHARS`: 413), ``out`` breaks the data folder's rules (422), exists without
        ``overwrite`` or is another queued run's output (409), is not a session ``overwrite`` may replace
        (:func:`rigctl.storage.outputs.check_output` with ``kind="session"``: 422)."""
        if toml is not None and len(toml) > MAX_PROTOCOL_CHARS:
            raise QueueError(f"the protocol text has {len(toml)} characters: at most {MAX_PROTOCOL_CHARS}", 413)
        out_path = self._out_path(out)
        proto = self._load_protocol(protocol, toml)
        if not hasattr(proto, "texture_set"):
            raise QueueError("Python-script protocols cannot be queued: give a TOML protocol")
        if self.data_dir is not None:  # its subfolders made, as asked ("mouse1/s1.h5")
            out_path = self._out_path(out, create=True)
        with self._lock:
            if any(Path(r.out) == out_path for r in self.runs.values() if r.state in ACTIVE):
                raise QueueError(f"{out_path} is the output of a run already queued", 409)
            if out_path.exists() and not overwrite:
                raise QueueError(f"{out_path} exists (pass overwrite, or choose another output)", 409)
            try:  # the one output policy: only a session is replaced, the folder takes a file, no other writer
                check_output(out_path, option="out", overwrite=overwrite, kind="session")
            except OutputLocked as exc:
                raise QueueError(str(exc), 409) from None
            except OutputError as exc:
                raise QueueError(str(exc), 422) from None
            run = QueuedRun(id=uuid.uuid4().hex[:12], protocol_name=proto.name, protocol_source=proto.source,
                            out=str(out_path), overwrite=overwrite, trials_total=len(proto.plan()),
                            created_utc=_utc_now())
            self.runs[run.id] = run
            self._save()
            self._wake.notify_all()
        self._emit({"type": "run", "id": run.id, "state": run.state})
        return run

    def _out_path(self, out: str | os.PathLike[str], *, create: bool = False) -> Path:
        """``out`` as the absolute session path: a name inside :attr:`data_dir` when there is one (its missing
        subfolders made when ``create``)."""
        try:
            if self.data_dir is not None:
                return place_in_folder(self.data_dir, os.fspath(out) if isinstance(out, os.PathLike) else out,
                                       create=create)
            return Path(out).expanduser().resolve()
        except OutputError as exc:
            raise QueueError(str(exc), 422) from None
        except (ValueError, OSError, RuntimeError) as exc:
            raise QueueError(f"out {str(out)[:100]!r}: not a usable file name ({exc})", 422) from None

    def get(self, run_id: str) -> QueuedRun:
        with self._lock:
            run = self.runs.get(run_id)
        if run is None:
            raise QueueError(f"no run {run_id!r}", 404)
        return run

    def list(self) -> list[QueuedRun]:
        with self._lock:
            return list(self.runs.values())

    def _set(self, run: QueuedRun, **changes: Any) -> None:
        with self._lock:
            for k, v in changes.items():
                setattr(run, k, v)
            self._save()
        if "state" in changes:
            self._emit({"type": "run", "id": run.id, "state": run.state})

    def pause(self, run_id: str) -> QueuedRun:
        """Pause the running run after its trial in progress (sensor released). QueueError unless it runs."""
        run = self.get(run_id)
        with self._lock:
            if self.current_id != run_id or self.current is None:
                raise QueueError(f"run {run_id} is {run.state}: only the running run can be paused", 409)
            self.current.pause()
            state = self.current.state
            self._set(run, state="paused" if state == "paused" else "pausing", cause=run.cause or "paused on request")
        return run

    def resume(self, run_id: str) -> QueuedRun:
        """The start: go on after :meth:`pause`, STOP or an acknowledged latch; or queue a ``stopped`` or ``failed``
        run again: it continues its session file with the session's own resume (the trials finished kept, none
        recorded twice; it waits while the queue is held after STOP). QueueError (409) for any other state, and
        while a latched fault holds the rig (naming it: ``POST /ack`` first)."""
        run = self.get(run_id)
        latch = self.control.latch
        with self._lock:
            if latch is not None and (run.state in ACTIVE or run.latch is not None):
                raise QueueError(f"run {run_id} is paused on a latched fault: {latch.describe()} (POST /ack, then "
                                 "resume)", 409)
            if self.current_id == run_id and self.current is not None:
                try:
                    self.current.resume()
                except RuntimeError as exc:  # latched meanwhile
                    raise QueueError(f"run {run_id}: {exc}", 409) from None
                self.held = False  # the one start after STOP: the run goes on, and the queue after it
                self._wake.notify_all()
                self._set(run, state="running", cause="", latch=None)
                return run
            if run.state not in ("stopped", "failed"):
                raise QueueError(f"run {run_id} is {run.state}: only a paused, stopped or failed run can be "
                                 "resumed", 409)
            if any(r.out == run.out for r in self.runs.values() if r.state in ACTIVE):
                raise QueueError(f"{run.out} is the output of a run already queued", 409)
            self._set(run, state="queued", ended_utc=None,
                      errors=[*run.errors, f"resumed on request at {_utc_now()}"])
            self._wake.notify_all()
        return run

    def abort(self, run_id: str) -> QueuedRun:
        """Abort a run: the running one stops cleanly (finished trials kept), a queued one never starts."""
        run = self.get(run_id)
        with self._lock:
            if self.current_id == run_id and self.current is not None:
                self.current.abort()
                self._set(run, state="aborting")
            elif run.state == "queued":
                self._set(run, state="aborted", ended_utc=_utc_now())
            else:
                raise QueueError(f"run {run_id} is {run.state}: nothing to abort", 409)
        return run

    def stop(self) -> bool:
        """STOP, at once: the drum to rest and the actuator home (:meth:`RigControl.stop`, not waiting for the
        run); the current run pauses (the trial in progress discarded, recorded again at its resume: STOP means one
        thing on every face, docs/safety.md), and the queue is held: no queued run starts. The start is one
        ``resume`` of the paused run (it lets the queue go on after it) or :meth:`release`. Abort is its own
        action (:meth:`abort`). True when the controller acknowledged STOP."""
        with self._lock:
            self.held = True
            current, current_id = self.current, self.current_id
            run = self.runs.get(current_id) if current_id is not None else None
            if run is not None and current is not None and run.state in ("running", "pausing"):
                self._set(run, state="pausing", cause="STOP: the trial in progress is discarded; resume records "
                          "it again")
        acknowledged = bool(self.control.stop())  # the run on the rig hears it first and pauses (ProtocolRun.stop)
        self._emit({"type": "stop", "acknowledged": acknowledged})
        return acknowledged

    def start_needed(self) -> str:
        """What start the rig waits for now, in words (the answer to an acknowledgement: it never starts anything)."""
        with self._lock:
            current_id, held = self.current_id, self.held
            queued = any(r.state == "queued" for r in self.runs.values())
        if current_id is not None:
            return f"nothing moves until the run is resumed: POST /runs/{current_id}/resume"
        if held and queued:
            return "nothing moves until the queue is released: POST /queue/release"
        return "nothing moves until a run starts (its start homes the rig)"

    def release(self) -> None:
        """Let queued runs start again after STOP, or after a latch found at open has been acknowledged: a start, so
        the safety table decides (:meth:`RigControl.start_allowed`). QueueError (409) naming it while the rig holds a
        latched fault, or with the table's why for any other refusal."""
        latch = self.control.latch
        if latch is not None:
            raise QueueError(f"the rig holds a latched fault: {latch.describe()} (POST /ack first)", 409)
        try:
            self.control.start_allowed("POST /queue/release")
        except RuntimeError as exc:  # LatchedFault (latched meanwhile), SafetyRefused
            raise QueueError(f"the queue is not released: {exc}", 409) from None
        with self._lock:
            self.held = False
            self._wake.notify_all()

    # ----------------------------------------------------------------------------------------------- worker
    def start(self) -> "RunQueue":
        """Start the worker, and the rig's monitor (its status poll, what ``/status`` shows; the monitor's state,
        fault, link and latch events go into the event feed as ``{"type": "rig", "kind", "message"}``). Returns
        self."""
        self._unsubscribe_rig = self.control.subscribe(self._rig_event)
        if self.control.latch is not None:  # found at open (or kept from before a restart): shown, the queue held
            self.held = True
        self.control.monitor  # noqa: B018 - starts the library's poll: the server reads nothing from the rig itself
        self._thread = threading.Thread(target=self._work, name="run-queue", daemon=True)
        self._thread.start()
        return self

    def _rig_event(self, event: RigEvent) -> None:
        if event.kind in ("state", "faults", "link", "deadman", "latch"):
            self._emit({"type": "rig", "kind": event.kind, "message": event.message})
        if event.kind == "latch" and isinstance(event.latch, Acknowledgement):  # acknowledged: no run keeps it
            with self._lock:
                kept = [r for r in self.runs.values() if r.latch is not None and r.id != self.current_id]
                for r in kept:
                    r.latch = None
                    r.cause = "acknowledged: it starts once the queue is released (POST /queue/release)" \
                        if r.state == "queued" else "acknowledged"
                if kept:
                    self._save()

    def close(self, timeout_s: float = 60.0) -> None:
        """End the worker; a run in progress stops cleanly and stays queued (it resumes at the next start)."""
        with self._lock:
            self._closing = True
            current = self.current
            self._wake.notify_all()
        self.end_streams()
        if self._unsubscribe_rig is not None:
            self._unsubscribe_rig()
            self._unsubscribe_rig = None
        if current is not None:
            current.abort()
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self.lsl is not None:
            self.lsl.close()
        self._file_lock.release()

    def _next(self) -> QueuedRun | None:
        with self._lock:
            while not self._closing:
                if not self.held:
                    for run in self.runs.values():
                        if run.state == "queued":
                            return run
                self._wake.wait(0.5)
        return None

    def _work(self) -> None:
        while True:
            run = self._next()
            if run is None:
                return
            self._record(run)

    def _protocol_run(self, run: QueuedRun, out: Path, resume: bool) -> ProtocolRun:
        proto = parse_protocol(run.protocol_source)
        if self.lsl is not None:
            self.lsl.protocol_name = proto.name
        return ProtocolRun(self.control, proto, out, resume=resume, overwrite=run.overwrite and not resume,
                           progress=lambda e: self._progress(run, e), on_trial=lambda e: self._trial(run, e),
                           prompt=lambda message: self._emit({"type": "plate", "id": run.id, "message": message}),
                           lsl=self.lsl if self.lsl is not None else False)

    def _fail(self, run: QueuedRun, exc: BaseException) -> None:
        with self._lock:
            self.current = self.current_id = None
            self._set(run, state="failed", errors=[*run.errors, self._shown(describe_error(exc))],
                      ended_utc=_utc_now())

    def _run_path(self, run: QueuedRun) -> Path:
        """The run's session path checked again as it starts: a subfolder replaced by a symlink since the run was
        queued (or anything else that breaks the folder's rules now) is refused, QueueError."""
        if self.data_dir is None:
            return Path(run.out)
        try:
            name = Path(run.out).relative_to(self.data_dir).as_posix()
        except ValueError:
            raise QueueError(f"{run.out} is not inside the data folder {self.data_dir}", 422) from None
        out = self._out_path(name, create=True)
        if str(out) != run.out:
            raise QueueError(f"out {name}: now resolves to {out}, not {run.out}", 422)
        return out

    def _record(self, run: QueuedRun) -> None:
        """Record ``run``: its path checked again as it starts, then written through the descriptor of its
        subfolder (:func:`rigctl.storage.outputs.opened_in_folder`: a subfolder flipped to a link meanwhile sends
        nothing elsewhere); messages name the path by name."""
        try:
            out = self._run_path(run)
            with contextlib.ExitStack() as held:
                if self.data_dir is not None:
                    name = Path(run.out).relative_to(self.data_dir).as_posix()
                    via = held.enter_context(opened_in_folder(self.data_dir, name))
                    self._alias = (str(via.parent), str(out.parent))
                    out = via
                self._record_at(run, out)
        except QueueError as exc:  # refused as it starts: failed, nothing written
            self._fail(run, exc)
        except OutputError as exc:
            self._fail(run, QueueError(str(exc), 422))
        finally:
            self._alias = None

    def _shown(self, text: str) -> str:
        """``text`` with the descriptor path of the run's folder as its name (``/proc/<pid>/fd/<n>`` -> the folder)."""
        alias = self._alias
        return text.replace(alias[0], alias[1]) if alias else text

    def _record_at(self, run: QueuedRun, out: Path) -> None:
        resume = run.starts > 0 and out.exists()
        # a session a killed server was writing stays locked while its journal helper finishes the last commit
        # (rigctl.storage.journal): a restart that resumes it at once waits for the lock, up to LOCKED_WAIT_S
        deadline = time.monotonic() + LOCKED_WAIT_S
        first = True
        while True:
            try:
                pr = self._protocol_run(run, out, resume)
            except Exception as exc:  # noqa: BLE001 - a run that cannot start fails, the queue goes on
                self._fail(run, exc)
                return
            with self._lock:
                self.current, self.current_id, self.current_trial = pr, run.id, None
                self._set(run, state="running", starts=run.starts + int(first),
                          started_utc=run.started_utc or _utc_now())
            first = False
            try:
                summary = pr.run()
            except SessionLocked as exc:
                if time.monotonic() < deadline and not self._closing:
                    time.sleep(LOCKED_POLL_S)
                    continue
                self._fail(run, exc)
                return
            except Exception as exc:  # noqa: BLE001
                self._fail(run, exc)
                return
            break
        with self._lock:
            self.current = self.current_id = None
            if self._closing and not summary.ok:  # the server is ending: resume at its next start
                self._set(run, state="queued", trials_done=summary.complete,
                          summary=[self._shown(line) for line in summary.lines()])
                return
            state = "done" if summary.ok else ("stopped" if summary.stopped else "failed")
            self._set(run, state=state, trials_done=summary.complete, trials_total=summary.planned,
                      errors=[*run.errors, *map(self._shown, summary.failures)],
                      summary=[self._shown(line) for line in summary.lines()], ended_utc=_utc_now())

    def _progress(self, run: QueuedRun, event: ProgressEvent) -> None:
        if event.total is not None and (event.done != run.trials_done or event.total != run.trials_total):
            with self._lock:  # written at most every PROGRESS_SAVE_S (a state change writes at once); a restart
                # resumes from the session file, which holds every finished trial
                run.trials_done, run.trials_total = int(event.done), int(event.total)
                if time.monotonic() - self._saved_t >= PROGRESS_SAVE_S:
                    self._save()
        self._emit({"type": "progress", "id": run.id, "stage": event.stage, "done": event.done,
                    "total": event.total, "message": event.message})

    def _trial(self, run: QueuedRun, event: TrialEvent) -> None:
        latch = self.control.latch
        if event.kind == "latched" and latch is not None:  # paused with its cause; kept across a restart
            self._set(run, state="paused", cause=f"latched: {latch.describe()}", latch=latch.to_dict())
        elif event.kind == "acknowledged":
            self._set(run, cause="acknowledged: nothing moves until the run is resumed (POST /runs/{id}/resume)"
                      .replace("{id}", run.id), latch=None)
        elif event.kind == "halted":
            self._set(run, cause="STOP: the trial in progress was discarded; resume records it again")
        elif event.kind == "paused":  # the rig at rest: the sensor released (or the actuator stranded by a latch)
            self._set(run, state="paused", cause=run.cause or "paused")
        elif event.kind == "resumed":
            self._set(run, state="running", cause="")
        p = event.planned
        if p is not None:
            self.current_trial = {"trial_id": p.trial_id, "texture": p.texture, "speed_mm_s": p.speed_mm_s,
                                  "force_g": p.force_g, "attempt": event.attempt, "event": event.kind}
        self._emit({"type": "trial", "id": run.id, "kind": event.kind, "index": event.index, "total": event.total,
                    "trial_id": None if p is None else p.trial_id, "texture": None if p is None else p.texture,
                    "error": event.error, "attempt": event.attempt})
