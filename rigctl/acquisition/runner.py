"""The trial runner: records a protocol's plan into a session file, trial by trial, resumable.

Per trial (paper, Materials and Methods): mount the texture when it changes (simulation: set it; hardware: prompt the
operator), force setpoint and wait until settled, speed (or ramp) setpoint and wait until steady, record the trial's
duration, stop the drum; write the trial to the session file in one go (:meth:`SessionWriter.write_trial`).

Run control, for the CLI and the GUI alike:

- ``progress``: a callback receiving :class:`rigctl.core.progress.ProgressEvent` s (stage = the protocol's name,
  done/total = complete trials of the plan; a message per trial started and per retry, failure or link note);
  None prints nothing (notes go to the log). The CLI draws them as a tqdm bar;
- ``on_trial(event)``: a :class:`TrialEvent` when each trial starts and ends (complete / failed), when an attempt is
  recorded again (retry) and while a write waits for the session file (waiting);
- ``stop_event`` (set it), Ctrl-C (KeyboardInterrupt) or SIGTERM (handled like Ctrl-C while the run lasts, when it
  runs in the main thread; the previous handlers are restored afterwards): clean stop: the trial in progress is
  discarded, the rig is left safe (STOP: drum stopped, actuator backed off), every finished trial stays in the
  file, and the run can be resumed. A trial being written is written first (the signal is held until then; a second
  one stops at once);
- ``pause_event``: while it is set the runner waits between trials with the rig released (no force applied, so the
  controller's watchdog cannot trip); clear it to continue;
- ``halt_event`` (STOP, :meth:`rigctl.operations.ProtocolRun.stop`): the trial in progress is cut short and
  discarded, the rig stopped, and the run pauses (``pause_event`` is set with it); resuming records that trial
  again. Abort (``stop_event``) is the separate action that ends the run;
- the safety latch (:mod:`rigctl.acquisition.safety`, docs/safety.md): a latched fault (e-stop, over-force, reversed
  cell, watchdog, unexpected reset, HOME failure, stall, drum link lost mid-press) is never cleared here and never
  retried: the rig is stopped and, with ``on_latch="wait"`` (the GUI, the server), the run pauses (``pause_event``
  set) until an operator acknowledges it (:meth:`rigctl.acquisition.rig.Rig.acknowledge`, which moves nothing) and
  then starts it (``pause_event`` cleared: Resume), as after STOP; it then records the trial again. With ``"end"``
  (``rigctl acquire``) it ends, resumable (``RunSummary.latched`` says why), and resuming is the acknowledgement
  (``acknowledge``) and the start. Every latch and acknowledgement is written into the session's event log
  (:meth:`rigctl.storage.session.SessionWriter.log_event`), within 50 ms also while the run is paused;
- ``resume=True``: continue an interrupted session file from its ``/plan`` (refused if the protocol source differs);
  complete trials are never recorded again, failed and pending ones are.

Python protocols run in the same engine: ``plan(ctx)`` (:mod:`rigctl.acquisition.plans`) yields each trial, which
is appended to the session's plan and recorded under all of the above, and gets its recording back; on resume the
plan runs again and the trials the file holds are sent back from it.

Trial quality (the protocol's ``max_dropped_frames`` and ``retries``): a trial that lost more frames than
``max_dropped_frames`` (sequence gaps among its kept frames, ``TrialData.dropped_frames``) is never stored as
complete. It is recorded again at once, like a trial that failed (timeout, fault, lost stream; after
:meth:`Rig.recover`), up to ``retries`` times; then it is marked failed in the plan with the reason, and the run
continues (``on_failure="continue"``) or stops (``"stop"``). A trial kept with some losses (``max_dropped_frames`` >
0) carries its ``dropped_frames``; the summary counts such trials (``lossy``).

A lost link ends the run after a bounded time, not trial by trial: when a failed attempt leaves a link down (the
drum controller does not answer, or no taxel frame arrives: :meth:`Rig.recover`), the runner waits for it to come
back (a vanished port is reopened by its client) and goes on; after :data:`LINK_LOSS_ATTEMPTS` attempts in a row
failing with a link down, or :data:`LINK_LOSS_S` seconds of waiting since the first of them, it stops (``stopped``,
``link_lost`` says why): finished trials intact, the session resumable.

A reader holding the session file never costs a recorded trial: the trial is kept in memory, the rig released and
the write retried, reporting, for as long as the file is held.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigctl.acquisition.calibration import session_calibration_block
from rigctl.acquisition.labels import recorded_labels
from rigctl.acquisition.plans import PlanContext
from rigctl.acquisition.protocol import Protocol, ScriptProtocol
from rigctl.acquisition.provenance import session_provenance
from rigctl.acquisition.rig import CaptureError, Rig, TrialAborted
from rigctl.acquisition.safety import Acknowledgement, Latch, operator_name
from rigctl.core.errors import describe_error
from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.provenance import PROVENANCE_ATTR, provenance_json
from rigctl.core.trial import REPEATED_SAMPLES_FLAG, PlannedTrial, TrialData, repeated_samples
from rigctl.storage.session import SessionError, SessionWriter, TrialStatus

log = logging.getLogger(__name__)

#: a lost link ends the run after this many trial attempts in a row that failed and left a link down ...
LINK_LOSS_ATTEMPTS = 3
#: ... or once a link has been down this long since the first of them, s
LINK_LOSS_S = 60.0
#: how often the runner checks whether a lost link is back, s
LINK_POLL_S = 0.5
#: a trial's first write waits this long for the session file (less than the controller's watchdog: the force loop
#: is still engaged), s
FIRST_WRITE_WAIT_S = 0.5
#: then, with the rig released, each further write attempt waits this long, reporting in between, until written, s
WRITE_RETRY_S = 10.0
#: while latched (``on_latch="wait"``) the runner reads the controller's status this often, on the drum client's
#: clock (simulated in-process), s
LATCH_POLL_S = 0.1
#: what ``on_latch`` takes
ON_LATCH = ("end", "wait")


class LostFramesError(CaptureError):
    """A recorded trial lost more frames than the protocol's ``max_dropped_frames`` allows."""


