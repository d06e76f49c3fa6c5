"""The trial runner: records a protocol's plan into a session file, trial by trial, resumable.

Per trial (paper, Materials and Methods): mount the texture when it changes (simulation: set it; hardware: prompt the
operator), force setpoint and wait until settled, speed (or ramp) setpoint and wait until steady, record the trial's
duration, stop the drum; write the trial to the session file in one go (:meth:`SessionWriter.write_trial`).

Run control, for the CLI and the GUI alike:

- progress: a tqdm bar with ETA (``progress=True``), or nothing printed at all (``progress=False``, callbacks only);
- ``on_trial(event)``: a :class:`TrialEvent` when each trial starts and ends (complete / failed);
- ``stop_event`` (set it) or Ctrl-C (KeyboardInterrupt): clean stop: the trial in progress is discarded, the rig is
  left safe (STOP), every finished trial stays in the file, and the run can be resumed;
- ``pause_event``: while it is set the runner waits between trials with the rig released (no force applied, so the
  controller's watchdog cannot trip); clear it to continue;
- ``resume=True``: continue an interrupted session file from its ``/plan`` (refused if the protocol source differs);
  complete trials are never recorded again, failed and pending ones are;
- a trial that fails (timeout, fault, lost stream) is marked failed in the plan; the run continues
  (``on_failure="continue"``) or stops (``"stop"``).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from rigctl.acquisition.calibration import session_calibration_block
from rigctl.acquisition.protocol import Protocol, ScriptProtocol
from rigctl.acquisition.rig import Rig, TrialAborted
from rigctl.core.trial import PlannedTrial, TrialData
from rigctl.storage.session import SessionError, SessionWriter, TrialStatus


@dataclass
class TrialEvent:
    """What :func:`run_protocol` reports to ``on_trial``.

    Attributes
    ----------
    kind : "start" | "complete" | "failed" | "texture" (a plate is being mounted) | "paused" | "resumed"
    planned : the trial (None for "paused"/"resumed")
    index : 0-based position among the trials this run records
    total : how many trials this run records
    data : the recorded TrialData ("complete" only)
    error : the failure in words ("failed" only)
    elapsed_s : wall time since the run started
    eta_s : estimated wall time left (NaN before the first trial ends)
    """

    kind: str
    planned: PlannedTrial | None
    index: int
    total: int
    data: TrialData | None = None
    error: str = ""
    elapsed_s: float = 0.0
    eta_s: float = math.nan


@dataclass
class RunSummary:
    """Outcome of :func:`run_protocol`.

    ``planned`` trials in the file's plan, ``complete`` (in the file, including earlier runs), ``recorded`` (by this
    run), ``failed`` (this run), ``samples``/``dropped_frames``/``crc_errors`` (this run), ``stopped`` (interrupted
    by stop_event or Ctrl-C), ``elapsed_s``, ``path``.
    """

    path: Path
    planned: int = 0
    complete: int = 0
    recorded: int = 0
    failed: int = 0
    samples: int = 0
    dropped_frames: int = 0
    crc_errors: int = 0
    stopped: bool = False
    elapsed_s: float = 0.0
    failures: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.stopped and self.failed == 0 and self.complete == self.planned

    def lines(self) -> list[str]:
        state = "stopped early (resume with --resume)" if self.stopped else "finished"
        out = [
            f"session {self.path}: {state} in {self.elapsed_s:.1f} s",
            f"  trials complete: {self.complete}/{self.planned} (recorded now: {self.recorded}, failed now: "
            f"{self.failed})",
            f"  samples: {self.samples}  dropped frames: {self.dropped_frames}  CRC errors: {self.crc_errors}",
        ]
        out += [f"  failed: {f}" for f in self.failures]
        return out


def _emit(cb, event: TrialEvent) -> None:
    if cb is not None:
        cb(event)


def _wait_while_paused(rig: Rig, pause_event, stop_event, on_trial, index, total, t0) -> None:
    if pause_event is None or not pause_event.is_set():
        return
    rig.recover()  # STOP (clearing any fault): no force on the sensor while paused
    _emit(on_trial, TrialEvent("paused", None, index, total, elapsed_s=time.monotonic() - t0))
    while pause_event.is_set():
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
    progress: bool = True,
    stop_event: threading.Event | None = None,
    pause_event: threading.Event | None = None,
    on_trial: Callable[[TrialEvent], Any] | None = None,
    prompt: Callable[[str], Any] | None = None,
    on_failure: str = "continue",
    overwrite: bool = False,
) -> RunSummary:
    """Record ``protocol`` on ``rig`` into the session file ``out_path``.

    Parameters
    ----------
    protocol : a loaded protocol (:func:`rigctl.acquisition.protocol.load_protocol`).
    out_path : session file (``.h5``); must not exist unless ``resume`` or ``overwrite``.
    rig : an open :class:`rigctl.acquisition.rig.Rig` (:func:`rigctl.rigs.open_rig`). Its texture set becomes the
        protocol's (:attr:`Protocol.texture_set`), which the session stores with the taxel source's layout.
    resume : continue the existing file from its plan.
    progress : show a tqdm progress bar on stderr (False: print nothing).
    stop_event, pause_event : run control (see the module docstring).
    on_trial : callback receiving :class:`TrialEvent` s (called from the thread running this function).
    prompt : operator prompt for plate changes on hardware (default: the rig's).
    on_failure : "continue" or "stop" after a failed trial.
    overwrite : replace an existing ``out_path`` (not with ``resume``).

    Returns
    -------
    RunSummary

    Raises
    ------
    FileExistsError (out_path exists, no resume/overwrite), FileNotFoundError (resume without a file),
    SessionError (resume with a different protocol), ValueError (bad on_failure).
    KeyboardInterrupt is caught: the run stops cleanly and the summary says ``stopped``.
    """
    if on_failure not in ("continue", "stop"):
        raise ValueError(f"on_failure must be 'continue' or 'stop', got {on_failure!r}")
    out_path = Path(out_path)
    if isinstance(protocol, ScriptProtocol):
        return _run_script(protocol, out_path, rig=rig, resume=resume, overwrite=overwrite)

    rig.apply_settle(protocol.settle)
    rig.textures = protocol.texture_set
    if resume:
        writer = SessionWriter.open(out_path, protocol_source=protocol.source)
    else:
        writer = SessionWriter.create(
            out_path, plan=protocol.plan(), layout=rig.layout, textures=protocol.texture_set,
            protocol_source=protocol.source, protocol_name=protocol.name,
            protocol_format="toml", rig_config=rig.describe(), kind="recorded",
            calibration=session_calibration_block(rig.host_config, rig.layout.n_channels), overwrite=overwrite,
        )
    plan = [PlannedTrial.from_row(r) for r in writer.plan]
    todo = [p for p, st in zip(plan, writer.plan["status"]) if st != TrialStatus.COMPLETE]
    summary = RunSummary(path=out_path, planned=len(plan))
    total = len(todo)
    t0 = time.monotonic()
    bar = None
    if progress:
        from tqdm import tqdm

        done_before = len(plan) - total
        bar = tqdm(total=len(plan), initial=done_before, unit="trial", desc=protocol.name, dynamic_ncols=True)
    durations: list[float] = []
    try:
        for index, planned in enumerate(todo):
            if stop_event is not None and stop_event.is_set():
                summary.stopped = True
                break
            _wait_while_paused(rig, pause_event, stop_event, on_trial, index, total, t0)
            if stop_event is not None and stop_event.is_set():
                summary.stopped = True
                break
            eta = (sum(durations) / len(durations)) * (total - index) if durations else math.nan
            t_trial = time.monotonic()
            try:
                if rig.texture != planned.texture:
                    _emit(on_trial, TrialEvent("texture", planned, index, total, elapsed_s=t_trial - t0, eta_s=eta))
                    rig.mount_texture(planned.texture, prompt=prompt)
                _emit(on_trial, TrialEvent("start", planned, index, total, elapsed_s=t_trial - t0, eta_s=eta))
                if bar is not None:
                    bar.set_postfix_str(f"{planned.texture} {planned.profile if planned.is_ramp else ''}"
                                        f"{planned.speed_mm_s:g} mm/s {planned.force_g:g} g", refresh=True)
                data = rig.record_trial(planned, stop_event=stop_event)
            except Exception as exc:  # noqa: BLE001 - a failed trial is recorded as failed, the run goes on
                if isinstance(exc, TrialAborted):
                    summary.stopped = True
                    break
                reason = f"trial {planned.trial_id} ({planned.texture}, {planned.speed_mm_s:g} mm/s, " \
                         f"{planned.force_g:g} g): {type(exc).__name__}: {exc}"
                writer.mark_failed(planned.trial_id, f"{type(exc).__name__}: {exc}")
                summary.failed += 1
                summary.failures.append(reason)
                _emit(on_trial, TrialEvent("failed", planned, index, total, error=reason,
                                           elapsed_s=time.monotonic() - t0, eta_s=eta))
                rig.recover()
                if bar is not None:
                    bar.write(f"FAILED {reason}")
                if on_failure == "stop":
                    break
                continue
            _write_trial(writer, planned.trial_id, data, rig, bar)
            summary.recorded += 1
            summary.samples += data.n_samples
            summary.dropped_frames += data.dropped_frames
            summary.crc_errors += data.crc_errors
            durations.append(time.monotonic() - t_trial)
            left = total - index - 1
            eta = (sum(durations) / len(durations)) * left
            _emit(on_trial, TrialEvent("complete", planned, index, total, data=data,
                                       elapsed_s=time.monotonic() - t0, eta_s=eta))
            if bar is not None:
                bar.update(1)
    except KeyboardInterrupt:
        summary.stopped = True
    finally:
        rig.safe_stop()
        if bar is not None:
            bar.close()
    summary.complete = len(writer.completed_ids())
    summary.elapsed_s = time.monotonic() - t0
    return summary


def _write_trial(writer: SessionWriter, trial_id: int, data: TrialData, rig: Rig, bar) -> None:
    """Write a trial; if a reader holds the file, release the rig (so the controller's watchdog cannot trip while
    the host waits) and keep trying for up to two minutes, the trial's data kept in memory meanwhile."""
    from rigctl.storage.journal import FileBusy

    wait_s = writer.wait_s
    writer.wait_s = 0.5  # shorter than the controller's watchdog (the force loop is still engaged)
    try:
        writer.write_trial(trial_id, data)
        return
    except FileBusy as exc:
        msg = f"{exc}; the rig is released while waiting for the session file"
        if bar is not None:
            bar.write(msg)
        rig.recover()
    finally:
        writer.wait_s = wait_s
    for attempt in range(12):
        try:
            writer.write_trial(trial_id, data)
            return
        except FileBusy:
            if attempt == 11:
                raise


def _run_script(protocol: ScriptProtocol, out_path: Path, *, rig: Rig, resume: bool, overwrite: bool) -> RunSummary:
    """Run a Python-script protocol: ``protocol.run(rig, session)`` with a fresh session writer (empty plan)."""
    if resume:
        raise SessionError(f"{protocol.path}: a Python-script protocol cannot be resumed by the runner "
                           "(the script decides its trials); start a new session file")
    writer = SessionWriter.create(
        out_path, plan=[], layout=rig.layout, textures=rig.textures, protocol_source=protocol.source, protocol_name=protocol.name, protocol_format="python",
        rig_config=rig.describe(), kind="recorded", calibration=session_calibration_block(rig.host_config, rig.layout.n_channels),
        overwrite=overwrite,
    )
    summary = RunSummary(path=out_path)
    t0 = time.monotonic()
    try:
        protocol.run(rig, writer)
    except KeyboardInterrupt:
        summary.stopped = True
    finally:
        rig.safe_stop()
    from rigctl.storage.session import open_session

    with open_session(out_path) as s:
        summary.planned = len(s.plan)
        summary.complete = len(s.completed_ids())
        summary.recorded = summary.complete
        for tid in s.completed_ids():
            a = s.trial_attrs(tid)
            summary.samples += int(a.get("n_samples", 0))
            summary.dropped_frames += int(a.get("dropped_frames", 0))
            summary.crc_errors += int(a.get("crc_errors", 0))
    summary.elapsed_s = time.monotonic() - t0
    return summary
