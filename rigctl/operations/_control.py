"""An open rig as the operator drives it: :class:`RigControl` and :func:`open_control`.

What the CLI and the GUI both do with a rig, once: open it (moving nothing: a latched fault refused or left for the
operator to see; the first start HOMEs), check manual setpoints against the controller's limits, run the drum at a
speed and force (press, wait for the force to settle, then run, so the drum never turns before the sensor is
loaded), stop, tare, home (a start), clear a
fault, mount a plate, read the status. Every call blocks until the controller has done it (the GUI runs them in its
command thread); errors are the library's (:mod:`rigctl.core.drum`: ``SetpointRangeError`` before anything is
sent, ``DrumError`` / ``DrumTimeout`` / ``DrumFault`` from the controller).
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from rigctl.acquisition.rig import Rig
from rigctl.acquisition.safety import Acknowledgement, Latch, LatchedFault
from rigctl.core.drum import DrumLimits, DrumStatus, SetpointRangeError
from rigctl.core.faults import FaultInjector
from rigctl.core.interfaces import MassPlacer, TaxelSource
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.operations._drum_view import DrumView
from rigctl.operations._monitor import RigEvent, RigMonitor
from rigctl.operations._rules import Event, Refused, SafetyState, Transition, decide
from rigctl.operations._setpoints import SetpointRefusal, setpoint_refusals
from rigctl.operations._source import RigSource
from rigctl.rigs import open_rig

if TYPE_CHECKING:
    from rigctl.simulation.model import RigConfig

__all__ = ["Home", "RigControl", "RunStarted", "open_control", "rig_of"]

log = logging.getLogger(__name__)


class Home(enum.Enum):
    """What :func:`open_control` does with a fault the controller latches when the rig opens. Whatever the policy,
    opening moves nothing and never acknowledges (docs/safety.md, hazard table 'opening a face'): the rig is left as
    the controller holds it and the first start (a press, a run's first trial, :meth:`RigControl.home`) HOMEs and
    TAREs. The values name where that HOME happens: at the start."""

    #: a latched fault fails the opening (:class:`rigctl.acquisition.rig.FaultAtOpen`): ``rigctl acquire``
    ALWAYS = "always"
    #: a latched fault is kept for the operator to see and acknowledge (the GUI, ``rigctl doctor``)
    UNLESS_FAULTED = "unless_faulted"
    #: as UNLESS_FAULTED (kept for callers that said "never")
    NEVER = "never"
    #: as UNLESS_FAULTED (``rigctl serve``: a restarted server never moves by itself)
    AT_START = "at_start"


@dataclass(frozen=True)
class RunStarted:
    """What :meth:`RigControl.run_at` did: the drum runs at ``speed_mm_s`` with the force loop holding ``force_g``;
    the force settled after ``settle_s`` s."""

    speed_mm_s: float
    force_g: float
    settle_s: float


def open_control(source: RigSource | None = None, *, home: Home | str = Home.ALWAYS, config: RigConfig | None = None,
                 seed: int = 0, host_config_path: str | os.PathLike[str] | None = None,
                 prompt: Callable[[str], object] | None = None,
                 textures: TextureSet | None = None,
                 acknowledge: tuple[str, str] | None = None) -> "RigControl":
    """Open the rig ``source`` names (default: the simulated rig) and start its taxel stream.

    Parameters
    ----------
    source : the rig (:class:`RigSource`: kind, ports or recording).
    home : :class:`Home` (or its value): a latched fault fails the opening (``ALWAYS``) or is kept for the
        operator (the others). Opening moves nothing: the first start HOMEs and TAREs (docs/safety.md).
    acknowledge : ``(reason, by)``: an operator acknowledges at open a fault the controller holds (``--ack
        REASON``): cleared without moving (:meth:`RigControl.acknowledge`, logged), kept in
        ``Rig.acknowledged_at_open`` for the run's session; nothing latched: nothing to do.
    config, seed : the simulated rig's model configuration (:class:`rigctl.simulation.model.RigConfig`) and seed
        (simulated kinds; ignored on hardware).
    host_config_path : the rig config file (calibration); None: the library's default.
    prompt : operator prompt for plate changes on hardware (``prompt(message)``; default: the terminal).
    textures : the texture set plates are mounted from (default: the paper's 16 textures).

    Returns
    -------
    RigControl (a context manager; closing it stops the rig safely).

    Raises
    ------
    rigctl.acquisition.rig.RigError
        The backend cannot start or the boards do not answer (:class:`rigctl.acquisition.rig.RigOpenError`, also a
        ``DrumError``, when the controller failed while the rig was prepared; it says whether STOP was acknowledged).
    rigctl.acquisition.rig.FaultAtOpen
        ``home=ALWAYS`` and the controller latches a fault (the rig is closed).
    """
    source = source or RigSource()
    home = Home(home)
    opts = source.open_options()
    kind = opts.pop("kind")
    if kind != "hardware":
        opts.update(config=config, seed=seed)
    if textures is not None:
        opts["textures"] = textures
    rig = open_rig(kind, prompt=prompt, host_config_path=host_config_path,
                   refuse_fault=home is Home.ALWAYS and acknowledge is None, **opts)
    control = RigControl(rig, source)
    if not control.has_drum:  # the handheld rig: no actuator, no latch of a controller
        return control
    try:
        # the table's open: the rig as the controller left it, read and left so (nothing moves); refused only for
        # a face that holds it already, which the ports' own locks refused before this
        control._decide(Event.OPEN, dataclasses.replace(control.safety_state(), link=False))
        if acknowledge is not None and control.latch is not None:  # found at open: the operator's acknowledgement,
            # given with the command; it moves nothing either (the first start HOMEs)
            rig.acknowledged_at_open = control.acknowledge(acknowledge[0], by=acknowledge[1])
    except BaseException:
        control.close()
        raise
    return control


class _Run(Protocol):
    """What :meth:`RigControl.stop` asks of the run recording on the rig (:class:`rigctl.operations.ProtocolRun`)."""

    def stop(self) -> None: ...


def rig_of(control: "RigControl") -> Rig:
    """The acquisition layer's :class:`rigctl.acquisition.rig.Rig` that ``control`` owns: for the operator layer's own
    modules (the run engine, the calibration, the doctor) and for tests that look inside. Never a face's: the faces
    (CLI, GUI, server, LSL feed, protocols) hold the :class:`RigControl` and its events only (the import-linter
    contracts ``faces-public-api`` and ``faces-never-reach-the-rig`` keep them off this module and the rig's)."""
    return control._rig


class RigControl:
    """An open rig, driven as an operator does (see the module docstring). Open one with :func:`open_control`; the
    :class:`rigctl.acquisition.rig.Rig` it owns is private to the operator layer (:func:`rig_of`).

    Attributes
    ----------
    source : the :class:`RigSource` it was opened from
    active_run : the protocol run recording on this rig now (:class:`rigctl.operations.ProtocolRun` registers
        itself), which :meth:`stop` pauses; None
    """

    def __init__(self, rig: Rig, source: RigSource | None = None) -> None:
        self._rig = rig
        self.source = source or RigSource(rig.mode)
        self._monitor: RigMonitor | None = None
        self._stop_listeners: list[Callable[[str], object]] = []
        self.active_run: _Run | None = None
        #: the one lock the table's decisions for this rig are taken under (:meth:`start_allowed`)
        self._rules_lock = threading.RLock()
        #: the table's last transition on this rig (:mod:`rigctl.operations._rules`: an open, a close, an
        #: acknowledgement, a STOP; starts are asked, :meth:`start_allowed`), or None
        self.last_transition: Transition | None = None

    @property
    def monitor(self) -> RigMonitor:
        """The rig's monitor (:class:`rigctl.operations.RigMonitor`, its poll started on first use here): the status
        poll that feeds the controller's watchdog, the event stream faces subscribe to, and the dead man's switch (a
        face's :meth:`~rigctl.operations.RigMonitor.heartbeat`), whose trip is this rig's :meth:`stop`."""
        return self._events().start()

    def subscribe(self, fn: Callable[[RigEvent], object]) -> Callable[[], None]:
        """Call ``fn(event)`` for every :class:`rigctl.operations.RigEvent` of this rig (the one stream of every face:
        the monitor's state / faults / link / dead-man events once its poll runs, the safety latch, a run's progress
        and trial events), without starting the poll (:attr:`monitor` does). Returns the function that
        unsubscribes."""
        return self._events().subscribe(fn)

    def publish(self, event: RigEvent) -> None:
        """Hand ``event`` to every subscriber of this rig's stream (the run engine's progress and trial events)."""
        self._events().publish(event)

    def _events(self) -> RigMonitor:
        if self._monitor is None:
            self._monitor = RigMonitor(self._rig.drum if self.has_drum else None, self.stop)
            self._monitor.subscribe(self._latch_from)
            self._rig.safety.listeners.append(self._latch_event)
            cues = getattr(self._rig, "cue_listeners", None)
            if cues is not None:  # the handheld rig: what its operator is told goes on the stream
                cues.append(self._cue_event)
        return self._monitor

    def _cue_event(self, cue: str, text: str, fields: dict[str, Any]) -> None:
        """The handheld rig told its operator something: a ``prompt`` event (``fields["cue"]``: plate / go)."""
        self.publish(RigEvent("prompt", text, time.monotonic(), fields={"cue": cue, **fields}))

    def _latch_event(self, item: Latch | Acknowledgement) -> None:
        """The safety latch tripped or was acknowledged: a ``latch`` event on the stream."""
        text = (f"acknowledged by {item.by} ({item.reason}): {item.latch.label}" if isinstance(item, Acknowledgement)
                else f"latched: {item.describe()}")
        self.publish(RigEvent("latch", text, time.monotonic(), latch=item))

    def _latch_from(self, event: RigEvent) -> None:
        """The monitor saw a new state or fault bits: a latched fault or an unexpected reset latches the rig (the
        safety policy's :meth:`rigctl.acquisition.rig.Rig.latch_unsafe`), as the rig's own reads do."""
        if event.kind in ("state", "faults") and event.status is not None:
            self._rig.latch_unsafe(event.status, "status poll")

    def on_stop(self, fn: Callable[[str], object]) -> Callable[[], None]:
        """Call ``fn(reason)`` at every :meth:`stop` before the controller is stopped (a run that must pause, not
        retry). Returns the function that removes it."""
        self._stop_listeners.append(fn)
        return lambda: self._stop_listeners.remove(fn) if fn in self._stop_listeners else None

    # ------------------------------------------------------------------------------------------------- the rules
    def safety_state(self, status: DrumStatus | None = None) -> SafetyState:
        """The host's state of this rig for the safety table (:mod:`rigctl.operations._rules`), from the truth: a
        face holds it (this object is open), the latch held, the e-stop's input as ``status`` says (default: as the
        monitor last read it), the run on it (:attr:`active_run`'s state)."""
        st = status if status is not None else (self._monitor.latest if self._monitor is not None else None)
        run = self.active_run
        state = getattr(run, "state", "none") if run is not None else "none"
        return SafetyState(link=True, latch=self.latch is not None,
                           estop=bool(st is not None and getattr(st, "estop_open", False)),
                           run=state if state != "latched" or self.latch is not None else "paused")

    def start_allowed(self, what: str) -> None:
        """Ask the safety table whether a start (``what``: PRESS, RUN, HOME, a run's resume) is allowed now; raises
        :class:`rigctl.acquisition.safety.LatchedFault` naming the latch when a latched fault refuses it (the
        faces' one refusal), :class:`rigctl.operations.SafetyRefused` for any other refusal. Nothing is sent."""
        with self._rules_lock:
            try:
                decide(self.safety_state(), Event.START)
            except Refused:
                latch = self.latch
                if latch is not None:
                    raise LatchedFault(latch, f"{what} refused") from None
                raise

    def _decide(self, event: Event, state: SafetyState | None = None) -> Transition:
        """The table's transition for ``event`` in ``state`` (default: :meth:`safety_state`), under the rules lock
        (its caller holds it while it acts); kept in :attr:`last_transition`. Refused."""
        with self._rules_lock:
            t = decide(state if state is not None else self.safety_state(), event)
            self.last_transition = t
            return t

    # ------------------------------------------------------------------------------------------------- parts
    @property
    def drum(self) -> DrumView:
        """The drum controller, read-only (:class:`rigctl.operations.DrumView`: its status, settings, limits, the
        waits on them, the rig's clock). Nothing a face holds moves the rig by itself: every command goes through
        this object's methods (:meth:`press`, :meth:`run_at`, :meth:`home`, :meth:`stop`, :meth:`tare`, ...), where
        a latched fault refuses it before anything is sent (docs/safety.md)."""
        return DrumView(self._rig.drum)

    @property
    def taxels(self) -> TaxelSource:
        """The taxel stream (its live ring, its link statistics ``stats`` where it keeps them)."""
        return self._rig.stream

    @property
    def layout(self) -> SensorLayout:
        """The sensor the taxel stream delivers (its identify reply)."""
        return self._rig.layout

    @property
    def textures(self) -> TextureSet:
        """The texture set plates are mounted from."""
        return self._rig.textures

    @property
    def has_drum(self) -> bool:
        """False for the handheld rig (no drum: :attr:`drum` raises, the monitor polls nothing, nothing moves by
        itself; STOP pauses its run and tells its operator to lift the finger)."""
        return bool(self._rig.has_drum)

    @property
    def mode(self) -> str:
        """The rig's kind: "sim" | "hil" | "hardware" | "replay" | "inprocess" | "handheld"."""
        return self._rig.mode

    @property
    def plate(self) -> str | None:
        """The label of the plate mounted now (:meth:`mount_plate`), or None when unknown."""
        return self._rig.texture

    @property
    def host_config(self) -> dict[str, Any]:
        """The rig config (the file's content: calibration, ``lsl``, ...) this rig copies into each session (a copy).
        Set it to take up a config just written to the file (the calibration tab): later sessions copy it."""
        return dict(self._rig.host_config)

    @host_config.setter
    def host_config(self, config: dict[str, Any]) -> None:
        self._rig.host_config = dict(config)

    def taxel_normalisation(self) -> dict[str, Any] | None:
        """The rig config's per-taxel normalisation block (``taxel_min`` / ``taxel_max``, counts), or None."""
        return self._rig.taxel_normalisation()

    def on_marker(self, fn: Callable[[str, float, dict[str, Any]], object]) -> Callable[[], None] | None:
        """Call ``fn(name, host_time_s, fields)`` at each marker the rig itself emits (the handheld rig: a scan's
        entry into and exit from the plate's used middle). Returns the function that removes it, or None when this
        rig emits none (the drum rigs: their state comes from :attr:`monitor` and the taxel stream)."""
        listeners = getattr(self._rig, "marker_listeners", None)
        if listeners is None:
            return None
        listeners.append(fn)
        return lambda: listeners.remove(fn) if fn in listeners else None

    @property
    def bench(self) -> FaultInjector | None:
        """The simulated bench's hand, for tests, demos and training (None on hardware): :meth:`inject_faults
        <rigctl.core.faults.FaultInjector.inject_faults>` presses the e-stop, resets the controller, reverses the
        load cell or the actuator, blocks the drum, cuts a link, on the rig's own clock from now (``--inject``'s
        faults, docs/safety.md; a new schedule replaces the one armed before), and ``fault_refusal`` says what this
        rig cannot model."""
        backend = self._rig.backend
        return backend if isinstance(backend, FaultInjector) else None

    @property
    def places_mass(self) -> bool:
        """True when the rig rests a calibration mass itself (the simulated backends)."""
        return isinstance(self._rig.backend, MassPlacer)

    # ------------------------------------------------------------------------------------------------- life
    def close(self) -> None:
        """The table's close (:mod:`rigctl.operations._rules`: never refused while open): stop the monitor, stop the
        rig safely and close it (never raises a device error)."""
        with self._rules_lock:
            try:
                self._decide(Event.CLOSE)
            except Refused:  # (closed already: closing again does what it did)
                pass
            if self._monitor is not None:
                self._monitor.close()
            self._rig.close()

    def __enter__(self) -> "RigControl":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------- setpoints
    def limits(self) -> DrumLimits:
        """The controller's hard limits (read from it). DrumError."""
        return self.drum.limits()

    def refusals(self, *, speed_mm_s: float | None = None, force_g: float | None = None,
                 limits: DrumLimits | None = None) -> list[SetpointRefusal]:
        """Why the given manual setpoints cannot be sent (empty when they can), under ``limits`` (default: read from
        the controller)."""
        return setpoint_refusals(limits or self.limits(), speed_mm_s=speed_mm_s, force_g=force_g)

    def _check(self, *, speed_mm_s: float | None = None, force_g: float | None = None) -> None:
        limits = self.limits()
        bad = setpoint_refusals(limits, speed_mm_s=speed_mm_s, force_g=force_g)
        if bad:
            rng = limits.speed_range() if bad[0].name == "speed" else limits.force_range()
            raise SetpointRangeError(bad[0].name, bad[0].value, bad[0].unit, rng.low, rng.high, rng.source)

    def apply_setpoints(self, speed_mm_s: float, force_g: float) -> None:
        """Send both setpoints (mm/s, g) once both are accepted; nothing is sent otherwise (SetpointRangeError)."""
        self._check(speed_mm_s=speed_mm_s, force_g=force_g)
        self._rig.drum.set_speed(float(speed_mm_s))
        self._rig.drum.set_force(float(force_g))

    def press(self, force_g: float) -> float:
        """Press to ``force_g`` (g) and wait until the force has settled (:meth:`rigctl.acquisition.rig.Rig.press`);
        returns the time it took, s. SetpointRangeError (nothing sent), DrumTimeout, DrumFault."""
        self.start_allowed("PRESS")  # a refused command sends nothing (not even the setpoint check's read)
        self._check(force_g=force_g)
        return self._rig.press(float(force_g))

    def run_at(self, speed_mm_s: float, force_g: float) -> RunStarted:
        """Run the drum at ``speed_mm_s`` (mm/s) with the force loop holding ``force_g`` (g): both checked first,
        then the speed set, PRESS until the force has settled, RUN. The drum never turns before the sensor is
        loaded. Refused while a fault is latched (:class:`rigctl.acquisition.safety.LatchedFault`) before anything is
        sent, the speed setpoint too. SetpointRangeError (nothing sent), DrumTimeout (the force did not settle),
        DrumFault."""
        self.start_allowed("RUN")
        self._check(speed_mm_s=speed_mm_s, force_g=force_g)
        drum = self._rig.drum
        drum.set_speed(float(speed_mm_s))
        settle_s = self._rig.press(float(force_g))
        self._rig.safety.refuse("RUN")  # a latch that tripped while the force settled
        drum.run()
        return RunStarted(float(speed_mm_s), float(force_g), settle_s)

    # ------------------------------------------------------------------------------------------------- safety
    @property
    def latch(self) -> Latch | None:
        """The latched fault that holds the rig (docs/safety.md), or None. Nothing moves while one is held."""
        return self._rig.safety.latch

    def acknowledge(self, reason: str, *, by: str) -> Acknowledgement:
        """An operator acknowledges the latched fault (the GUI's dialog, ``POST /ack``, ``rigctl acquire --resume``
        or ``--ack``): the condition must be gone (the e-stop released), then the controller is cleared and the latch
        released. Nothing moves: acknowledging is not starting (docs/safety.md). A run waiting on it stays paused
        until its :meth:`rigctl.operations.ProtocolRun.resume` (the acknowledgement goes into its session's event log
        at once, and into the rig's own log); the start (that resume, or the next press) HOMEs and TAREs first.

        Returns the :class:`rigctl.acquisition.safety.Acknowledgement`. Raises ValueError (nothing latched, an empty
        reason), :class:`rigctl.acquisition.safety.LatchedFault` (the condition persists: e.g. the e-stop is still
        pressed; the latch stays), DrumError.

        The table decides (:mod:`rigctl.operations._rules`, event ``acknowledge``) on the controller's status read
        now (the e-stop's contact as it is, not as the last poll saw it): nothing latched is a ValueError, any other
        refusal a LatchedFault naming why; the acknowledgement itself runs under the table's lock."""
        if not self.has_drum:  # the handheld rig: no controller, its own latch
            return self._rig.acknowledge(reason, by=by)
        with self._rules_lock:
            st = self._rig.drum.read_status()
            if self.latch is None:  # a fault the controller latched while nobody asked the rig to move
                self._rig.latch_unsafe(st, "status check")
            try:
                self._decide(Event.ACKNOWLEDGE, self.safety_state(st))
            except Refused as exc:
                latch = self.latch
                if latch is None:
                    raise ValueError("nothing is latched: no fault to acknowledge") from None
                raise LatchedFault(latch, exc.why) from None
            return self._rig.acknowledge(reason, by=by)

    # ------------------------------------------------------------------------------------------------- commands
    def stop(self, reason: str = "STOP") -> bool:
        """STOP (drum to rest, actuator home) for ``reason`` (the operator's STOP, the dead man's switch); the
        :meth:`on_stop` listeners hear it first. Never raises. True when the controller acknowledged it. The table's
        STOP (:mod:`rigctl.operations._rules`: never refused); not under its lock (a STOP waits for nothing)."""
        try:
            self.last_transition = decide(self.safety_state(), Event.STOP)
        except Exception:  # noqa: BLE001 - the STOP itself must go out
            log.exception("the safety table's STOP failed")
        for fn in list(self._stop_listeners):
            try:
                fn(reason)
            except Exception:  # noqa: BLE001 - the STOP itself must go out
                log.exception("a STOP listener failed")
        run = self.active_run  # a protocol run on this rig pauses (the trial in progress discarded, resumable)
        if run is not None:
            run.stop()
        announce = getattr(self._rig, "announce_stop", None)
        if announce is not None and run is not None:  # a handheld block: its operator is told to lift the finger
            try:
                announce(reason)
            except Exception:  # noqa: BLE001 - the STOP itself goes on
                log.exception("telling the operator about the STOP failed")
        return self._rig.safe_stop()

    def stop_drum(self) -> None:
        """Drum to rest, the force loop keeps holding."""
        self._rig.drum.stop_drum()

    def tare(self) -> None:
        """Zero the load cell (actuator released)."""
        self._rig.drum.tare()

    def home(self) -> None:
        """The start (the GUI's Home): wait for the actuator to back off, drive it to its home switch and TARE there;
        blocks until IDLE. Refused while a fault is latched (:class:`rigctl.acquisition.safety.LatchedFault`:
        :meth:`acknowledge` it first). DrumError / DrumTimeout / DrumFault (HOME failed: latched)."""
        self.start_allowed("HOME")
        with self._rig.latching("HOME"):
            self._rig.home_pending = True
            self._rig.home_if_pending()

    def keep_latch(self, latch: Latch) -> Latch:
        """Hold ``latch``, a latched fault a face remembered across its own restart (the run queue's file): nothing
        moves until an operator acknowledges it, whatever the controller says now. Returns the latch held."""
        return self._rig.safety.trip(latch)

    def clear_fault(self, *, by: str = "operator") -> None:
        """Clear the latched faults: an operator's acknowledgement (:meth:`acknowledge`, reason "clear fault") when
        the rig holds a latch, else CLEAR_FAULT (refused by the controller while the condition persists)."""
        if self.latch is not None:
            self.acknowledge("clear fault", by=by)
            return
        self._rig.drum.clear_fault()

    def mount_plate(self, label: str, prompt: Callable[[str], object] | None = None) -> str:
        """Release the sensor and mount plate ``label`` (taken in the set's spelling, ``"l"`` -> ``"L"``); returns
        the label mounted. ValueError (TextureSetError) for a label outside the rig's set, DrumError."""
        label = self.textures.resolve(str(label))
        self._rig.mount_texture(label, prompt)
        return label

    def status(self) -> DrumStatus:
        """The controller's status now; a latched fault or a reset it shows latches the rig (:attr:`latch`: the
        owner's poll sees it whoever commanded the motion). DrumError."""
        st = self.drum.read_status()
        self._rig.latch_unsafe(st, "status poll")
        return st