@dataclass
class TrialEvent:
    """What :func:`run_protocol` reports to ``on_trial``.

    Attributes
    ----------
    kind : "start" | "complete" | "failed" | "retry" (an attempt failed, the trial is recorded again) | "link_down"
        (a failed attempt left a link down; the runner waits for it) | "waiting" (the session file is held by another
        process; the trial is kept until written) | "texture" (a plate is being mounted) | "paused" | "resumed" |
        "halted" (STOP: the trial in progress discarded, the run paused) | "latched" (a latched fault, the rig at rest:
        ``error`` says which and what clears it) | "acknowledged" (an operator cleared it; the run stays paused until
        its start, then records the trial again)
    planned : the trial (None for "paused"/"resumed")
    index : 0-based position among the trials this run records
    total : how many trials this run records
    data : the recorded TrialData ("complete" only)
    error : the failure in words ("failed", "retry"; "link_down": the link problem; "waiting": what holds the write)
    elapsed_s : wall time since the run started
    eta_s : estimated wall time left (NaN before the first trial ends)
    attempt : 1 for a trial's first recording, 2 for its first retry, ...
    """

    kind: str
    planned: PlannedTrial | None
    index: int
    total: int
    data: TrialData | None = None
    error: str = ""
    elapsed_s: float = 0.0
    eta_s: float = math.nan
    attempt: int = 1


@dataclass
class RunSummary:
    """Outcome of :func:`run_protocol`.

    ``planned`` trials in the file's plan, ``complete`` (in the file, including earlier runs), ``recorded`` (by this
    run), ``failed`` (this run), ``retried`` (attempts recorded again, this run), ``lossy`` (trials kept with lost
    frames, within the protocol's ``max_dropped_frames``), ``samples``/``dropped_frames``/``crc_errors`` (this
    run's kept trials), ``stopped`` (interrupted by stop_event, Ctrl-C, SIGTERM, a lost link or a latched fault),
    ``link_lost`` (why a lost link ended the run, else ""), ``latched`` (the latched fault that ended it, in words,
    else ""), ``elapsed_s``, ``path``, ``failures`` (one line per failed trial).
    """

    path: Path
    planned: int = 0
    complete: int = 0
    recorded: int = 0
    failed: int = 0
    retried: int = 0
    lossy: int = 0
    samples: int = 0
    dropped_frames: int = 0
    crc_errors: int = 0
    #: samples identical on every taxel to the one before (rigctl.core.trial.repeated_samples), in ``held`` trials
    repeated: int = 0
    held: int = 0
    stopped: bool = False
    link_lost: str = ""
    latched: str = ""
    elapsed_s: float = 0.0
    failures: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.stopped and self.failed == 0 and self.complete == self.planned

    def _recorded_line(self) -> str:
        """What this run recorded: samples, lost frames (and in how many kept trials, when any), CRC errors."""
        if self.recorded == 0:
            return ("  nothing recorded now: every planned trial was already complete" if self.complete == self.planned
                    else "  nothing recorded now")
        lossy = f" (in {self.lossy} kept trials)" if self.lossy else ""
        held = f" (in {self.held} trials)" if self.held else ""
        return (f"  samples: {self.samples}  dropped frames: {self.dropped_frames}{lossy}  repeated samples: "
                f"{self.repeated}{held}  CRC errors: {self.crc_errors}")

    def lines(self) -> list[str]:
        if self.latched:
            state = (f"stopped on a latched fault: {self.latched}. Nothing moves until then: run the same command "
                     "with --resume to acknowledge it (logged in the session) and go on")
        elif self.link_lost:
            state = f"stopped: link lost: {self.link_lost} (resume with --resume once the rig answers again)"
        else:
            state = "stopped early (resume with --resume)" if self.stopped else "finished"
        out = [
            f"session {self.path}: {state} in {self.elapsed_s:.1f} s",
            f"  trials complete: {self.complete}/{self.planned} (recorded now: {self.recorded}, failed now: "
            f"{self.failed}, attempts recorded again: {self.retried})",
            self._recorded_line(),
        ]
        out += [f"  failed: {f}" for f in self.failures]
        return out


