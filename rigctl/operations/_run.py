"""Run, pause, resume and abort a protocol: :class:`ProtocolRun`, the one run control of the CLI and the GUI.

A run records a protocol's plan into a session file (:func:`rigctl.acquisition.runner.run_protocol`, which owns the
trial loop, the retries, the safety latch and the clean stops); this object holds its controls: :meth:`pause`
(between trials, the sensor released), :meth:`stop` (STOP: the drum stopped and the trial in progress discarded at
once, the run paused), :meth:`resume`, :meth:`abort` (the trial in progress is discarded, the rig left safe, finished
trials kept: resumable), :meth:`acknowledge` (a latched fault: docs/safety.md), and its state (:attr:`state`:
"ready", "running", "pausing", "paused", "latched", "aborting", "done").
:meth:`run` records in the calling thread (the CLI: Ctrl-C and SIGTERM stop it cleanly there); :meth:`start` in a
worker thread (the GUI), :meth:`wait` for its :class:`rigctl.acquisition.runner.RunSummary`.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rigctl.acquisition.rig import Rig
from rigctl.acquisition.runner import RunSummary, TrialEvent, run_protocol
from rigctl.acquisition.safety import Acknowledgement, LatchedFault
from rigctl.core.progress import ProgressEvent
from rigctl.operations._control import RigControl, rig_of
from rigctl.operations._lsl import LslPublisher
from rigctl.operations._monitor import RigEvent
from rigctl.operations._rules import RUN_STATES

__all__ = ["ProtocolRun", "RUN_STATES"]


class ProtocolRun:
    """One run of ``protocol`` on ``rig`` into ``out_path``.

    Parameters
    ----------
    rig : an open rig: a :class:`rigctl.operations.RigControl` (or a :class:`rigctl.acquisition.rig.Rig` from
        :func:`rigctl.open_rig`, which the run wraps in one).
    protocol : a loaded protocol (:func:`rigctl.acquisition.protocol.load_protocol`).
    out_path : the session file; must not exist unless ``resume`` or ``overwrite``.
    resume, overwrite, on_failure, prompt : as :func:`rigctl.acquisition.runner.run_protocol`.
    progress : receives :class:`rigctl.core.progress.ProgressEvent` s.
    on_trial : receives :class:`rigctl.acquisition.runner.TrialEvent` s (from the thread the run records in).
    Both also go onto the rig's event stream (:meth:`RigControl.subscribe`: ``progress`` and ``run``
    :class:`rigctl.operations.RigEvent` s), which a face listens to instead (``rigctl acquire``'s bars).
    on_latch : "wait" (default: after a latched fault the run pauses; an operator's :meth:`acknowledge` clears it
        and moves nothing, :meth:`resume` is the start) or "end" (it ends, resumable: ``rigctl acquire``); see
        :func:`rigctl.acquisition.runner.run_protocol`.
    acknowledge : ``(reason, by)`` of the acknowledgement a resumed session's open latch gets (``resume``).
    lsl : publish the run on Lab Streaming Layer (:class:`rigctl.operations.LslPublisher`: taxels, spikes, drum
        state, one marker per run and trial event); the outlets open here, so a missing pylsl is
        :class:`rigctl.acquisition.lsl.LslUnavailable` before anything moves. Or an ``LslPublisher`` to reuse.

    Raises (from :meth:`run` / :meth:`wait`) what ``run_protocol`` raises: FileExistsError, FileNotFoundError,
    SessionError, ValueError.
    """

    def __init__(self, rig: RigControl | Rig, protocol: Any, out_path: str | os.PathLike[str], *, resume: bool = False,
                 overwrite: bool = False, on_failure: str = "continue",
                 prompt: Callable[[str], Any] | None = None,
                 progress: Callable[[ProgressEvent], Any] | None = None,
                 on_trial: Callable[[TrialEvent], Any] | None = None, lsl: Any = False, on_latch: str = "wait",
                 acknowledge: tuple[str, str] | None = None) -> None:
        #: the rig's owner: the run registers itself as its :attr:`~RigControl.active_run` (its STOP pauses the run)
        self.control = rig if isinstance(rig, RigControl) else RigControl(rig)
        self.on_latch, self.acknowledge_as = on_latch, acknowledge
        #: STOP: set with pause_event to cut the trial in progress short (:meth:`stop`)
        self.halt_event = threading.Event()
        self.protocol = protocol
        self.out_path = Path(out_path)
        #: continue an interrupted session file (not to be confused with :meth:`resume` after a pause)
        self.resume_file = resume
        self.overwrite, self.on_failure, self.prompt = overwrite, on_failure, prompt
        self.progress, self.on_trial = progress, on_trial
        #: set to stop the run cleanly (:meth:`abort`); set to pause it between trials (:meth:`pause`)
        self.stop_event = threading.Event()
        self.pause_event = threading.Event()
        self.summary: RunSummary | None = None
        self.error: BaseException | None = None
        self._paused_now = False
        self._started = False
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self.lsl: LslPublisher | None = None
        self._own_lsl = False  # a publisher made here is closed at the run's end; one passed in, by its owner
        if isinstance(lsl, LslPublisher):
            self.lsl = lsl
        elif lsl:
            self.lsl = LslPublisher(self.control, protocol_name=getattr(protocol, "name", ""))
            self._own_lsl = True

    # ------------------------------------------------------------------------------------------------- state
    @property
    def state(self) -> str:
        """"ready" (not started), "running", "pausing" (asked, the trial in progress ends first; or the rig still
        backing off), "paused" (between trials, the sensor released: after :meth:`pause`, :meth:`stop` or an
        acknowledged latch, until :meth:`resume`), "latched" (a latched fault holds the run: :meth:`acknowledge`,
        then :meth:`resume`), "aborting", "done"."""
        if self._done.is_set():
            return "done"
        if not self._started:
            return "ready"
        if self.stop_event.is_set():
            return "aborting"
        if self.control.latch is not None:
            return "latched"
        if self.pause_event.is_set():
            return "paused" if self._paused_now else "pausing"
        return "running"

    @property
    def running(self) -> bool:
        """Started and not done (paused counts as running: the run owns the rig)."""
        return self._started and not self._done.is_set()

    # ------------------------------------------------------------------------------------------------- controls
    def pause(self) -> None:
        """Pause after the trial in progress, with the sensor released; :meth:`resume` goes on."""
        if not self._done.is_set() and not self.stop_event.is_set():
            self.pause_event.set()

    def stop(self) -> None:
        """STOP: the drum stopped and the trial in progress discarded at once, the run paused (resumable with
        :meth:`resume`, which records that trial again). Not an abort."""
        if not self._done.is_set() and not self.stop_event.is_set():
            self.pause_event.set()
            self.halt_event.set()
            rig_of(self.control).safe_stop()

    def resume(self) -> None:
        """The start: go on after :meth:`pause`, :meth:`stop` or an acknowledged latch (the trial cut short is
        recorded again; after an acknowledgement the rig HOMEs and TAREs first). Raises
        :class:`rigctl.acquisition.safety.LatchedFault` naming the latch while one is held: :meth:`acknowledge`
        first (docs/safety.md)."""
        latch = self.control.latch
        if latch is not None and self.running:
            raise LatchedFault(latch, "resume refused")
        if self.running:  # the table's start (one rule for every face's resume)
            self.control.start_allowed("resume")
        self.pause_event.clear()

    def acknowledge(self, reason: str, *, by: str) -> Acknowledgement:
        """Acknowledge the rig's latched fault (:meth:`RigControl.acknowledge`): nothing moves, the run stays
        paused until :meth:`resume` (the start)."""
        return self.control.acknowledge(reason, by=by)

    def abort(self) -> None:
        """Stop cleanly: the trial in progress is discarded, the rig left safe, finished trials stay in the file
        (the run can be resumed later). Returns at once; :meth:`wait` for the end."""
        self.stop_event.set()
        self.pause_event.clear()
        if self.lsl is not None and not self._done.is_set():
            self.lsl.run_marker("abort")

    # ------------------------------------------------------------------------------------------------- running
    def run(self) -> RunSummary:
        """Record in the calling thread until the plan is done, the run is aborted or stops; returns the summary.
        In the main thread Ctrl-C and SIGTERM stop it cleanly (``summary.stopped``)."""
        if self._started:
            raise RuntimeError("this run has already been started")
        self._started = True
        self.control.active_run = self
        try:
            if self.lsl is not None:
                self.lsl.run_marker("run_start", out=str(self.out_path), resume=self.resume_file)
            self.summary = run_protocol(
                self.protocol, self.out_path, rig=rig_of(self.control), resume=self.resume_file, progress=self._progress,
                stop_event=self.stop_event, pause_event=self.pause_event, on_trial=self._trial,
                prompt=self.prompt, on_failure=self.on_failure, overwrite=self.overwrite,
                session_attrs=None if self.lsl is None else self.lsl.session_attrs(), on_latch=self.on_latch,
                halt_event=self.halt_event, acknowledge=self.acknowledge_as)
            if self.lsl is not None:
                s = self.summary
                self.lsl.run_marker("run_end", complete=s.complete, planned=s.planned, failed=s.failed,
                                    stopped=s.stopped)
            return self.summary
        except BaseException as exc:
            self.error = exc
            raise
        finally:
            if self.control.active_run is self:
                self.control.active_run = None
            if self._own_lsl and self.lsl is not None:
                self.lsl.close()
            self._done.set()

    def start(self) -> "ProtocolRun":
        """Record in a worker thread; returns self. :meth:`wait` for the summary."""
        def work() -> None:
            try:
                self.run()
            except BaseException:  # noqa: BLE001 - kept in self.error, raised by wait()
                pass

        self._thread = threading.Thread(target=work, name="protocol-run", daemon=True)
        self._thread.start()
        return self

    def wait(self, timeout_s: float | None = None) -> RunSummary | None:
        """The summary once the run has ended (None if it has not within ``timeout_s``); raises the run's error."""
        if not self._done.wait(timeout_s):
            return None
        if self.error is not None:
            raise self.error
        return self.summary

    def _progress(self, event: ProgressEvent) -> None:
        if self.progress:
            self.progress(event)
        self.control.publish(RigEvent("progress", event.message, time.monotonic(), progress=event))

    def _trial(self, event: TrialEvent) -> None:
        self.control.publish(RigEvent("run", f"trial {event.kind}", time.monotonic(), trial=event))
        if event.kind == "paused":
            self._paused_now = True
        elif event.kind == "resumed":
            self._paused_now = False
        if self.lsl is not None:
            self.lsl.on_trial(event)
        if self.on_trial is not None:
            self.on_trial(event)
