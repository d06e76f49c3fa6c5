"""The rig facade: one object that owns a drum controller, a taxel source and the backend they come from.

:class:`Rig` is written against the typed seams of :mod:`rigctl.core.interfaces` (:class:`DrumController`,
:class:`TaxelSource`, :class:`PlateMounter`, :class:`RigBackend`), never against a concrete backend; it is opened by
the composition root, :func:`rigctl.rigs.open_rig` (``kind`` "sim" | "hil" | "hardware" | "replay" | "inprocess"),
or by :meth:`Rig.connect` on any backend. On the simulated, HIL and hardware backends the host talks to the boards
through :class:`rigctl.devices.drum.DrumClient` (pymodbus, Modbus RTU) and
:class:`rigctl.devices.taxel_stream.TaxelStream` (pyserial) on serial ports, the same code paths; the in-process
backend calls the same controller logic directly on a simulated clock (fast unit tests).

A trial (:meth:`Rig.record_trial`), as in the paper's Methods ("Tactile Texture Dataset"): set the force setpoint and
engage the force loop (PRESS), wait until the force has settled; set the speed and RUN, wait until the drum runs
steadily at speed (for a ramp: at its start speed, then switch to the RAMP profile and RUN again, which starts the
ramp); capture exactly ``duration_s * rate`` taxel frames (``rate`` = the taxel source's layout) (counted, not timed) while
sampling the load-cell force and drum speed at ~50 Hz (these Modbus reads also feed the controller's watchdog);
STOP_DRUM. A constant-speed trial starts at the drum's index mark: the capture keeps the frames from the first one
flagged SYNC_IN (the Mega's index pulse, latched by the Uno, docs/wire-protocol.md 2.6) on, so every trial of a
texture starts at the same place on the plate (phase-aligned, up to the 1 ms latch and the index repeatability);
the paper's 100 ms-window features are time series along the plate and need that alignment. A lost index frame
costs at most that frame: the index is placed in the sequence gap where the drum angle predicts it
(:func:`locate_index`). :meth:`Rig.safe_stop` (STOP: drum to rest, actuator backed off) always leaves the rig safe;
:meth:`Rig.recover` after a failed trial also restarts a taxel stream that delivers nothing and says whether both
links work (:meth:`Rig.check_links`).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from rigctl.acquisition.clock import trial_clock_attrs
from rigctl.acquisition.drum_marks import mark_attrs
from rigctl.acquisition.motion import wait_released
from rigctl.acquisition.protocol import PlannedTrial, Settle
from rigctl.acquisition.rigconfig import config_path, load_rig_config
from rigctl.acquisition.safety import (
    Acknowledgement,
    ConfigResolution,
    DrumStall,
    Latch,
    LatchedFault,
    SafetyLatch,
    SafetyLog,
    latch_for,
    latch_from_faults,
    unacknowledged_latch,
)
from rigctl.core.clocksync import DeviceClockFit
from rigctl.core.drum import (
    DRUM_CIRCUMFERENCE_MM,
    DRUM_MICROSTEPS,
    DRUM_SPEED_TOLERANCE,
    DRUM_STEPS_PER_REV,
    PROTOCOL_LIMITS,
    DrumError,
    DrumFault,
    DrumReset,
    DrumState,
    DrumTimeout,
    DrumWaitAborted,
    Fault,
    ForceLoopConfig,
    SpeedProfile,
    StatusFlag,
    fault_advice,
)
from rigctl.core.interfaces import DrumController, ReplayProvenance, RigBackend, TaxelSource
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import TrialData, lower_envelope_rate_hz
from rigctl.devices import wire
from rigctl.devices.capture_parts import first_with_seq
from rigctl.devices.drum import default_force_loop

log = logging.getLogger(__name__)

#: force/speed trace sampling period during a trial, s (~50 Hz)
STATUS_PERIOD_S = 0.02
#: how often the drum controller's watchdog is fed while a session file is written (:meth:`Rig.while_fed`), s of
#: the rig's clock: well inside the shortest WATCHDOG_MS (100 ms)
WRITE_FEED_S = 0.05
#: a capture fails when no taxel frame has arrived for this long (a stalled or unplugged stream), s
CAPTURE_STALL_S = 2.0
#: and in any case when it takes longer than 3 x the trial's duration + this margin, s
CAPTURE_MARGIN_S = 5.0
#: the index pulse must arrive within this many drum revolutions (at the trial speed) after the capture starts
INDEX_TIMEOUT_REVS = 1.25
#: extra frames captured beyond the expected index position + the trial's frames (status-read latency, jitter)
INDEX_MARGIN_FRAMES = 150
#: extra frames a replayed trial captures: the frames sent before the source's next trial began (in flight)
REPLAY_MARGIN_S = 0.25
#: and at most this many, s: the frames a simulated taxel board sent before the source's next trial began that may
#: still be on their way as its capture begins (an unpaced rig runs ahead of a slow reader by up to seconds)
REPLAY_IN_FLIGHT_MAX_S = 10.0
#: a lost index frame is placed in a sequence gap of at most this many frames (the trial then starts at most this
#: many frames after the index mark) ...
INDEX_GAP_MAX_FRAMES = 5
#: ... lying within this time of the index pulse predicted from the drum angle, s, or this fraction of a revolution if
#: longer (status-read latency, the frames' receive-time jitter, a simulator starved on a loaded host: mostly a few
#: ms, up to ~0.4 s seen; a revolution is 2.1-7.9 s at 150-40 mm/s)
INDEX_PREDICTION_TOLERANCE_S = 0.5
INDEX_PREDICTION_TOLERANCE_REVS = 0.1
#: the drum controller times its HX711's rate at boot (6 DOUT-ready edges: 75 ms at 80 SPS, 0.6 s at 10 SPS; spec 2.9)
#: and refuses PRESS and RUN until then. A rig that opens, or re-homes after a reset, waits up to this long (s of the
#: drum client's clock; it ends at the measurement) so that a rate fault is latched before it judges the controller's
#: state: the firmware under simavr answered 0.1 s after boot, HOME passed, and HX711_RATE latched during the wait for
#: IDLE ("cannot open the rig")
HX711_BOOT_WAIT_S = 5.0
#: the measured HX711 rate matches the configured one within this fraction (spec 2.9: RIGCTL_HX711_RATE_TOLERANCE_PCT)
HX711_RATE_TOLERANCE = 0.2
#: :meth:`Rig.press` waits for the settled force in steps of this long, checking for an abort in between, s
SETTLE_POLL_S = 0.25
#: :meth:`Rig.check_links` waits this long for a taxel frame, s
LINK_CHECK_S = 1.0
#: the drum runs at less than this fraction of its target while told to turn: stalled (two status reads in a row
#: during a capture, or when the spin-up times out)
STALL_FRACTION = 0.2


class RigError(RuntimeError):
    """The rig could not be opened or did not do what a trial needs (with the reason in words)."""


class FaultAtOpen(RigError):
    """The drum controller held a latched fault when the rig was opened with ``refuse_fault`` (a face that opens to
    record: ``rigctl acquire``): opening never
    acknowledges it (docs/safety.md). The fault is named in one line (:attr:`latch`); an operator acknowledges it at
    open (``rigctl acquire|doctor|serve --ack REASON``, :func:`rigctl.operations.open_control`'s ``acknowledge``)."""

    def __init__(self, latch: Latch) -> None:
        self.latch = latch
        super().__init__(f"the drum controller holds a latched fault: {latch.describe()} (opening never acknowledges "
                         "it)")


class FirmwareMismatch(RigError):
    """A board runs another firmware build than the installed sources', or the drum controller reports build 0 (an
    image without a build id: the Arduino IDE, ``make BUILD_ID=``): one line naming both, the firmware versions this
    rigctl knows and the flash command (:func:`rigctl.firmware.build_mismatch`); or a drum controller below the safety
    floor (:func:`rigctl.firmware.below_safety_floor`), which ``--allow-firmware-mismatch`` never runs."""


class TrialAborted(RigError):
    """A trial was stopped on request (stop event / Ctrl-C); the rig has been stopped, nothing was recorded."""


class RigOpenError(RigError, DrumError):
    """The boards opened but the drum controller failed while the rig was being prepared (status read, HOME): a
    :class:`rigctl.core.drum.DrumError` (``__cause__``) that also says whether the clean-up's STOP was acknowledged.

    Attributes
    ----------
    mode : the rig's backend ("sim", "hardware", ...)
    stop_acknowledged : bool, False when the controller did not acknowledge STOP either (the drum may be moving)
    """

    def __init__(self, mode: str, cause: BaseException, *, stop_acknowledged: bool) -> None:
        self.mode, self.stop_acknowledged = mode, stop_acknowledged
        super().__init__(f"cannot open the {mode} rig: {' '.join(str(cause).split())}")


class CaptureError(RigError):
    """The taxel stream delivered fewer frames than a trial needs within its time (a stalled or lost stream)."""


@dataclass
class _Status:
    t: float
    force_g: float
    speed_mm_s: float
    state: int
    faults: int
    index_source: str = "steps"
    index_period_s: float = 0.0
    index_steps: int = 0
    index_count: int = 0
    mark_period_s: float = 0.0
    mark_steps: int = 0
    mark_count: int = 0


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _ports(backend) -> dict:
    try:
        d = backend.describe()
    except Exception:  # noqa: BLE001 - only for an error message
        return {}
    return {k.replace("_port", ""): v for k, v in d.items() if k.endswith("_port") and v}




class Rig:
    """An open rig: a drum controller, a streaming taxel source and the backend they come from.

    Open one with :func:`rigctl.rigs.open_rig` (or :meth:`connect` on a backend); a context manager
    (``with open_rig("sim") as rig:``) that stops the rig safely on exit and stops the backend.

    Attributes
    ----------
    drum : :class:`rigctl.core.interfaces.DrumController`
    stream : :class:`rigctl.core.interfaces.TaxelSource` (streaming from :meth:`connect` to :meth:`close`)
    backend : :class:`rigctl.core.interfaces.RigBackend` (the simulated rig's backend exposes it as ``.sim``)
    mode : "sim" | "hil" | "hardware" | "replay" | "inprocess" (the backend's)
    texture : label of the mounted plate, or None if unknown
    settle : :class:`rigctl.acquisition.protocol.Settle`, the timeouts used by :meth:`record_trial`
    host_config : dict, the rig config file's content (calibration), copied into each session
    has_drum : False for a rig whose trials are not the drum's (the handheld rig: nothing to poll, nothing moves by
        itself)
    """

    has_drum: bool = True

    def __init__(self, backend: RigBackend, drum: DrumController, stream: TaxelSource, *,
                 prompt: Callable[[str], Any] | None = None, host_config: dict | None = None,
                 host_config_path: str | None = None):
        self.backend = backend
        self.drum = drum
        self.stream = stream
        self.mode = str(backend.mode)
        self.prompt = prompt
        self.texture: str | None = None
        self.settle = Settle()
        #: replay rig: True plays the source on across trials (the protocol's ``replay = "continuous"``); False
        #: starts each trial at the source's next trial
        self.replay_continuous = False
        self.host_config = dict(host_config or {})
        self.host_config_path = host_config_path
        #: the simulated board's HX711 rate chosen at open (``--hx711-rate``), which the force loop is configured for
        self.chosen_hx711_rate_sps: int | None = None
        self._textures: TextureSet = backend.textures or PAPER_TEXTURES
        self._closed = False
        self._lock = threading.RLock()
        #: the drum controller's BOOT_COUNT when this rig last homed it (None before): a change is a reset
        self.drum_boot_count: int | None = None
        #: unexpected resets of the drum controller seen while this rig used it
        self.drum_resets = 0
        self._counted_boot: int | None = None  # the boot count whose reset drum_resets counted last
        #: warnings about the drum controller's state found when opening (bad EEPROM, calibration mismatch), in words
        self.warnings: list[str] = []
        #: frames the last trial's capture received (None before the first, or once the stream is known to work)
        self.last_capture_frames: int | None = None
        #: whether the controller acknowledged the STOP of :meth:`close` (None while open)
        self.stop_acknowledged: bool | None = None
        #: the host <-> taxel-board clock mapping, fitted online on every captured frame (rigctl.acquisition.clock)
        self.clock_fit: DeviceClockFit | None = None
        #: the safety latch (rigctl.acquisition.safety): a latched fault refuses motion until acknowledged
        self.safety = SafetyLatch()
        #: every latch and acknowledgement also goes into the rig's own log at once ($XDG_STATE_HOME/rigctl)
        self.safety_log = SafetyLog({"mode": self.mode, **_ports(backend)})
        self.safety.listeners.append(self.safety_log)
        #: the last acknowledgement no run's session has logged yet (a run that resumes the session it concerns logs
        #: it: a served run acknowledged while no run was going, e.g. after a restart)
        self.unlogged_acknowledgement: Acknowledgement | None = None
        self.safety.listeners.append(self._remember_acknowledgement)  # before any run's listener
        #: this rig has homed the controller (a NOT_HOMED controller since then was reset: latched)
        self.homed_once = False
        #: the operator's acknowledgement of a fault the controller held when this rig opened (given at open:
        #: ``--ack REASON``; opening itself never acknowledges); the run logs it in its session
        #: (:func:`rigctl.acquisition.runner.run_protocol`) and sets this back to None
        self.acknowledged_at_open: Acknowledgement | None = None
        #: configuration mismatches (HX711_RATE) the rig config resolved when this rig opened (not acknowledgements:
        #: :meth:`_resolve_by_config`); the run logs them in its session and empties this
        self.resolved_at_open: list[ConfigResolution] = []
        #: the next start (a press, a trial) HOMEs and TAREs first: an acknowledgement cleared the controller
        #: without moving anything (docs/safety.md: acknowledging is not starting)
        self.home_pending = False

    # ------------------------------------------------------------------------------------------------- opening
    @classmethod
    def connect(cls, backend: RigBackend, *, prompt: Callable[[str], Any] | None = None,
                host_config_path: str | None = None, refuse_fault: bool = True,
                allow_firmware_mismatch: bool = False, hx711_rate_sps: int | None = None) -> "Rig":
        """Start ``backend``, open its drum controller and taxel source, start streaming. Nothing moves: opening is
        not starting (docs/safety.md); the first start (a press, a run's first trial, :meth:`home_if_pending`) HOMEs
        and TAREs first (:attr:`home_pending`).

        Parameters
        ----------
        backend : a :class:`rigctl.core.interfaces.RigBackend` (not yet entered; the rig stops it on close).
        prompt : ``prompt(message)`` that blocks until the operator has done what it asks (hardware plate changes).
        host_config_path : the rig config JSON file (calibration); default
            :func:`rigctl.acquisition.rigconfig.default_config_path`.
        refuse_fault : a fault the controller latches when the rig opens fails the opening (:class:`FaultAtOpen`,
            the rig closed; opening never acknowledges). False: it stays latched (logged, :attr:`safety`) for the
            caller to show and the operator to acknowledge.
        allow_firmware_mismatch : run boards whose firmware build differs from the installed sources' or a drum
            controller without a build id (logged; for developers); False (default): :class:`FirmwareMismatch`
            naming both builds, the versions this rigctl knows and the flash command.
        hx711_rate_sps : the HX711 rate chosen for a simulated rig's board (``--hx711-rate``, 10 or 80), or None: the
            force loop the rig is configured with takes it (the rig config's ``force_loop`` with that rate, or the
            controller's defaults for it), as the lab's rig config for that board would say.

        Raises
        ------
        RigError
            The backend cannot start or the boards do not answer (the message names the backend and its ports).
        """
        host_config = load_rig_config(host_config_path)
        drum = stream = None
        entered = False
        try:
            backend.__enter__()
            entered = True
            drum = backend.drum()
            drum.__enter__()
            stream = backend.taxels()
            stream.open()
            stream.start()
        except BaseException as exc:
            for obj in (stream, drum):
                if obj is not None:
                    with contextlib.suppress(Exception):
                        obj.close()
            if entered:
                with contextlib.suppress(Exception):
                    backend.__exit__(None, None, None)
            if isinstance(exc, Exception) and not isinstance(exc, RigError):
                where = ", ".join(f"{k} {v}" for k, v in _ports(backend).items())
                raise RigError(f"cannot open the {backend.mode} rig{' (' + where + ')' if where else ''}: "
                               f"{exc}") from exc
            raise
        rig = cls(backend, drum, stream, prompt=prompt, host_config=host_config,
                  host_config_path=str(config_path(host_config_path)))
        rig.chosen_hx711_rate_sps = None if hx711_rate_sps is None else int(hx711_rate_sps)
        try:
            rig._check_firmware_build(allow_firmware_mismatch)
            rig._prepare(refuse_fault=refuse_fault)
        except BaseException as exc:
            rig.close()
            if isinstance(exc, DrumError):
                raise RigOpenError(rig.mode, exc, stop_acknowledged=bool(rig.stop_acknowledged)) from exc
            raise
        return rig

    def _check_firmware_build(self, allow: bool) -> None:
        """Each board's build id against the installed sources' (:func:`rigctl.firmware.build_mismatch`): a mismatch
        raises :class:`FirmwareMismatch` unless ``allow`` (then a warning); a drum controller below the safety floor
        (:func:`rigctl.firmware.below_safety_floor`) raises it whatever ``allow`` says."""
        from rigctl import firmware

        banner = getattr(self.stream, "banner", None) or {}
        st = self.drum.read_status()
        builds = {"mega": getattr(st, "build_id", None), "uno": banner.get("build")}
        versions = {"mega": getattr(st, "firmware", None), "uno": banner.get("firmware")}
        floor = firmware.below_safety_floor(versions)
        if floor:
            raise FirmwareMismatch(floor)
        try:
            line = firmware.build_mismatch(builds, versions=versions)
        except OSError as exc:  # no firmware sources installed: nothing to compare with
            log.warning("cannot compare the boards' firmware builds with the installed sources: %s", exc)
            return
        if line and allow:
            self._warn(line.split(", or pass")[0] + " (allowed: --allow-firmware-mismatch)")
        elif line:
            raise FirmwareMismatch(line)

    def _prepare(self, *, refuse_fault: bool) -> None:
        """Configure the opened controller and read its state; nothing moves (opening is not starting,
        docs/safety.md): a latched fault is latched here (and refused when ``refuse_fault``), else the first start
        HOMEs and TAREs (:attr:`home_pending`)."""
        first = self.drum.read_status()  # the controller as this rig first reads it: a reset after it, this rig saw
        self._apply_force_loop()
        st = self._resolve_by_config(self._booted_status())
        self._check_calibration(st)
        self.drum_boot_count = getattr(first, "boot_count", None)
        if st.state == DrumState.FAULT:  # shown and kept: opening never acknowledges (docs/safety.md)
            what = "held when the rig opened"
            if Fault.HX711_RATE in Fault(int(st.faults)):  # the rates that do not match, by name
                what += (f" (HX711_RATE: measured {float(getattr(st, 'hx711_rate_sps', 0.0)):.0f} SPS, the force "
                         f"loop set for {self.drum.force_loop().hx711_rate_sps} SPS)")
            self.latch_unsafe(st, what)
            log.warning("drum controller is in FAULT (fault bits %s): left latched", st.faults)
            if refuse_fault and self.safety.latch is not None:
                raise FaultAtOpen(self.safety.latch)
            return
        self.home_pending = True  # the first start HOMEs and TAREs: opening moves nothing
        # a reset while the rig was opened (its force loop written and lost, its boot count changed since the first
        # read): latched as every reset this rig sees (issue 76: one read later, it was taken for the controller's own)
        self.latch_unsafe(st, "while the rig was opened")
        self._keep_logged_latch()  # (a controller in FAULT holds its latch itself: above)
        if refuse_fault and self.safety.latch is not None:  # kept from the rig's log: refused as a controller's
            raise FaultAtOpen(self.safety.latch)
        if st.state == DrumState.NOT_HOMED:  # its status shows the state; a warning here read as a fault above a
            # doctor report that passes (issue 38)
            log.info("drum controller is NOT_HOMED (reset cause %s): the first start HOMEs",
                     getattr(st, "reset_cause", "?"))

    def _keep_logged_latch(self) -> None:
        """A controller that outlives its faces (``hardware``: a real one, or ``rigctl sim``'s over its ports): a
        latch an earlier face saw and nobody acknowledged (the rig's own log,
        :func:`rigctl.acquisition.safety.unacknowledged_latch`) is held again, whatever the controller says now
        (a reset under load leaves it NOT_HOMED, with nothing latched of its own). The simulated kinds start a
        controller of their own at every open: nothing to keep."""
        if self.mode != "hardware":
            return
        kept = unacknowledged_latch(self.safety_log.rig)
        if kept is not None:
            log.warning("the rig's log holds a latch no one acknowledged: %s", kept.describe())
            self.safety.trip(replace(kept, detail=f"seen by an earlier face, not acknowledged: {kept.detail}"))

    def _resolve_by_config(self, st: Any) -> Any:
        """A configuration mismatch, not a hazard: an HX711_RATE latch alone (the controller timed its HX711 at boot,
        before the host wrote the rig config's rate) is cleared as part of configuring the rig when the rig config's
        force_loop is applied (the controller's HX711_RATE_SPS reads back as the config's) and the measured rate
        matches it (:data:`HX711_RATE_TOLERANCE`). Logged as a :class:`ConfigResolution` (the rig's log,
        :attr:`resolved_at_open` for the run's session): no acknowledgement, nothing moves. Any other fault, or a
        rate that does not match, is left latched. Returns the status after."""
        block = self._force_loop_block()
        if not block or st.state != DrumState.FAULT or int(st.faults) != int(Fault.HX711_RATE):
            return st
        configured = int(self.drum.force_loop().hx711_rate_sps)
        measured = float(getattr(st, "hx711_rate_sps", 0.0))
        if configured != int(block["hx711_rate_sps"]) or abs(measured / configured - 1) > HX711_RATE_TOLERANCE:
            return st
        try:
            self.drum.clear_fault()
        except DrumError as exc:  # the controller disagrees: left latched, refused as any fault at open
            log.warning("the drum controller refused to clear HX711_RATE after the rig config's rate: %s", exc)
            return self.drum.read_status()
        after = self.drum.read_status()
        if after.state == DrumState.FAULT:
            return after
        chosen = self.chosen_hx711_rate_sps is not None
        res = ConfigResolution("hx711-rate", int(Fault.HX711_RATE), "--hx711-rate" if chosen else "rig config",
                               "" if chosen else str(self.host_config_path or ""),
                               f"hx711 rate {configured} SPS configured, measured {measured:.0f} SPS")
        self.resolved_at_open.append(res)
        self.safety_log(res)
        log.info("HX711_RATE cleared by the rig config %s: %s (a configuration, not an acknowledgement; nothing "
                 "moved)", res.source, res.reason)
        return after

    def _booted_status(self) -> Any:
        """The drum controller's status once it has timed its HX711's rate (or faulted, or after
        :data:`HX711_BOOT_WAIT_S`: an HX711 that never converts latches LOADCELL_TIMEOUT instead)."""
        clock = self.drum.clock
        deadline = clock.now() + HX711_BOOT_WAIT_S
        st = self.drum.read_status()
        while not getattr(st, "hx711_rate_sps", 1.0) and st.state != DrumState.FAULT and clock.now() < deadline:
            clock.sleep(STATUS_PERIOD_S)
            st = self.drum.read_status()
        return st

    def _home(self) -> None:
        """HOME (the controller tares at the home switch), wait for IDLE, TARE again at home, and remember the
        controller's BOOT_COUNT: a later change of it is an unexpected reset (:meth:`check_drum_reset`)."""
        self.drum.home()
        wait_homed = getattr(self.drum, "wait_homed", None)  # (a STOP during HOME ends the wait: NOT_HOMED again)
        st = wait_homed(30.0) if wait_homed is not None else self.drum.wait_state([DrumState.IDLE], timeout_s=30.0)
        self.drum.tare()
        self.homed_once = True
        self.drum_boot_count = getattr(self.drum.read_status(), "boot_count", getattr(st, "boot_count", None))

    def home_if_pending(self) -> None:
        """The start after an acknowledgement (or an open without HOME): when :attr:`home_pending`, wait for the
        actuator to back off, HOME and TARE (the first motion of a start: a press, a trial). DrumError / DrumFault
        (HOME failed: latched by the caller's :meth:`latching`)."""
        if not self.home_pending:
            return
        if self._booted_status().state != DrumState.NOT_HOMED:  # (not homed: nothing to back off to)
            wait_released(self.drum)  # the actuator backs off to home first (HOME is refused under load)
        self._home()
        self.home_pending = False

    def _check_calibration(self, st: Any) -> None:
        """Warn (log and :attr:`warnings`) when the controller runs on default calibration (its EEPROM record was
        missing or failed its checksum) or its load-cell scale differs from the rig config's."""
        from rigctl.acquisition.rigconfig import loadcell_scale_mismatch

        if getattr(st, "calibration_defaults", False):
            self._warn("the drum controller's EEPROM calibration is missing or failed its checksum: it runs on the "
                       "default load-cell scale and lead-screw calibration (recalibrate the load cell)")
        try:
            scale = self.drum.loadcell_scale()
        except Exception as exc:  # noqa: BLE001 - a warning only; opening goes on
            log.warning("cannot read the drum controller's load-cell scale: %s", exc)
            return
        mismatch = loadcell_scale_mismatch(self.host_config, scale)
        if mismatch:
            self._warn(mismatch)

    def _warn(self, text: str) -> None:
        log.warning("%s", text)
        self.warnings.append(text)

    def check_drum_reset(self, st: Any = None) -> bool:
        """Has the drum controller reset since this rig homed it (BOOT_COUNT changed, or NOT_HOMED unasked)? If so it
        latches the rig (:attr:`safety`, cause "reset": nothing moves until an operator acknowledges, which homes
        and tares it again) and returns True. Raises DrumError when the controller does not answer."""
        st = self.drum.read_status() if st is None else st
        before = self.safety.latch
        self.latch_unsafe(st, "status check")
        return self.safety.latch is not None and self.safety.latch is not before and self.safety.latch.cause == "reset"

    def _force_loop_block(self) -> dict[str, Any] | None:
        """The force loop the rig is configured with: the rig config's ``force_loop`` block, with the HX711 rate chosen
        at open (:attr:`chosen_hx711_rate_sps`: its gains for that rate; the controller's defaults without a block),
        or None (neither: the controller keeps its own)."""
        block = self.host_config.get("force_loop")
        rate = self.chosen_hx711_rate_sps
        if rate is None:
            return dict(block) if block else None
        return {**(block or default_force_loop(rate).to_dict()), "hx711_rate_sps": rate}

    def _apply_force_loop(self) -> None:
        """The force loop the rig is configured with (:meth:`_force_loop_block`: this rig's HX711 rate and gains), if
        any, to the controller."""
        block = self._force_loop_block()
        if block:
            self.drum.set_force_loop(ForceLoopConfig(**block))
            log.info("force loop from the %s: %s",
                     "rig config" if self.chosen_hx711_rate_sps is None else "rig config and --hx711-rate", block)

    # ------------------------------------------------------------------------------------------------- sensor, textures
    @property
    def layout(self) -> SensorLayout:
        """The sensor the taxel source streams (its identify reply): channels, grid, rate, ADC bits."""
        return self.stream.layout

    @property
    def textures(self) -> TextureSet:
        """The texture set plates are mounted from (the backend's, default the paper's A-P; a protocol run sets
        its own: :func:`rigctl.acquisition.runner.run_protocol`)."""
        return self._textures

    @textures.setter
    def textures(self, textures: TextureSet) -> None:
        if not isinstance(textures, TextureSet):
            raise TypeError(f"textures must be a rigctl.core.TextureSet, got {type(textures).__name__}")
        self._textures = textures

    # ------------------------------------------------------------------------------------------------- context
    def __enter__(self) -> "Rig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the rig safely, stop the stream, close the drum controller and stop the backend."""
        if self._closed:
            return
        self._closed = True
        self.stop_acknowledged = self.safe_stop()
        with contextlib.suppress(Exception):
            self.stream.close()
        with contextlib.suppress(Exception):
            self.drum.close()
        with contextlib.suppress(Exception):
            self.backend.__exit__(None, None, None)

    # ------------------------------------------------------------------------------------------------- info
    def describe(self) -> dict:
        """The rig's configuration as a JSON-able dict (stored as a session's ``rig_config`` attribute).

        Keys: the backend's (mode, drum_port, taxel_port, seed, model: the simulated rig's RigConfig, ...), plugin
        (a plugin's rig: :func:`rigctl.rigs.plugin_identity`),
        sensor_layout (the taxel source's layout), texture_set (the rig's), taxel_streamer (banner), drum_firmware,
        drum_registers (every holding register by name), host_config (the rig config file: calibration).
        """
        out: dict[str, Any] = {"mode": self.mode, "drum_port": None, "taxel_port": None, "seed": None}
        out.update(self.backend.describe())
        plugin = getattr(self.backend, "plugin", None)  # a plugin's rig: its distribution, version, describe()
        if plugin is not None:
            out["plugin"] = plugin
        out.update({
            "sensor_layout": self.layout.to_dict(),
            "texture_set": self.textures.to_dict(),
            "taxel_streamer": {k: v for k, v in (self.stream.banner or {}).items()},
            "host_config_path": self.host_config_path,
            "host_config": self.host_config,
        })
        try:
            st = self.drum.read_status()
            out["drum_firmware"] = list(st.firmware)
            out["drum_registers"] = self.drum.settings()
        except Exception as exc:  # describing must not fail a session
            out["drum_error"] = str(exc)
        return out

    def reload_host_config(self) -> dict:
        """Re-read the rig config file (e.g. after a calibration); later sessions copy the new content."""
        self.host_config = load_rig_config(self.host_config_path)
        return self.host_config

    def taxel_normalisation(self) -> dict | None:
        """The per-taxel normalisation block of the rig config (``taxel_min``/``taxel_max``), or None."""
        block = self.host_config.get("taxel_normalisation")
        return dict(block) if block else None

    # ------------------------------------------------------------------------------------------------- control
    def apply_settle(self, settle: Settle) -> None:
        """Use ``settle``'s timeouts; write its optional controller settings (FORCE_TOLERANCE_G, SETTLE_TIME_MS)."""
        self.settle = settle
        if settle.force_tolerance_g is not None or settle.settle_time_ms is not None:
            self.drum.set_settle_band(force_tolerance_g=settle.force_tolerance_g, settle_time_ms=settle.settle_time_ms)

    def release(self, timeout_s: float = 20.0) -> None:
        """STOP and wait until IDLE with the actuator back home (drum at rest, sensor free): the state for changing
        a plate. A fault the controller latched (the watchdog too) latches the rig (:attr:`safety`): LatchedFault.
        Raises DrumTimeout, LatchedFault. After an acknowledgement (or an open without HOME) this is a start: the
        actuator HOMEs (:meth:`home_if_pending`), which ends with the sensor free.
        """
        with self.latching("release"):
            if self.home_pending:
                self.home_if_pending()
            else:
                wait_released(self.drum, timeout_s=timeout_s)

    def while_fed(self, work: Callable[[], Any]) -> Any:
        """``work()`` in a thread of its own while this thread keeps the drum controller's watchdog fed (a status
        read every :data:`WRITE_FEED_S` of the rig's clock); returns what it returns and raises what it raises.

        For a session file's write between two trials, while the drum turns and the force loop holds: it took ~0.6
        CPU-s at the first trial (and seconds of wall on a slow disk), on the thread that feeds the watchdog; beside
        four CPU hogs the README's quick check latched WATCHDOG so (5 s of the simulated rig's time; a bench's
        controller has 1 s). On a simulated rig the feeding thread's waits hold the world, so a starved host pauses it
        (docs/architecture.md "Time on a simulated rig"); an in-process rig's clock (``stands_between_sleeps``) runs
        ``work()`` here. A status read that fails (the link) is left to the run's next exchange, which reports it."""
        if not self.has_drum:  # (the handheld rig: no watchdog to feed)
            return work()
        clock = self.drum.clock
        if getattr(clock, "stands_between_sleeps", False):  # an in-process rig: nothing moves while the host works
            return work()
        done = threading.Event()
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["value"] = work()
            except BaseException as exc:  # noqa: BLE001 - raised again in the caller's thread
                box["error"] = exc
            finally:
                done.set()

        worker = threading.Thread(target=run, name="rig-while-fed", daemon=True)
        worker.start()
        wait_for = getattr(clock, "wait_for", None)  # a simulated rig's shared clock; else the wall's
        while not (wait_for(done.is_set, WRITE_FEED_S) if wait_for is not None else done.wait(WRITE_FEED_S)):
            try:
                self.drum.read_status()
            except DrumError as exc:
                log.debug("while writing: the drum controller's status not read: %s", exc)
        worker.join()
        if "error" in box:
            raise box["error"]
        return box.get("value")

    def mount_texture(self, label: str, prompt: Callable[[str], Any] | None = None) -> None:
        """Mount texture plate ``label`` (any label of :attr:`textures`): release the sensor, then the backend's
        :class:`rigctl.core.interfaces.PlateMounter` puts it on (simulation: renders the set's geometry; hardware:
        asks the operator, with ``prompt`` or the rig's).

        Raises
        ------
        ValueError (:class:`rigctl.core.textures.TextureSetError`) on a label outside the rig's texture set.
        :class:`rigctl.devices.errors.DrumError` if the rig does not release.
        """
        label = self.textures.resolve(str(label))
        self.release()
        self.backend.mounter.mount(label, self.textures, prompt=prompt or self.prompt)
        if label != self.texture:  # another plate: the next press HOMEs first, and the controller then locates its
            self.home_pending = True  # contact from scratch (it keeps the last one's across a release, spec 2.11)
        self.texture = label

    def safe_stop(self) -> bool:
        """Send STOP (drum decelerates to rest, actuator backs off to home); never raises.

        Returns True if the controller acknowledged it (tries 3 times).
        """
        for attempt in range(3):
            try:
                self.drum.stop()
                return True
            except Exception as exc:  # noqa: BLE001 - safety path: keep trying, never raise
                log.warning("STOP attempt %d failed: %s", attempt + 1, exc)
                time.sleep(0.1)
        log.error("could not send STOP to the drum controller: stop the rig by hand")
        return False

    def recover(self) -> str | None:
        """After a failed trial: STOP, wait for IDLE, and make sure the taxel stream delivers frames (restarting it
        when the last capture or the check saw none: a START the board never got leaves it silent until the next
        START). A latched fault of the controller, or a reset, is never cleared here: it latches the rig
        (:attr:`safety`) for an operator to acknowledge (:meth:`acknowledge`). Never raises a device error.

        Returns
        -------
        None when both links work again, else the link problem in words (see :meth:`check_links`).
        """
        self.safe_stop()
        try:
            st = self.drum.read_status()
            self.latch_unsafe(st, "after a failed trial")
            if not self.safety.latched:  # NOT_HOMED: an acknowledged e-stop or reset, homed at the next start
                self.drum.wait_state([DrumState.IDLE, DrumState.NOT_HOMED], timeout_s=20.0)
        except DrumError as exc:
            log.warning("recovering the rig: %s", exc)
        return self.check_links(restart=True)

    def _remember_acknowledgement(self, item: Latch | Acknowledgement) -> None:
        if isinstance(item, Acknowledgement):
            self.unlogged_acknowledgement = item

    def wait_at_rest(self, timeout_s: float = 20.0) -> Any:
        """After a STOP: wait (on the drum client's clock) until the sensor is released (the actuator at home, the
        drum still) or the actuator cannot back off by itself (not homed: an e-stop or a reset stopped it where it
        stands, still pressing; the next start's HOME backs it off). Returns the last status (None when the
        controller does not answer); never raises. A run reports ``paused`` only after this."""
        clock = self.drum.clock
        deadline = clock.now() + timeout_s
        st = None
        while True:
            try:
                st = self.drum.read_status()
            except DrumError:
                return st
            home = st.actuator_mm <= 0.05 or st.home_switch
            still = st.state in (DrumState.IDLE, DrumState.FAULT, DrumState.NOT_HOMED)
            if (still and (home or not st.homed)) or clock.now() >= deadline:
                return st
            clock.sleep(STATUS_PERIOD_S)

    # ------------------------------------------------------------------------------------------------- safety
    @contextlib.contextmanager
    def latching(self, what: str) -> Any:
        """Run a motion (``what``: its name) under the safety policy: refused while latched (LatchedFault); a
        latched condition it runs into (a controller fault, a reset, a stall) latches the rig, which stops it, and is
        raised as LatchedFault. (A drum link lost mid-press: the controller's watchdog latches WATCHDOG, seen when the
        link is back.)"""
        self.safety.refuse(what)
        try:
            yield
        except LatchedFault:
            self.safe_stop()
            raise
        except (DrumError, CaptureError) as exc:
            latch = latch_for(exc)
            if latch is None:
                raise
            self.safety.trip(latch)
            self.safe_stop()
            raise LatchedFault(latch, what) from exc

    def latch_unsafe(self, st: Any, what: str) -> None:
        """Latch the rig (:attr:`safety`) when the status ``st`` shows a latched fault, or a reset of the controller
        since this rig homed it (BOOT_COUNT changed, or NOT_HOMED unasked). Nothing is cleared. One latch ``reset``
        for a reset (issue 76): the controller's own (RESET, firmware 1.5: a reset away from home, which every face
        finds) or, for one at rest it did not latch, the one this rig saw by the boot count."""
        boot = getattr(st, "boot_count", None)
        reset_seen = boot is not None and self.drum_boot_count is not None and boot != self.drum_boot_count
        if reset_seen and boot != self._counted_boot:
            self.drum_resets += 1
            self._counted_boot = boot
        if st.state == DrumState.FAULT:
            latch = latch_from_faults(int(st.faults))
            self.safety.trip(replace(latch, detail=f"{what}: {latch.detail}"))
            return
        if reset_seen:
            self.safety.trip(Latch("reset", f"{what}: the drum controller reset (reset cause "
                                            f"{getattr(st, 'reset_cause', '?')}, boot count {self.drum_boot_count} -> "
                                            f"{boot}): it stopped and must be homed"))
        elif st.state == DrumState.NOT_HOMED and self.homed_once:
            self.safety.trip(Latch("reset", f"{what}: the drum controller reports NOT_HOMED unasked (a reset)"))

    def acknowledge(self, reason: str, *, by: str) -> Acknowledgement:
        """An operator acknowledges the latched fault: the condition must be gone (the e-stop released; the
        controller accepts CLEAR_FAULT), then the controller is cleared (STOP, CLEAR_FAULT; the taxel stream checked)
        and the latch released. Nothing moves: acknowledging is not starting (docs/safety.md). The next start (a
        press, a run's next trial once it is resumed) HOMEs and TAREs first (:attr:`home_pending`); until then an
        actuator the e-stop stranded stays where it stopped.

        Returns the :class:`rigctl.acquisition.safety.Acknowledgement` (which the run engine writes into the session's
        event log). Raises ValueError (nothing latched, no reason), LatchedFault (the condition persists: the latch
        stays), DrumError (the controller does not answer: the latch stays).
        """
        if self.safety.latch is None:  # a fault the controller latched while nobody asked the rig to move
            self.latch_unsafe(self.drum.read_status(), "status check")
        latch = self.safety.latch
        if latch is None:
            raise ValueError("nothing is latched: no fault to acknowledge")
        if not str(reason).strip() or not str(by).strip():
            raise ValueError("an acknowledgement needs a reason and who gives it")
        with self._lock:  # no trial starts while the rig is made ready; the latch is released last
            st = self.drum.read_status()
            if StatusFlag.ESTOP_OPEN in StatusFlag(int(getattr(st, "flags", 0))):
                raise LatchedFault(latch, "the e-stop is still pressed (its contact is open): release it first")
            self.drum.stop()
            if st.state == DrumState.FAULT:
                try:
                    self.drum.clear_fault()
                except DrumError:
                    st = self.drum.read_status()
                    raise LatchedFault(latch, f"the controller refuses to clear it, the condition persists "
                                              f"({fault_advice(int(st.faults)) or st.faults})") from None
            st = self.drum.read_status()
            if st.state == DrumState.FAULT:  # another fault latched meanwhile: the latch stays
                raise LatchedFault(latch, f"the controller latched again ({fault_advice(int(st.faults)) or st.faults})")
            # the controller as it is now is the one this rig knows: not homed after an e-stop or a reset (the start
            # homes it), its boot count the one a later reset changes
            self.drum_boot_count = getattr(st, "boot_count", self.drum_boot_count)
            if st.state == DrumState.NOT_HOMED:
                self.homed_once = False
            self.home_pending = True
            ack = self.safety.clear(reason, by)
        self.check_links(restart=True)
        return ack

    def check_links(self, *, restart: bool = True, timeout_s: float | None = None) -> str | None:
        """Check both links: the drum controller answers a status read, and taxel frames arrive.

        With ``restart``, a taxel stream that is connected but silent (or whose last capture received nothing) is
        restarted (STOP, START) and checked again. Waits at most ``timeout_s`` (:data:`LINK_CHECK_S`) for a frame
        per check, on the drum client's clock. Never raises a device error.

        Returns
        -------
        None if both work, else what does not, e.g. ``"the drum controller does not answer (...)"`` or ``"no taxel
        frame for 1.0 s (stream disconnected, 2 reconnects)"``.
        """
        from rigctl.devices.errors import TaxelStreamError

        timeout_s = LINK_CHECK_S if timeout_s is None else float(timeout_s)
        frames0 = self.stream.stats.frames
        try:
            self.drum.read_status()
        except DrumError as exc:
            return f"the drum controller does not answer ({exc})"
        # a connected stream whose last capture got nothing is restarted at once; a disconnected one is waited for
        # (its client reopens the port and restarts streaming when the port comes back)
        silent = restart and self.last_capture_frames == 0 and self.stream.stats.connected
        if not silent and self._frames_arrive(frames0, timeout_s):
            self.last_capture_frames = None
            return None
        if restart and self.stream.stats.connected:
            log.warning("the taxel stream delivers no frames: restarting it")
            try:
                with contextlib.suppress(TaxelStreamError):
                    self.stream.stop()
                frames0 = self.stream.stats.frames
                self.stream.start()
            except Exception as exc:  # noqa: BLE001 - reported as the link problem
                return f"the taxel stream cannot be restarted ({exc})"
            if self._frames_arrive(frames0, timeout_s):
                self.last_capture_frames = None
                return None
        st = self.stream.stats
        return (f"no taxel frame for {timeout_s:.1f} s (stream "
                f"{'connected' if st.connected else 'disconnected'}, {st.reconnects} reconnects)")

    def _frames_arrive(self, frames0: int, timeout_s: float) -> bool:
        clock = self.drum.clock
        deadline = clock.now() + timeout_s
        while self.stream.stats.frames == frames0:
            if clock.now() >= deadline:
                return False
            clock.sleep(0.02)
        return True

    def _status(self) -> _Status:
        clock = self.drum.clock  # the clock of the taxel source's host times (simulated in-process)
        t0 = clock.now()
        st = self.drum.read_status()
        t1 = clock.now()
        return _Status(0.5 * (t0 + t1), float(st.force_g), float(st.speed_mm_s), int(st.state), int(st.faults),
                       str(st.index_source), float(st.index_period_s), int(st.index_steps), int(st.index_count),
                       float(st.mark_period_s), int(st.mark_steps), int(st.mark_count))

    def _check_fault(self, s: _Status, what: str) -> None:
        if s.state == DrumState.FAULT:
            raise DrumFault(Fault(s.faults), what)
        if s.state == DrumState.NOT_HOMED:  # only a reset leaves it NOT_HOMED without a fault
            raise DrumReset(f"the drum controller reset {what} (it reports NOT_HOMED): the trial is lost; the rig "
                            "homes and tares it again before the next press")

    # ------------------------------------------------------------------------------------------------- trials
    def press(self, force_g: float, *, timeout_s: float | None = None,
              stop_event: StopFlag | None = None) -> float:
        """Set the force setpoint, engage the force loop and wait until the force has settled on it.

        Returns the time it took, s. Raises :class:`rigctl.devices.errors.SetpointRangeError` (out of range, nothing
        sent), :class:`rigctl.devices.errors.DrumTimeout` (not settled in time), :class:`LatchedFault` (the rig is
        latched, or a latched fault or reset happens: :attr:`safety`), :class:`TrialAborted` (``stop_event`` set while
        waiting: within :data:`SETTLE_POLL_S`).
        """
        force_g = PROTOCOL_LIMITS.force_range().check(force_g)
        with self.latching("PRESS"), self._waits_end_at(stop_event):
            return self._press(force_g, self.settle.force_timeout_s if timeout_s is None else timeout_s, stop_event)

    @contextlib.contextmanager
    def _waits_end_at(self, stop_event: StopFlag | None) -> Iterator[None]:
        """Within the block, the drum client's waits in this thread end at ``stop_event`` (TrialAborted) rather than
        at their timeouts (:meth:`rigctl.devices.drum.DrumClient.aborting_waits`): a STOP during the first trial's
        HOME left the controller NOT_HOMED and the run waiting 30 s for IDLE (seen as 30 s of the rig's clock
        between STOP and STOPPED in a loaded CI run's GUI test)."""
        aborting = getattr(self.drum, "aborting_waits", None)
        if stop_event is None or aborting is None:
            yield
            return
        try:
            with aborting(stop_event.is_set):
                yield
        except DrumWaitAborted as exc:
            raise TrialAborted("trial aborted on request") from exc

    def _press(self, force_g: float, timeout_s: float, stop_event: StopFlag | None) -> float:
        clock = self.drum.clock  # wall time on a real link, simulated time in-process
        t0 = clock.now()
        st = self.drum.read_status()
        # never press on a position or a zero from before a reset or an e-stop: those latch (safety policy)
        self.latch_unsafe(st, "before pressing")
        self.safety.refuse("PRESS")
        if self.home_pending:  # the start after an acknowledgement: HOME and TARE first
            self.home_if_pending()
            st = self.drum.read_status()
        if st.state == DrumState.NOT_HOMED:  # opened without HOME: home and tare first
            self._home()
            st = self.drum.read_status()
        if st.state == DrumState.RUNNING:
            self.drum.stop_drum()
            self.drum.wait_state([DrumState.FORCE_SETTLED, DrumState.SEEKING_FORCE], timeout_s=10.0)
            st = self.drum.read_status()
        self.drum.set_force(force_g)
        if st.state not in (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED):
            if getattr(st, "stiffness_max_g_per_mm", 0) and not st.contact_stiffness_g_per_mm:
                timeout_s += wire.probe_time_s(st.hx711_rate_sps)  # the first press probes the contact (spec 2.10)
            self.drum.press()
        # the controller may still report FORCE_SETTLED for the previous setpoint for one control period
        tol = self.drum.settle_band().force_tolerance_g
        deadline = t0 + timeout_s
        while True:
            # in short waits, so that an abort (STOP in the GUI, Ctrl-C's stop event) ends the wait at once
            _abort_if(stop_event)
            try:
                self.drum.wait_force_settled(timeout_s=min(SETTLE_POLL_S, max(0.05, deadline - clock.now())))
            except DrumTimeout:
                if clock.now() <= deadline:
                    continue
                st = self.drum.read_status()
            else:
                st = self.drum.read_status()
            if (st.state == DrumState.FORCE_SETTLED and int(st.force_setpoint_active_g) == int(round(force_g))
                    and abs(float(st.force_g) - force_g) <= tol):
                return clock.now() - t0
            if clock.now() > deadline:
                _abort_if(stop_event)
                raise DrumTimeout(f"force did not settle at {force_g:g} g within {timeout_s:g} s "
                                  f"(state {DrumState(int(st.state)).name}, force {float(st.force_g):.0f} g)")
            _abort_if(stop_event)
            clock.sleep(0.02)

    def record_trial(self, planned: PlannedTrial, *, stop_event: StopFlag | None = None) -> TrialData:
        """Record one trial on the mounted plate.

        Parameters
        ----------
        planned : the trial's setpoints (texture, speed_mm_s or ramp, force_g, duration_s).
        stop_event : set it to abort the trial (the drum is stopped, :class:`TrialAborted` raised).

        Returns
        -------
        TrialData
            ``taxels`` (round(duration_s * rate), n_channels) uint16 ADC counts (:attr:`layout`), ``seq``, ``flags``, ``host_time_s``
            (s since the first frame, host monotonic clock), force and speed traces at ~50 Hz on the same clock,
            dropped frames (sequence gaps among the kept frames), CRC errors during the capture, and attrs
            (``started_utc``, ``settle_time_s``, measured means, ``host_rate_hz``, ``aligned_to_index``,
            ``index_wait_frames``, ``index_frame_lost``: 0, or the length of the sequence gap the lost index frame
            was placed in).

        Notes
        -----
        On the replay rig (:class:`rigctl.core.interfaces.ReplayProvenance`) a trial follows the source's trials
        instead (unless :attr:`replay_continuous`): the source goes on at its next trial as the capture starts, the
        trial starts at the frame carrying that trial's first sample, and the source's labels and sample range are
        stored (``source_file``, ``source_trial_id``, ``source_texture``, ``source_speed_mm_s``, ``source_force_g``,
        ``source_first_sample``, ``source_last_sample``; ``source_pieces`` when it crosses source trials).

        Index alignment (other constant-speed trials): once the drum runs steadily, the capture starts and the drum angle
        is read to predict when the index mark passes; the capture runs until that point + ``duration_s * rate``
        frames + :data:`INDEX_MARGIN_FRAMES`. The frames before the first one flagged
        ``wire.FrameFlag.SYNC_IN`` are dropped and exactly ``duration_s * rate`` frames from it on are kept
        (``aligned_to_index=True``, ``index_wait_frames`` = frames dropped). When the index frame itself was lost
        on the link, the trial starts right after the short sequence gap where the drum angle predicts the index
        (:func:`locate_index`): a lost index frame costs that frame, not the trial. No index pulse (and no such
        gap) within :data:`INDEX_TIMEOUT_REVS` revolutions at the trial speed (7.9 s x 1.25 at 40 mm/s on the
        314 mm drum) raises :class:`CaptureError`. Ramp trials start with the ramp instead (``aligned_to_index=False``): the
        ramp profile's clock starts with RUN.

        Raises
        ------
        ValueError (texture not mounted), SetpointRangeError, DrumTimeout, DrumFault, CaptureError, TrialAborted.
        """
        if self.texture is not None and planned.texture != self.texture:
            raise ValueError(f"trial {planned.trial_id} is on texture {planned.texture} but {self.texture} is mounted")
        speeds = [planned.ramp_start_mm_s, planned.ramp_end_mm_s] if planned.is_ramp else [planned.speed_mm_s]
        for v in speeds:
            PROTOCOL_LIMITS.speed_range().check(v)
        n = planned.samples_at(self.layout.sample_rate_hz)
        if n <= 0:
            raise ValueError(f"trial {planned.trial_id}: duration {planned.duration_s} s gives no samples")
        with self._lock, self.latching(f"trial {planned.trial_id}"), self._waits_end_at(stop_event):
            try:
                return self._record(planned, n, stop_event)
            except BaseException:
                # leave the drum at rest whatever happened (Ctrl-C, timeout, fault)
                with contextlib.suppress(Exception):
                    self.drum.stop_drum()
                raise

    def _record(self, planned: PlannedTrial, n: int, stop_event) -> TrialData:
        settle = self.settle
        layout = self.layout
        rate = layout.sample_rate_hz
        _abort_if(stop_event)
        settle_s = self.press(planned.force_g, stop_event=stop_event)
        # spin up at a constant speed (a ramp's start speed) and wait until the drum runs steadily there
        first_speed = planned.ramp_start_mm_s if planned.is_ramp else planned.speed_mm_s
        self.drum.set_speed(first_speed)
        self.drum.set_profile(SpeedProfile.CONSTANT)
        t_run = time.monotonic()
        self.drum.run()
        try:
            self.drum.wait_speed_steady(timeout_s=settle.speed_timeout_s, tol_mm_s=settle.speed_tolerance_mm_s)
        except DrumTimeout as exc:
            st = self.drum.read_status()
            if st.state == DrumState.RUNNING and abs(float(st.speed_mm_s)) < STALL_FRACTION * first_speed:
                raise DrumStall(f"the drum turns at {float(st.speed_mm_s):.1f} mm/s, told {first_speed:g} mm/s "
                                f"({settle.speed_timeout_s:g} s after RUN)") from exc
            raise DrumTimeout(f"drum did not reach {first_speed:g} mm/s within "
                              f"{settle.speed_timeout_s:g} s: {exc}") from exc
        if planned.is_ramp:
            # then start the ramp: RUN restarts the profile's clock, and the capture starts with it
            self.drum.set_ramp(planned.ramp_start_mm_s, planned.ramp_end_mm_s, planned.duration_s)
            self.drum.set_profile(SpeedProfile.RAMP)
            self.drum.run()
        spinup_s = time.monotonic() - t_run
        _abort_if(stop_event)

        statuses: list[_Status] = []
        started_utc = _utc_now()
        # the capture is paced on the drum client's clock, the clock of the frames' host times and the status
        # times (wall time on a real link; simulated time in-process, where a wait advances the simulation)
        clock = self.drum.clock
        replay = self.backend if self.mode == "replay" and isinstance(self.backend, ReplayProvenance) else None
        # a replayed trial follows the source's next trial (from the frame that carries its first sample), not the
        # drum's index; the capture starts first, so that frame is always in it (the frames before it: in flight).
        # Switched first, the rig sent that frame and more before the capture began whenever the host thread lost
        # the CPU between the two (a trial then started 10 to 3,336 samples into its source trial)
        self.stream.begin_capture()
        cue = replay.begin_source_trial() if replay is not None and not self.replay_continuous else None
        t_start = clock.now()
        deadline = t_start + 3 * planned.duration_s + CAPTURE_MARGIN_S
        align = not planned.is_ramp and replay is None
        n_capture = n_limit = n
        replay_margin = int(math.ceil(REPLAY_MARGIN_S * rate))
        if cue is not None:
            n_capture = n + replay_margin + 8
            n_limit = n + int(math.ceil(REPLAY_IN_FLIGHT_MAX_S * rate))
        t_index = math.nan  # when the index pulse is predicted, on the clock of the frames' host times
        tolerance_s = INDEX_PREDICTION_TOLERANCE_S
        if align:
            # predict the index pulse from the drum angle; capture up to it + the trial + a margin
            rev_s = DRUM_CIRCUMFERENCE_MM / planned.speed_mm_s
            t_asked = clock.now()
            st = self.drum.read_status()
            t_read = clock.now()
            to_index_s = (360.0 - float(st.angle_deg)) % 360.0 / 360.0 * rev_s
            # the angle is from some time between the request and its answer (a loaded host's Modbus read, with a
            # retry, took up to 2.8 s beside two CPU hogs): the index is due between t_asked and t_read plus to_index_s
            t_index = 0.5 * (t_asked + t_read) + to_index_s
            tolerance_s = max(tolerance_s, INDEX_PREDICTION_TOLERANCE_REVS * rev_s) + 0.5 * (t_read - t_asked)
            n_capture = n + int(math.ceil((t_read - t_start + to_index_s) * rate)) + INDEX_MARGIN_FRAMES
            n_limit = n + int(math.ceil(INDEX_TIMEOUT_REVS * rev_s * rate))
            n_capture = min(n_capture, n_limit)
            deadline += INDEX_TIMEOUT_REVS * rev_s
        next_poll = t_start
        frames_seen, t_frame = self.stream.stats.frames, t_start
        try:
            while True:
                now = clock.now()
                if self.stream.wait_capture(n_capture, timeout_s=max(0.0, next_poll - now)):
                    if cue is not None:  # the source trial's frames from its first one on; more frames in flight
                        k_cue = self.stream.capture_seq_index(cue)  # before it than the margin: a longer capture
                        want = k_cue + n if k_cue is not None else n_capture + replay_margin
                        if want <= n_capture or n_capture >= n_limit:
                            break
                        n_capture = min(want, n_limit)
                        continue
                    if not align:
                        break
                    # the index pulse came later in the capture than the drum angle predicted (the boards' clocks
                    # run apart: two simulated boards on a starved machine, or drift): capture the trial after it
                    # (not seen yet: a little more, up to the limit; a lost index frame is placed afterwards)
                    k_seen = self.stream.capture_flag_index(int(wire.FrameFlag.SYNC_IN))
                    want = k_seen + n if k_seen is not None else n_capture + INDEX_MARGIN_FRAMES
                    if want <= n_capture or n_capture >= n_limit:
                        break
                    n_capture = min(want, n_limit)
                    continue
                now = clock.now()
                if now >= next_poll:
                    s = self._status()
                    statuses.append(s)
                    self._check_fault(s, f"during trial {planned.trial_id}")
                    _check_stall(statuses, planned)
                    next_poll = max(next_poll + STATUS_PERIOD_S, now)
                _abort_if(stop_event)
                got = self.stream.stats
                if got.frames != frames_seen:
                    frames_seen, t_frame = got.frames, now
                if now - t_frame > CAPTURE_STALL_S or now > deadline:
                    why = (f"no frame for {now - t_frame:.1f} s" if now - t_frame > CAPTURE_STALL_S
                           else f"too few frames within {now - t_start:.1f} s")
                    raise CaptureError(
                        f"trial {planned.trial_id}: the taxel stream stalled: {why} (stream connected="
                        f"{got.connected}, {got.frames_per_s:.0f} frames/s)")
            statuses.append(self._status())
        finally:
            cap = self.stream.end_capture()
            self.last_capture_frames = len(cap)
        if self.clock_fit is None or self.clock_fit.nominal_rate_hz != rate:
            self.clock_fit = DeviceClockFit(rate)
        clock_fit = self.clock_fit
        counts = clock_fit.add(cap.seq, cap.host_time_s)
        self.drum.stop_drum()

        # the trial's frames made into its data on a thread of its own while this one feeds the drum controller's
        # watchdog (the force loop still holds): the first trial's lazy imports and fits took 1.6-5.3 s of wall at
        # load ~15 on the thread that feeds it, and a simulated Mega alone (its world run on the heartbeat's wall-time
        # grants) latched WATCHDOG after 4.2 s of its time (the fault campaign under simavr, issue 80 item 4)
        def finish() -> TrialData:
            nonlocal cap, counts
            k = lost = 0
            if align:
                try:
                    k, lost = locate_index(cap, n, t_index, rate_hz=rate, tolerance_s=tolerance_s)
                except CaptureError as exc:
                    raise CaptureError(f"trial {planned.trial_id}: {exc} ({len(cap) / rate:.1f} s at "
                                       f"{planned.speed_mm_s:g} mm/s)") from None
                if lost:
                    log.warning("trial %d: the index frame was lost; the trial starts after the %d-frame gap where the "
                                "drum angle predicts the index", planned.trial_id, lost)
            elif cue is not None:  # start at the frame of the source trial's first sample (the frames before: in flight)
                k_cue = first_with_seq([(cap.samples, cap.seq, cap.flags, cap.host_time_s)], cue)
                if k_cue is None:  # never a trial started elsewhere in the source, silently
                    raise CaptureError(f"trial {planned.trial_id}: the replayed source trial's first frame (sequence "
                                       f"number {int(cue)}) is not among the {len(cap)} frames captured")
                k = k_cue
            if k:
                cap = type(cap)(cap.samples[k:], cap.seq[k:], cap.flags[k:], cap.host_time_s[k:],
                                dropped=cap.dropped, crc_errors=cap.crc_errors)
                counts = counts[k:]
            ring = getattr(self.stream, "ring", None)  # a live stream's recent frames (in-process: once a live consumer asked)
            host_rate = math.nan
            if ring is not None and len(cap) >= n:
                _, ring_seq, ring_t = ring.timing_since(0)
                upto = ring_t <= cap.host_time_s[n - 1]
                host_rate = history_rate_hz(ring_seq[upto], ring_t[upto], rate, min_frames=n)
            data = _trial_data(planned, cap, n, statuses, started_utc=started_utc, settle_s=settle_s, spinup_s=spinup_s,
                               layout=layout, host_rate_hz=host_rate)
            data.attrs.update(aligned_to_index=bool(align), index_wait_frames=k, index_frame_lost=lost)
            if replay is not None and len(cap) >= n:
                data.attrs.update(replay.source_provenance(int(cap.seq[n - 1]), n))
            clock_attrs = trial_clock_attrs(clock_fit, counts[:n], cap.host_time_s[:n])
            data.attrs.update(clock_attrs)
            t_first = clock_attrs["fitted_time_origin_s"]
            data.attrs.update(recorded_means(statuses, t_first, t_first + float(counts[n - 1] - counts[0]) *
                                             clock_attrs["clock_period_s"]))
            data.attrs.update(mark_attrs(statuses))
            data.attrs.update(index_speed_attrs(planned, statuses[0], statuses[-1], marks_mm_s=data.attrs[
                "drum_speed_marks_mm_s"]))
            if data.attrs["drum_slip"]:  # flagged like a speed mismatch (rigctl info shows it)
                slipped = (f"the drum slipped: a speed-mark interval took {100 * data.attrs['drum_slip_max']:.0f} % more "
                           "steps than it should")
                data.attrs["drum_speed_warning"] = "; ".join(w for w in (data.attrs["drum_speed_warning"], slipped) if w)
                data.attrs["drum_speed_mismatch"] = True
            if data.attrs["drum_speed_mismatch"]:
                log.warning("trial %d: %s", planned.trial_id, data.attrs["drum_speed_warning"])
            return data

        return self.while_fed(finish)


def index_speed_attrs(planned: PlannedTrial, first, last, *, marks_mm_s: float = math.nan) -> dict:
    """What the drum index sensor measured during a trial (docs/session-format.md, trial attributes).

    ``first`` and ``last``: the drum statuses at the start and the end of the capture (``index_source``,
    ``index_period_s``, ``index_steps``, ``index_count``). Returns

    - ``index_source``: "sensor" or "steps" (what marked the index at the end of the trial);
    - ``drum_steps_per_rev_index``: the microsteps the firmware sent between the last two sensor edges (0 without a
      live sensor): how far one step really turns the drum, whatever the speed;
    - ``drum_speed_index_mm_s`` and ``drum_speed_index_method``: the real drum speed of a constant-speed trial,
      ``"marks"`` = ``marks_mm_s``, the mean over the speed-mark intervals inside the capture
      (:func:`rigctl.acquisition.drum_marks.mark_attrs`), when there was one; else
      ``"period"`` = pi x diameter / the index period when both edges of that period fell inside the capture,
      else ``"steps"`` = the setpoint x steps_per_rev x microsteps / ``drum_steps_per_rev_index`` (the step rate
      is the setpoint's; the revolutions per step come from the sensor); NaN and ``""`` when neither is known
      (no sensor, a ramp trial);
    - ``drum_speed_mismatch`` (True when the sensor disagrees with the step count by more than
      :data:`rigctl.core.drum.DRUM_SPEED_TOLERANCE`) and ``drum_speed_warning`` (why, "" when none).

    Geometry: :mod:`rigctl.core.drum`.
    """
    usteps = DRUM_STEPS_PER_REV * DRUM_MICROSTEPS
    steps = int(last.index_steps) if last.index_source == "sensor" else 0
    fresh = (int(last.index_count) - int(first.index_count)) % 65536 >= 2 and last.index_period_s > 0
    speed, method = math.nan, ""
    if not planned.is_ramp and math.isfinite(marks_mm_s):
        speed, method = float(marks_mm_s), "marks"
    elif not planned.is_ramp and fresh:
        speed, method = DRUM_CIRCUMFERENCE_MM / last.index_period_s, "period"
    elif not planned.is_ramp and steps:
        speed, method = planned.speed_mm_s * usteps / steps, "steps"
    why = []
    if steps and abs(usteps / steps - 1.0) > DRUM_SPEED_TOLERANCE:
        why.append(f"the drum turned once every {steps} microsteps, the firmware assumes {usteps} (is the driver "
                   f"set to {DRUM_MICROSTEPS * steps / usteps:g} microsteps instead of {DRUM_MICROSTEPS}?)")
    if method in ("period", "marks") and abs(speed / planned.speed_mm_s - 1.0) > DRUM_SPEED_TOLERANCE:
        why.append(f"the index sensor measured {speed:.1f} mm/s at a setpoint of {planned.speed_mm_s:g} mm/s "
                   "(wrong microstep setting, or the Mega's step timing?)")
    return {"index_source": str(last.index_source), "drum_speed_index_mm_s": float(speed),
            "drum_speed_index_method": method, "drum_steps_per_rev_index": steps, "drum_speed_mismatch": bool(why),
            "drum_speed_warning": "; ".join(why)}


def locate_index(cap, n: int, t_index: float, *, rate_hz: float,
                 tolerance_s: float = INDEX_PREDICTION_TOLERANCE_S) -> tuple[int, int]:
    """Where a constant-speed trial starts in its capture: at the drum's index mark.

    Parameters
    ----------
    cap : the capture (``seq``, ``flags``, ``host_time_s`` (s), ``len(cap)`` frames).
    n : frames the trial keeps from its start.
    t_index : when the drum angle predicts the index pulse, s, on the clock of ``cap.host_time_s`` (NaN: unknown).
    rate_hz : the link's frame rate, Hz.
    tolerance_s : how far from ``t_index`` a gap may lie to hold the lost index frame, s. A gap's time is when the
        board sent the frames around it: their stamps less their delay over the capture's least-delayed frame (at
        ``rate_hz``, from the sequence numbers; a loaded host delivers stretches of frames over a second late).

    Returns
    -------
    (k, lost)
        ``k``: the trial's first frame in the capture. ``lost`` = 0: frame ``k`` is the first frame flagged
        ``SYNC_IN`` with ``n`` frames after it. Otherwise the index frame was lost on the link: the index is placed
        in the sequence gap of ``lost`` <= :data:`INDEX_GAP_MAX_FRAMES` frames nearest to ``t_index`` (within
        ``tolerance_s``, before any later ``SYNC_IN`` frame, with ``n`` frames after it), and
        ``k`` is the first frame after that gap: the trial starts at most ``lost`` frames after the index mark
        (exactly 1 frame after it when the index frame alone was lost) and loses no frame of its own. A restart of
        the stream (``STREAMING_START``) is not such a gap.

    Raises
    ------
    CaptureError
        No usable index frame and no gap that explains it (the trial is then recorded again by the runner's retry
        policy: the next attempt waits for the next index pulse).
    """
    n_cap = len(cap)
    sync = np.flatnonzero(cap.flags & wire.FrameFlag.SYNC_IN)
    usable = sync[n_cap - sync >= n]
    if usable.size:
        return int(usable[0]), 0
    if n_cap > 1 and math.isfinite(t_index):
        seq = cap.seq.astype(np.int64)
        gap = (seq[1:] - seq[:-1] - 1) & 0xFFFF
        after = np.arange(1, n_cap)  # the frame after each gap
        t = np.asarray(cap.host_time_s, dtype=np.float64)
        # when the board sent each frame: the least-delayed frame's stamp, on at the frame rate by the sequence
        # (each stream, from its STREAMING_START on, for itself)
        index = np.concatenate(([0], np.cumsum((seq[1:] - seq[:-1]) & 0xFFFF))) / float(rate_hz)
        stream = np.cumsum((cap.flags & wire.FrameFlag.STREAMING_START) != 0)
        starts = np.flatnonzero(np.r_[True, stream[1:] != stream[:-1]])
        offset = np.minimum.reduceat(t - index, starts)
        sent = index + np.repeat(offset, np.diff(np.r_[starts, n_cap]))
        before_t, after_t = sent[:-1], sent[1:]
        dist = np.maximum(0.0, np.maximum(before_t - t_index, t_index - after_t))
        ok = ((gap > 0) & (gap <= INDEX_GAP_MAX_FRAMES) & (n_cap - after >= n)
              & ((cap.flags[1:] & wire.FrameFlag.STREAMING_START) == 0)
              & (dist <= tolerance_s))
        if sync.size:
            ok &= after <= sync[0]
        if ok.any():
            i = int(np.flatnonzero(ok)[np.argmin(dist[ok])])
            return int(after[i]), int(gap[i])
    if sync.size:
        k = int(sync[0])
        raise CaptureError(f"the index pulse came {k} frames into the capture, only {n_cap - k} of {n} frames "
                           "follow it")
    raise CaptureError(f"no drum index pulse (SYNC_IN) in {n_cap} frames, and no short gap where it was predicted")


def _check_stall(statuses: list[_Status], planned: PlannedTrial) -> None:
    """Raise DrumStall when the last two status reads of a capture found the drum RUNNING at less than
    :data:`STALL_FRACTION` of the trial's slowest speed."""
    slowest = min(planned.ramp_start_mm_s, planned.ramp_end_mm_s) if planned.is_ramp else planned.speed_mm_s
    last = statuses[-2:]
    if len(last) == 2 and all(s.state == DrumState.RUNNING and abs(s.speed_mm_s) < STALL_FRACTION * slowest
                              for s in last):
        raise DrumStall(f"trial {planned.trial_id}: the drum turns at {last[-1].speed_mm_s:.1f} mm/s while told "
                        f"{slowest:g} mm/s")


class StopFlag(Protocol):
    """What a trial checks for an abort (a ``threading.Event``, or the run engine's combined flag)."""

    def is_set(self) -> bool: ...


def _abort_if(stop_event) -> None:
    if stop_event is not None and stop_event.is_set():
        raise TrialAborted("trial aborted on request")


def count_dropped(seq: np.ndarray, flags: np.ndarray, host_time_s: np.ndarray,
                  rate_hz: float = PAPER_SENSOR.sample_rate_hz) -> int:
    """Frames missing among consecutive frames: 16-bit sequence gaps (wrap-aware).

    Where the stream restarted (a STREAMING_START frame, e.g. after a reconnect) the device's counter restarted,
    so the gap is estimated from the host time instead (at ``rate_hz``, the sensor's frame rate).
    """
    if len(seq) < 2:
        return 0
    s = seq.astype(np.int64)
    gaps = (s[1:] - s[:-1] - 1) & 0xFFFF
    restart = (flags[1:] & wire.FrameFlag.STREAMING_START) != 0
    if restart.any():
        dt = np.diff(host_time_s)[restart]
        gaps[restart] = np.maximum(0, np.round(dt * float(rate_hz)).astype(np.int64) - 1)
    return int(gaps.sum())


def history_rate_hz(seq: np.ndarray, host_time_s: np.ndarray, rate_hz: float, *, min_frames: int) -> float:
    """The device's frame rate on the host clock (frames/s) over the stream's unbroken history that ends with the
    last frame given: :func:`rigctl.core.trial.lower_envelope_rate_hz` of the frames back to where the device's
    counter restarted or the link was gone (a sequence step of 0 or of more than 1 s of frames, or a host-time gap
    that disagrees with a step of more than one frame by more than 1 s). NaN if that history has fewer than
    ``min_frames`` frames.

    A trial's ``host_rate_hz`` is measured this way over the live ring (up to its ``ring_seconds``, at least the
    trial): the device's crystal clock does not change between trials, and a longer baseline keeps a loaded
    host's late deliveries over a part of the trial from moving the estimate (the per-trial lower envelope read
    994-998 Hz for a 1 kHz board when the reader stalled for 0.2-0.3 s at a time over a third of a 2 s trial).
    Two consecutive frames (a step of one) were sent one period apart, however long the host took to deliver the
    second: a host that delivered nothing for over a second and then the backlog (a starved reader, simulator or
    pty) does not end the history. Cut there, the history began with the backlog draining (a simulated rig stopped
    for 1.3 s: its frames 1.28 s late, draining over 1,600 frames), and a trial inside the drain read the drain's
    rate (a CI run: 1,313 Hz for a 1 kHz board).
    """
    seq = np.asarray(seq, dtype=np.int64)
    t = np.asarray(host_time_s, dtype=np.float64)
    if len(seq) < max(6, min_frames):
        return math.nan
    rate = float(rate_hz)
    steps = (seq[1:] - seq[:-1]) & 0xFFFF
    broken = (steps == 0) | (steps > rate) | ((steps > 1) & (np.abs(np.diff(t) * rate - steps) > rate))
    start = int(np.flatnonzero(broken)[-1]) + 1 if broken.any() else 0
    if len(seq) - start < max(6, min_frames):
        return math.nan
    return lower_envelope_rate_hz(seq[start:], t[start:], rate)


def recorded_means(statuses: list[_Status], t_first: float, t_last: float) -> dict[str, float]:
    """A trial's ``force_mean_g`` (g) and ``speed_mean_mm_s`` (mm/s): the means of the drum status reads
    (``statuses``, in time order) from ``t_first`` to ``t_last`` (s, on the clock of the status times): when the
    board recorded the trial's first and last frames (their fitted host times, :mod:`rigctl.acquisition.clock`).

    Not their receive times: a host or simulated rig starved for a second or two delivers that much of the stream
    within ms (a 2 s trial's 2,000 frames arrived within 0.13 s after a 2 s stall of ``acquire --sim``), and the
    status read in flight across the stall is stamped (halfway between request and answer) before the burst, so a
    trial received whole inside one burst held no status read (a loaded CI run: ``force_mean_g`` NaN). When no read
    lies in the window (the host read no status while the board recorded the trial), the traces are interpolated
    between the reads just before and after it; NaN without any read.
    """
    t = np.array([s.t for s in statuses], dtype=np.float64)
    out = {"force_mean_g": math.nan, "speed_mean_mm_s": math.nan}
    if not t.size:
        return out
    inside = (t >= t_first) & (t <= t_last)
    for key, trace in (("force_mean_g", [s.force_g for s in statuses]),
                       ("speed_mean_mm_s", [s.speed_mm_s for s in statuses])):
        v = np.asarray(trace, dtype=np.float64)
        out[key] = float(v[inside].mean()) if inside.any() else float(np.interp(0.5 * (t_first + t_last), t, v))
    return out


def _trial_data(planned: PlannedTrial, cap, n: int, statuses: list[_Status], *, started_utc: str, settle_s: float,
                spinup_s: float, layout: SensorLayout, host_rate_hz: float = math.nan) -> TrialData:
    if len(cap) < n:
        raise CaptureError(f"trial {planned.trial_id}: captured {len(cap)} frames, {n} needed")
    t0 = float(cap.host_time_s[0])
    force_t = np.array([s.t for s in statuses]) - t0
    force = np.array([s.force_g for s in statuses])
    speed = np.array([s.speed_mm_s for s in statuses])
    seq, flags, host_t = cap.seq[:n], cap.flags[:n], cap.host_time_s[:n] - t0
    data = TrialData(
        taxels=cap.samples[:n], seq=seq, flags=flags, host_time_s=host_t,
        force_g=force, force_time_s=force_t, speed_mm_s=speed, speed_time_s=force_t.copy(),
        dropped_frames=count_dropped(seq, flags, host_t, layout.sample_rate_hz), crc_errors=int(cap.crc_errors),
        layout=layout,
    )
    data.attrs.update(
        started_utc=started_utc,
        settle_time_s=round(settle_s, 4),
        spinup_time_s=round(spinup_s, 4),
        # over the stream's history up to the trial's end when the runner has it (history_rate_hz), else the trial's
        host_rate_hz=data.host_rate_hz() if math.isnan(host_rate_hz) else float(host_rate_hz),
        status_samples=int(len(statuses)),
    )
    return data