def _emit(cb, event: TrialEvent) -> None:
    if cb is not None:
        cb(event)


def _check_replay_plan(rig: Any, protocol: Any) -> None:
    """Before anything is recorded: a replayed recording (a source with ``check_plan``, rigctl.simulation.replay)
    must give each planned trial a source trial of its own, of its texture; it raises naming the shortfall."""
    backend = getattr(rig, "backend", None)
    source = getattr(getattr(backend, "sim", None), "source", None) or getattr(backend, "source", None)
    check = getattr(source, "check_plan", None)
    plan = getattr(protocol, "plan", None)
    if check is not None and callable(plan) and not getattr(rig, "replay_continuous", False):
        check([str(p.texture) for p in plan()])


class _Interrupts:
    """Ctrl-C (SIGINT) and SIGTERM during a run raise KeyboardInterrupt (a clean stop); held while the session file
    is written (:meth:`held`: the first signal then waits for :meth:`raise_pending`, a second one raises at once).

    Installed only in the main thread (the only one that may set signal handlers); SIGINT only while Python's
    default handler is in place, neither signal where it is ignored. The previous handlers are restored on exit.
    """

    def __init__(self):
        self._previous: dict[int, Any] = {}
        self._holding = 0
        self.pending: int | None = None

    def __enter__(self) -> "_Interrupts":
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig in (signal.SIGINT, signal.SIGTERM):
            prev = signal.getsignal(sig)
            if prev is None or prev is signal.SIG_IGN or (sig == signal.SIGINT and prev is not signal.default_int_handler):
                continue
            try:
                signal.signal(sig, self._handle)
            except ValueError:  # not the main interpreter
                continue
            self._previous[sig] = prev
        return self

    def __exit__(self, *exc) -> None:
        for sig, prev in self._previous.items():
            signal.signal(sig, prev)
        self._previous.clear()

    def _handle(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self._holding and self.pending is None:
            self.pending = signum
            log.warning("%s: stopping once the session file is written (again to stop at once, losing the trial "
                        "being written)", name)
            return
        raise KeyboardInterrupt(name)

    @contextlib.contextmanager
    def held(self):
        self._holding += 1
        try:
            yield
        finally:
            self._holding -= 1

    def raise_pending(self) -> None:
        if self.pending is not None:
            name = signal.Signals(self.pending).name
            self.pending = None
            raise KeyboardInterrupt(name)


class _StopFlag:
    """What a trial checks to stop: abort (``stop_event``) or STOP (``halt_event``)."""

    def __init__(self, *events: threading.Event | None) -> None:
        self.events = [e for e in events if e is not None]

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


def _wait_while_paused(rig: Rig, pause_event, stop_event, on_trial, index, total, t0,
                       tick: Callable[[], object] | None = None, halt_event=None) -> None:
    """While ``pause_event`` is set: the rig stopped and the sensor released (``paused`` is reported only then), wait
    for the start (the event cleared: Resume) or an abort; ``tick()`` runs every 50 ms meanwhile (the run writes the
    latches and acknowledgements of the wait into its session at once). A STOP (``halt_event``) that finds the run
    paused here has no trial to discard: cleared, and ``paused`` reported again (a Resume and a STOP within one 50 ms
    look left a served run ``pausing`` for good, issue 76); never cleared after the wait let the run go on."""
    if pause_event is None or not pause_event.is_set():
        return
    rig.recover()  # STOP (a latched fault stays latched): no force on the sensor while paused
    halt = halt_event if halt_event is not None else threading.Event()
    while pause_event.is_set():
        halt.clear()  # the STOP that paused the run (or one while it is paused): served by this wait
        rig.wait_at_rest()
        _emit(on_trial, TrialEvent("paused", None, index, total, elapsed_s=time.monotonic() - t0))
        while pause_event.is_set() and not halt.is_set():
            if tick is not None:
                tick()
            if stop_event is not None and stop_event.is_set():
                return
            time.sleep(0.05)
    _emit(on_trial, TrialEvent("resumed", None, index, total, elapsed_s=time.monotonic() - t0))


def run_protocol(
    protocol: Protocol | ScriptProtocol,
    out_path: str | Path,
    *,
    rig: Rig,
    resume: bool = False,
    progress: ProgressCallback | None = None,
    stop_event: threading.Event | None = None,
    pause_event: threading.Event | None = None,
    on_trial: Callable[[TrialEvent], Any] | None = None,
    prompt: Callable[[str], Any] | None = None,
    on_failure: str = "continue",
    overwrite: bool = False,
    session_attrs: Mapping[str, Any] | None = None,
    on_latch: str = "end",
    halt_event: threading.Event | None = None,
    acknowledge: tuple[str, str] | None = None,
) -> RunSummary:
    """Record ``protocol`` on ``rig`` into the session file ``out_path``.

    Parameters
    ----------
    protocol : a loaded protocol (:func:`rigctl.acquisition.protocol.load_protocol`): TOML, or Python (its
        ``plan(ctx)``); a TOML protocol's ``max_dropped_frames`` and ``retries`` set the trial quality policy (module
        docstring; a Python protocol: none lost, 2 retries).
    out_path : session file (``.h5``); must not exist unless ``resume`` or ``overwrite``.
    rig : an open :class:`rigctl.acquisition.rig.Rig` (:func:`rigctl.rigs.open_rig`). Its texture set becomes the
        protocol's (:attr:`Protocol.texture_set`), which the session stores with the taxel source's layout.
    resume : continue the existing file from its plan.
    progress : callback receiving :class:`~rigctl.core.progress.ProgressEvent` s (module docstring); None: none.
    stop_event, pause_event : run control (see the module docstring).
    on_trial : callback receiving :class:`TrialEvent` s (called from the thread running this function).
    prompt : operator prompt for plate changes on hardware (default: the rig's).
    on_failure : "continue" or "stop" after a trial failed (its retries used up).
    overwrite : replace an existing ``out_path`` (not with ``resume``).
    session_attrs : more root attributes of a new session file (e.g. the LSL streams and clock offset).
    on_latch : "end" (the run ends, resumable) or "wait" (it pauses: an acknowledgement, then a start, the
        ``pause_event`` cleared) on a latched fault.
    halt_event : STOP (module docstring): set it (with ``pause_event``) to cut the trial short and pause.
    acknowledge : ``(reason, by)``: with ``resume``, a latched fault the session's event log holds unacknowledged
        is acknowledged by this run (``rigctl acquire --resume``: the operator is present); default ("run resumed",
        the login name).

    Returns
    -------
    RunSummary

    Raises
    ------
    FileExistsError (out_path exists, no resume/overwrite), FileNotFoundError (resume without a file),
    SessionError (resume with a different protocol; a Python plan that yields other trials than the file holds),
    ValueError (bad on_failure or on_latch).
    KeyboardInterrupt (Ctrl-C) and SIGTERM are caught: the run stops cleanly and the summary says ``stopped``.
    """
    if on_failure not in ("continue", "stop"):
        raise ValueError(f"on_failure must be 'continue' or 'stop', got {on_failure!r}")
    if on_latch not in ON_LATCH:
        raise ValueError(f"on_latch must be one of {', '.join(ON_LATCH)}, got {on_latch!r}")
    if on_latch == "wait" and pause_event is None:
        raise ValueError("on_latch='wait' needs a pause_event: after the acknowledgement the run waits for a "
                         "separate start (the event cleared)")
    out_path = Path(out_path)
    script = isinstance(protocol, ScriptProtocol)
    with _Interrupts() as interrupts:
        if isinstance(protocol, Protocol):
            rig.apply_settle(protocol.settle)
            rig.textures = protocol.texture_set
        textures = rig.textures
        if not resume:
            _check_replay_plan(rig, protocol)
        if resume:
            writer = SessionWriter.open(out_path, protocol_source=protocol.source)
            # the trials from here on are this run's: its software, firmware and rig, beside the creating run's
            writer.note_resume(session_provenance(rig.describe(), protocol=protocol))
        else:
            described = rig.describe()
            writer = SessionWriter.create(
                out_path, plan=protocol.plan(), layout=rig.layout, textures=textures,
                protocol_source=protocol.source, protocol_name=protocol.name,
                protocol_format="python" if script else "toml", rig_config=described, kind="recorded",
                calibration=session_calibration_block(rig.host_config, rig.layout.n_channels),
                attrs={PROVENANCE_ATTR: provenance_json(session_provenance(described, protocol=protocol)),
                       **dict(session_attrs or {})},
                overwrite=overwrite,
            )
        run = _Run(protocol, writer, out_path, rig, interrupts=interrupts, progress=progress, stop_event=stop_event,
                   on_trial=on_trial, prompt=prompt, on_failure=on_failure, on_latch=on_latch,
                   halt_event=halt_event)
        run.log_acknowledgements_at_start(resume, acknowledge)
        return run.run(pause_event)


class _Run:
    """One run of a protocol (:func:`run_protocol`): the trial loop, retries, link watch, safety latch, writes."""

    def __init__(self, protocol: Protocol | ScriptProtocol, writer: SessionWriter, out_path: Path, rig: Rig, *,
                 interrupts: _Interrupts, progress: ProgressCallback | None, stop_event, on_trial, prompt,
                 on_failure: str, on_latch: str = "end", halt_event: threading.Event | None = None):
        self.protocol, self.writer, self.rig, self.interrupts = protocol, writer, rig, interrupts
        self.script = protocol if isinstance(protocol, ScriptProtocol) else None
        # what a replay rig does between trials
        rig.replay_continuous = self.script is None and getattr(protocol, "replay", "") == "continuous"
        self.progress, self.stop_event, self.on_trial, self.prompt = progress, stop_event, on_trial, prompt
        self.on_failure, self.on_latch, self.halt_event = on_failure, on_latch, halt_event
        self.max_dropped_frames = 0 if self.script else protocol.max_dropped_frames  # type: ignore[union-attr]
        self.retries = 2 if self.script else protocol.retries  # type: ignore[union-attr]
        self.plan = [PlannedTrial.from_row(r) for r in writer.plan]
        self.todo = [p for p, st in zip(self.plan, writer.plan["status"]) if st != TrialStatus.COMPLETE]
        self.summary = RunSummary(path=out_path, planned=len(self.plan))
        self.total = (self.script.max_trials or 0) if self.script else len(self.todo)
        #: the last trial's recording (None: failed), what a Python plan's yield returns
        self.last_data: TrialData | None = None
        self._safety_log: list[Latch | Acknowledgement] = []  # latches and acks to write into the event log
        self._safety_lock = threading.Lock()
        rig.safety.listeners.append(self._note_safety)
        self.t0 = time.monotonic()
        self.bar: Stage | None = None
        self.durations: list[float] = []
        self.link_failures = 0  # attempts in a row that failed and left a link down
        self.link_down_since: float | None = None

    def _stopping(self) -> bool:
        return self.stop_event is not None and self.stop_event.is_set()

    def _elapsed(self) -> float:
        return time.monotonic() - self.t0

    def _eta(self, left: int) -> float:
        return (sum(self.durations) / len(self.durations)) * left if self.durations else math.nan

    def _report(self, message: str) -> None:
        if self.bar is not None:
            self.bar.note(message)
        else:
            log.warning("%s", message)

    def _event(self, kind: str, planned, index: int, **kw) -> None:
        _emit(self.on_trial, TrialEvent(kind, planned, index, self.total, elapsed_s=self._elapsed(), **kw))

    def run(self, pause_event) -> RunSummary:
        summary = self.summary
        self.pause_event = pause_event
        if self.progress:
            if self.script is not None:
                self.bar = Stage(self.progress, self.protocol.name, self.total,
                                 done=len(self.writer.completed_ids()))
            else:
                self.bar = Stage(self.progress, self.protocol.name, len(self.plan), done=len(self.plan) - self.total)
        try:
            for index, planned in enumerate(self._trials()):
                if self._stopping():
                    summary.stopped = True
                    break
                _wait_while_paused(self.rig, pause_event, self.stop_event, self.on_trial, index, self.total,
                                   self.t0, tick=self._flush_safety, halt_event=self.halt_event)
                if self._stopping():
                    summary.stopped = True
                    break
                go_on = self._trial(index, planned)
                self.interrupts.raise_pending()
                if not go_on:
                    break
        except KeyboardInterrupt:
            summary.stopped = True
        finally:
            with self.interrupts.held():  # a signal now cannot cut the clean-up short: the run ends anyway
                self.rig.safe_stop()
                with contextlib.suppress(Exception):  # the event log is written best-effort at the end
                    self._flush_safety()
                self.rig.safety.listeners.remove(self._note_safety)
                summary.complete = len(self.writer.completed_ids())
                summary.planned = len(self.writer.plan)
                self.writer.close()
            self.interrupts.pending = None
        summary.elapsed_s = self._elapsed()
        return summary

    # ------------------------------------------------------------------------------------------------- the trials
    def _trials(self) -> Iterator[PlannedTrial]:
        """The trials to record: a TOML protocol's not yet complete, or what a Python plan yields (each sent its
        recording back: :attr:`last_data`)."""
        if self.script is None:
            yield from self.todo
            return
        ctx = PlanContext(self.rig.textures, self.rig.layout, self._report)
        gen = self.script.plan_function(ctx)
        k = 0
        try:
            request = next(gen)
            while True:
                planned, stored = self._plan_row(k, request)
                if stored is not None:
                    result: TrialData | None = stored  # recorded by an earlier run: sent back from the file
                else:
                    self.last_data = None
                    yield planned
                    result = self.last_data
                k += 1
                request = gen.send(result)
        except StopIteration:
            return
        finally:
            gen.close()

    def _plan_row(self, k: int, request: PlannedTrial) -> tuple[PlannedTrial, TrialData | None]:
        """The plan's ``k``-th yield: the file's ``k``-th plan row (checked to be the same trial; its recording when
        complete) or a new row appended to the plan."""
        from rigctl.storage.session import open_session

        if not isinstance(request, PlannedTrial):
            raise TypeError(f"a plan yields ctx.trial(...), got {type(request).__name__}")
        plan = self.writer.plan
        if k >= len(plan):
            tid = self.writer.append_trial(dataclasses.replace(request, trial_id=self.writer.next_trial_id()))
            return dataclasses.replace(request, trial_id=tid), None
        row = PlannedTrial.from_row(plan[k])
        same = row.texture == request.texture and all(
            math.isclose(a, b, rel_tol=1e-5, abs_tol=1e-6) for a, b in (
                (row.force_g, request.force_g), (row.speed_mm_s, request.speed_mm_s),
                (row.duration_s, request.duration_s)))  # the plan table stores float32
        if not same:
            raise SessionError(f"{self.summary.path}: the plan's trial {k + 1} ({request.texture}, "
                               f"{request.speed_mm_s:g} mm/s, {request.force_g:g} g) is not the file's ({row.texture}, "
                               f"{row.speed_mm_s:g} mm/s, {row.force_g:g} g): a resumed plan must yield the same "
                               "trials from the same recordings")
        if plan["status"][k] != TrialStatus.COMPLETE:
            return row, None
        with open_session(self.summary.path) as session:
            return row, session.trial(row.trial_id)

    # ------------------------------------------------------------------------------------------------- safety
    def _note_safety(self, item: Latch | Acknowledgement) -> None:
        with self._safety_lock:  # from any thread (an acknowledgement comes from a face); written by the run's
            self._safety_log.append(item)
        if isinstance(item, Acknowledgement) and getattr(self.rig, "unlogged_acknowledgement", None) is item:
            self.rig.unlogged_acknowledgement = None  # this run's session logs it

    def _flush_safety(self) -> None:
        """Write the latches and acknowledgements seen since the last call into the session's event log."""
        with self._safety_lock:
            items, self._safety_log = self._safety_log, []
        for item in items:
            if isinstance(item, Latch):
                self.writer.log_event("latched", **item.to_dict())
            else:
                self.writer.log_event("acknowledged", **item.to_dict())

    def log_acknowledgements_at_start(self, resume: bool, acknowledge: tuple[str, str] | None) -> None:
        """The acknowledgements this run starts with, into its session's event log: on resume, a latch the event
        log holds without its acknowledgement is acknowledged now (the operator resumes the run: ``acknowledge``'s
        reason and who, default "run resumed" and the login name), logged with the fault it clears; and the
        acknowledgement an operator gave when the rig opened (:attr:`Rig.acknowledged_at_open`: ``--ack``), unless
        it is that same one. Opening itself never acknowledges (docs/safety.md)."""
        resolved = getattr(self.rig, "resolved_at_open", None)
        if resolved:  # configured at open, not acknowledged (Rig._resolve_by_config)
            for res in resolved:
                self.writer.log_event("resolved", **res.to_dict())
            self.rig.resolved_at_open = []
        at_open = getattr(self.rig, "acknowledged_at_open", None)
        last = getattr(self.rig, "unlogged_acknowledgement", None)  # e.g. POST /ack while no run was going
        if at_open is not None:
            self.rig.acknowledged_at_open = None
        if last is not None:
            self.rig.unlogged_acknowledgement = None
        given = at_open or last
        reason, by = acknowledge or ((given.reason, given.by) if given is not None
                                     else ("run resumed", operator_name()))
        events = self.writer.events() if resume else []
        kinds = [e.get("kind") for e in events]
        if "latched" in kinds:
            last = len(kinds) - 1 - kinds[::-1].index("latched")
            if "acknowledged" not in kinds[last:]:
                clears = {k: v for k, v in events[last].items() if k != "kind"}
                self.writer.log_event("acknowledged", clears=clears, reason=reason, by=by)
                self._report(f"acknowledged by {by} ({reason}): {clears.get('cause', '?')}: "
                             f"{clears.get('detail', '')}")
                return
        if at_open is not None:
            self.writer.log_event("acknowledged", **at_open.to_dict())
            self._report(f"acknowledged by {at_open.by} ({at_open.reason}) when the rig opened: "
                         f"{at_open.latch.describe()}")

    def _on_latch(self, planned: PlannedTrial, index: int) -> bool:
        """The rig latched a fault: log it; end the run (``on_latch="end"``: False) or wait for an operator's
        acknowledgement (True then; False when the run is aborted meanwhile)."""
        latch = self.rig.safety.latch
        if latch is None:
            return True
        self._flush_safety()
        self.rig.wait_at_rest()  # the actuator backed off (or stranded where a stop of category 0 left it)
        latch = self.rig.safety.latch or latch  # a second fault latched meanwhile: both named
        self._event("latched", planned, index, error=latch.describe())
        self._report(f"LATCHED {latch.describe()}")
        if self.on_latch == "end":
            self.summary.stopped = True
            self.summary.latched = latch.describe()
            return False
        # the run pauses: after the acknowledgement it waits for a separate start (Resume), as after STOP
        self.pause_event.set()
        clock = self.rig.drum.clock
        while self.rig.safety.latched:
            if self._stopping():
                self.summary.stopped = True
                return False
            self._flush_safety()  # a second fault latched meanwhile: into the session at once
            with contextlib.suppress(Exception):  # a silent controller: keep waiting for the operator
                self.rig.drum.read_status()
            if not self.rig.safety.wait_cleared(0.02):
                clock.sleep(LATCH_POLL_S)
        self._flush_safety()
        self._event("acknowledged", planned, index)
        self._report(f"acknowledged: {latch.label}; the run stays paused until it is resumed (trial "
                     f"{planned.trial_id} is recorded again then)")
        _wait_while_paused(self.rig, self.pause_event, self.stop_event, self.on_trial, index, self.total, self.t0,
                           tick=self._flush_safety, halt_event=self.halt_event)
        if self._stopping():
            self.summary.stopped = True
            return False
        return True

    def _trial(self, index: int, planned: PlannedTrial) -> bool:
        """Record one trial, with its retries; False when the run must stop."""
        rig, summary = self.rig, self.summary
        where = (f"trial {planned.trial_id} ({planned.texture}, {planned.speed_mm_s:g} mm/s, "
                 f"{planned.force_g:g} g)")
        attempt = 0
        t_trial = time.monotonic()
        stop = _StopFlag(self.stop_event, self.halt_event)
        while True:
            attempt += 1
            eta = self._eta(self.total - index)
            try:
                if rig.texture != planned.texture:
                    self._event("texture", planned, index, eta_s=eta, attempt=attempt)
                    rig.mount_texture(planned.texture, prompt=self.prompt)
                self._event("start", planned, index, eta_s=eta, attempt=attempt)
                if self.bar is not None:
                    self.bar.advance(0, f"{planned.texture} {planned.profile + ' ' if planned.is_ramp else ''}"
                                        f"{planned.speed_mm_s:g} mm/s {planned.force_g:g} g")
                data = rig.record_trial(planned, stop_event=stop)
                limit = self.max_dropped_frames
                if data.dropped_frames > limit:
                    raise LostFramesError(f"{data.dropped_frames} frames lost on the taxel link ({data.crc_errors} "
                                          f"CRC errors), more than max_dropped_frames = {limit}")
            except TrialAborted:
                if self._stopping() or not self._halted(planned, index):
                    summary.stopped = True
                    return False
                attempt -= 1  # STOP: the trial is recorded again once the run resumes; no attempt is used up
                continue
            except Exception as exc:  # noqa: BLE001 - a failed attempt is retried or recorded as failed
                outcome = self._failed_attempt(exc, planned, index, attempt, where, eta)
                if outcome == "again":  # a latched fault acknowledged: no attempt is used up
                    attempt -= 1
                    continue
                if outcome == "retry":
                    continue
                return outcome == "continue"
            break
        self.link_failures, self.link_down_since = 0, None
        data.attrs["attempts"] = attempt
        data.attrs["repeated_samples"] = repeated = repeated_samples(data.taxels)  # any source: counted, kept
        labels = recorded_labels(planned, data.attrs)  # a replayed trial: the source trial's condition
        self._write(f"writing trial {planned.trial_id}",
                    lambda: self.writer.write_trial(planned.trial_id, data, labels=labels or None), planned, index)
        summary.recorded += 1
        summary.samples += data.n_samples
        summary.dropped_frames += data.dropped_frames
        summary.crc_errors += data.crc_errors
        summary.repeated, summary.held = summary.repeated + repeated, summary.held + bool(repeated)
        if repeated > REPEATED_SAMPLES_FLAG * data.n_samples:
            log.warning("%s: %d of %d samples repeat the one before on every taxel (a held reading?)", where,
                        repeated, data.n_samples)
        if data.dropped_frames:
            summary.lossy += 1
            log.warning("%s kept with %d lost frames (max_dropped_frames = %d)", where, data.dropped_frames,
                        self.max_dropped_frames)
        self.durations.append(time.monotonic() - t_trial)
        self._event("complete", planned, index, data=data, eta_s=self._eta(self.total - index - 1),
                    attempt=attempt)
        self.last_data = data
        if self.bar is not None:
            self.bar.advance(1)
        return True

    def _halted(self, planned: PlannedTrial, index: int) -> bool:
        """STOP cut the trial short (``halt_event``): the rig stopped, the run paused; wait for resume. False when
        it was no STOP (an abort)."""
        if self.halt_event is None or not self.halt_event.is_set():
            return False
        self.halt_event.clear()
        self.rig.safe_stop()
        self._event("halted", planned, index, error="STOP: the trial was discarded; it is recorded again on resume")
        self._report(f"STOP: trial {planned.trial_id} discarded, the run is paused (resume to record it again)")
        _wait_while_paused(self.rig, self.pause_event, self.stop_event, self.on_trial, index, self.total, self.t0,
                           tick=self._flush_safety, halt_event=self.halt_event)
        return not self._stopping()

    def _failed_attempt(self, exc: Exception, planned: PlannedTrial, index: int, attempt: int, where: str,
                        eta: float) -> str:
        """After a failed attempt: "again" (a latched fault was acknowledged: record the trial again), "retry",
        "continue" (marked failed; go on with the next trial) or "stop" (the run ends)."""
        summary = self.summary
        error = describe_error(exc)
        lost = self._after_failure(planned, index)
        if self.rig.safety.latched:  # never retried, never cleared here (docs/safety.md)
            return "again" if self._on_latch(planned, index) else "stop"
        if (attempt <= self.retries and not lost and not self._stopping()
                and not isinstance(exc, ValueError)):
            summary.retried += 1
            self._event("retry", planned, index, error=error, eta_s=eta, attempt=attempt)
            self._report(f"RETRY {where}, attempt {attempt} failed: {error}")
            return "retry"
        if attempt > 1:
            error += f" (after {attempt} attempts)"
        reason = f"{where}: {error}"
        self._write(f"marking trial {planned.trial_id} failed",
                    lambda: self.writer.mark_failed(planned.trial_id, error), planned, index)
        summary.failed += 1
        summary.failures.append(reason)
        self._event("failed", planned, index, error=reason, eta_s=eta, attempt=attempt)
        self._report(f"FAILED {reason}")
        self.last_data = None
        if lost:
            summary.stopped = True
            summary.link_lost = lost
            self._report(f"STOPPED: link lost: {lost}; every finished trial is in {self.summary.path}, "
                         "resume with --resume once the rig answers again")
            return "stop"
        return "continue" if self.on_failure != "stop" else "stop"

    def _after_failure(self, planned: PlannedTrial, index: int) -> str:
        """After a failed attempt: recover the rig; if a link stays down, wait (bounded) for it to come back.

        Returns "" to go on, else why the run must end (the link is lost).
        """
        problem = self.rig.recover()
        if problem is None or self.rig.safety.latched:  # a latch is the operator's, not a link wait
            self.link_failures, self.link_down_since = 0, None
            return ""
        now = time.monotonic()
        self.link_failures += 1
        if self.link_down_since is None:
            self.link_down_since = now
        if self.link_failures >= LINK_LOSS_ATTEMPTS:
            return f"{problem}; {self.link_failures} attempts in a row failed with a link down"
        deadline = self.link_down_since + LINK_LOSS_S
        self._report(f"link down: {problem}; waiting up to {max(0.0, deadline - now):.0f} s for it to come back")
        self._event("link_down", planned, index, error=problem)
        while not self._stopping():
            left = deadline - time.monotonic()
            if left <= 0:
                return f"{problem}; down for {time.monotonic() - self.link_down_since:.0f} s"
            time.sleep(min(LINK_POLL_S, left))
            problem = self.rig.check_links() or ""
            if not problem:
                self._report(f"link back after {time.monotonic() - self.link_down_since:.1f} s")
                return ""
        return ""

    def _write(self, what: str, write: Callable[[], None], planned: PlannedTrial, index: int) -> None:
        """Run a session-file write; while another process (a reader) holds the file, keep the trial in memory,
        release the rig (so the controller's watchdog cannot trip) and keep trying, reporting, until it is written.
        Ctrl-C/SIGTERM are held during the write (a second one stops at once)."""
        from rigctl.storage.journal import FileBusy

        writer = self.writer
        wait_s = writer.wait_s
        writer.wait_s = FIRST_WRITE_WAIT_S
        t_busy: float | None = None
        try:
            while True:
                try:
                    with self.interrupts.held():
                        fed = getattr(self.rig, "while_fed", None)  # the watchdog fed meanwhile (Rig.while_fed)
                        if fed is not None:
                            fed(write)
                        else:
                            write()
                    return
                except FileBusy as exc:
                    if t_busy is None:
                        t_busy = time.monotonic()
                        self.rig.recover()
                        writer.wait_s = WRITE_RETRY_S
                    msg = (f"{what}: {exc}; held for {time.monotonic() - t_busy:.0f} s: the rig is released, the "
                           "data kept in memory until the file is free")
                    self._report(msg)
                    self._event("waiting", planned, index, error=msg)
        finally:
            writer.wait_s = wait_s
