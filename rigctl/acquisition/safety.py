"""The rig's one safety policy: which conditions latch, what the rig does then, and what clears them.

Every face (CLI, GUI, server, Python protocols) reaches the rig through :class:`rigctl.acquisition.rig.Rig` (held by
:class:`rigctl.operations.RigControl`), whose :class:`SafetyLatch` this is; none decides what a fault means.

- **Latched** (:func:`latch_for`): every fault the drum controller latches (e-stop, over-force, reversed load cell,
  host watchdog, load cell silent, actuator end of travel, HOME failure, wrong HX711 rate, a drum that slips or
  stalls: its speed marks late), an unexpected reset of the controller (NOT_HOMED or a new BOOT_COUNT), a stalled
  drum; a drum link lost mid-press latches WATCHDOG in the
  controller (seen when the link is back; meanwhile the run ends after a bounded wait, resumable). The rig stops motion
  (STOP), the latch holds (:attr:`SafetyLatch.latch`) and every motion the host asks for (press, run, home) is
  refused with :class:`LatchedFault` until an operator acknowledges it (:meth:`rigctl.acquisition.rig.Rig.acknowledge`:
  the condition must be gone: the e-stop released; then CLEAR_FAULT). Releasing the e-stop never restarts anything,
  and neither does the acknowledgement: it moves nothing; the separate start (a run's resume, the next press) HOMEs
  and TAREs first. A run pauses (``on_latch="wait"``: GUI, server) until the acknowledgement and then the start, or
  ends resumably (``"end"``: ``rigctl acquire``, whose ``--resume`` is the acknowledgement and the start); opening a
  rig never acknowledges. Every latch and acknowledgement goes at once into the rig's own log (:class:`SafetyLog`)
  and the session's event log.
- **Recoverable** (everything else: a dropped frame, a CRC error, a late or lost Modbus answer, a trial that lost
  frames, a force that did not settle): the trial is recorded again (the protocol's ``retries``).

docs/safety.md holds the table: fault -> what the rig does -> what clears it -> what starts again.
"""

from __future__ import annotations

import datetime as _dt
import getpass
import json
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rigctl.core.drum import (
    CRUSH_NOTE,
    FAULT_WORDS,
    HAND_PRESS_STEP,
    DrumError,
    DrumFault,
    DrumReset,
    Fault,
    describe_faults,
)
from rigctl.core.parts import Part

__all__ = ["Latch", "Acknowledgement", "ConfigResolution", "LatchedFault", "DrumStall", "SafetyLatch", "SafetyLog", "latch_for",
           "latch_from_faults", "CAUSES", "CAUSE_PARTS", "FAULT_CAUSES", "operator_name", "safety_log_path"]

log = logging.getLogger(__name__)

#: what a crush-class cause's remedy adds (rigctl.core.drum.CRUSH_FAULTS)
_CRUSH = f" ({CRUSH_NOTE})"

#: every latch cause: (label, what the operator does before acknowledging)
CAUSES: dict[str, tuple[str, str]] = {
    "estop": ("e-stop", "release the e-stop"),
    "force-limit": ("force limit exceeded", "check the plate and the sensor, FORCE_G with nothing on the sensor (far "
                    "from 0 g: its zero moved, recalibrate), the actuator's coupling (its set screws) and the HX711's "
                    "DOUT and SCK wires, then lower the force setpoint; latched again: check that the lead screw "
                    "turns freely" + _CRUSH),
    "reversed-cell": ("load cell reversed", "with nothing touching the sensor read FORCE_G: far from 0 g, its zero "
                      "moved: recalibrate the load cell and change no wire; else " + HAND_PRESS_STEP + ": if they "
                      "all fall, swap A+/A- at the HX711 (or turn the cell over); if they all rise, change no wire "
                      "and recalibrate it with the right calibration mass (its scale is wrong)" + _CRUSH),
    "watchdog": ("host watchdog expired", "make sure the host program and its USB link are alive"),
    "loadcell-timeout": ("load cell not responding", "check the HX711's DOUT and SCK wires and its supply, then the "
                                                     "board itself"),
    "actuator-direction": ("actuator turning the wrong way or load cell reversed",
                           "with nothing touching the sensor read FORCE_G: far from 0 g, recalibrate the load cell and "
                           "change no wire; else " + HAND_PRESS_STEP + ": if they all fall, the cell "
                           "is reversed: swap A+/A- at the HX711, not the motor's coils; if they all rise, watch the "
                           "lead screw while HOME creeps: moving the right way, change no wire and check the home "
                           "switch and its wire; only if you see it close the gap to the sensor swap one coil pair of "
                           "the actuator motor (rigctl doctor --check actuator-direction)" + _CRUSH),
    "actuator-travel": ("actuator end of travel", "mount a plate, check the gap between drum and sensor, the "
                                                  "actuator's coupling (its set screws), the load cell's wires (A+, "
                                                  "A-, E+, E-) and that the actuator turns the right way (a coil "
                                                  "pair swapped drives it into its rear stop while its steps count "
                                                  "on), then the cell itself"),
    "home-failed": ("HOME failed", "check the home switch and its wire, then that the lead screw turns freely and the "
                                   "driver is enabled"),
    "hx711-rate": ("wrong HX711 rate", "set the HX711's RATE pin (or the rig config's force_loop) to match; seen "
                   "again with no power cycle of yours, the controller reset by itself: check its power and reset "
                   "line"),
    "reset": ("controller reset", "check the controller's power and reset line, and that nothing presses the sensor"),
    "stall": ("drum stalled or slipping", "check the drum's drive (its coupling, the stepper and its driver's "
              "current) and free the drum (nothing may block it)"),
    "contact-stiffness": ("contact too stiff", "use a softer plate, sensor mount or pad; on the calibrated plate, check "
                          "the excitation leads (E+, E-) and the calibration mass (a scale too high reads as a stiffer "
                          "contact); else store slower force-loop gains (the rig config's force_loop)" + _CRUSH),
    "position-limit": ("pressed past the contact's limit", "the reading disagreed with the position: check the plate "
                       "or mount (changed since the probe), the HX711's DOUT and SCK wires, the calibration mass, "
                       "that no coil pair of the actuator is swapped, then a frozen HX711 (rigctl doctor)" + _CRUSH),
    "hx711-stuck": ("load-cell reading frozen", "power-cycle the rig, then check the HX711's DOUT and SCK wires"
                    + _CRUSH),
    "hx711-line": ("load-cell line fault", "check the HX711's SCK and DOUT wires, then the load cell's (E+, E-, A+, "
                   "A-), then the cell itself" + _CRUSH),
    "hx711-cadence": ("load-cell readings too fast", "check the HX711's SCK and DOUT wires" + _CRUSH),
    "contact-lost": ("contact lost while the force held", "the reading did not follow the contact: remove anything "
                     "resting on the sensor or the actuator, check the HX711's DOUT and SCK wires, then a frozen "
                     "HX711" + _CRUSH),
    "loadcell-scale": ("the reading's scale disagrees with the stiffness stored at calibration",
                       "a plate or mount changed since the calibration, the actuator's coupling (its set screws), the "
                       "HX711's DOUT and SCK wires, the load cell's wires (E+, E-, A+, A-), a wrong calibration mass, "
                       "the lead screw binding, the cell itself: check them in that order, then recalibrate with the "
                       "reference mass (rigctl calibrate loadcell, or the GUI's calibration tab)" + _CRUSH),
    "loadcell-zero": ("the load cell read a force with nothing pressing",
                      "remove anything resting on the sensor or the actuator; else the plate or mount changed "
                      "(recalibrate: it stores the new contact) or its zero moved: check the cell's mount, then the "
                      "HX711's DOUT and SCK wires and the cell's cable (E+, E-, A+, A-); latched again with nothing "
                      "on the sensor, the cell itself is failing; the start HOMEs and tares again" + _CRUSH),
    "contact-missing": ("no force where the contact was",
                        "the plate or sample removed or changed (mount it), the actuator's coupling (its set screws), "
                        "the HX711's DOUT and SCK wires, the load cell's wires (A+, A-, E+, E-: an open lead reads no "
                        "load), the lead screw binding or the motor losing steps, a coil pair swapped, a frozen HX711, "
                        "the cell itself: check them in that order; the start HOMEs from where it stands and proves "
                        "its way" + _CRUSH),
}

#: the parts each latch cause's remedy (:data:`CAUSES`) names, in the order it names them: most likely first
#: (rigctl.core.parts.less_likely_first; its exceptions in rigctl.core.parts.ADVICE_ORDER_EXCEPTIONS); issue 75 item 4
CAUSE_PARTS: dict[str, tuple[Part, ...]] = {
    "estop": (Part.E_STOP,),
    "force-limit": (Part.PLATE, Part.LOADCELL_ZERO, Part.COUPLING, Part.HX711_WIRES, Part.SETPOINT, Part.LEAD_SCREW),
    "reversed-cell": (Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.CALIBRATION),
    "watchdog": (Part.HOST_LINK,),
    "loadcell-timeout": (Part.HX711_WIRES, Part.HX711_CHIP),
    "actuator-direction": (Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.HOME_SWITCH,
                           Part.ACTUATOR_COILS),
    "actuator-travel": (Part.PLATE, Part.COUPLING, Part.LOADCELL_WIRING, Part.ACTUATOR_COILS, Part.LOADCELL),
    "home-failed": (Part.HOME_SWITCH, Part.LEAD_SCREW, Part.DRIVER),
    "hx711-rate": (Part.HX711_RATE_PIN, Part.RIG_CONFIG, Part.CONTROLLER_POWER),
    "reset": (Part.CONTROLLER_POWER,),
    "stall": (Part.DRUM_DRIVE, Part.DRUM_BLOCKED),
    "contact-stiffness": (Part.PLATE, Part.LOADCELL_WIRING, Part.CALIBRATION, Part.RIG_CONFIG),
    "position-limit": (Part.PLATE, Part.HX711_WIRES, Part.CALIBRATION, Part.ACTUATOR_COILS, Part.HX711_CHIP),
    "hx711-stuck": (Part.HX711_CHIP, Part.HX711_WIRES),
    "hx711-line": (Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.LOADCELL),
    "hx711-cadence": (Part.HX711_WIRES,),
    "contact-lost": (Part.LOAD_ON_SENSOR, Part.HX711_WIRES, Part.HX711_CHIP),
    "loadcell-scale": (Part.PLATE, Part.COUPLING, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.CALIBRATION,
                       Part.LEAD_SCREW, Part.LOADCELL),
    "loadcell-zero": (Part.LOAD_ON_SENSOR, Part.PLATE, Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING,
                      Part.LOADCELL),
    "contact-missing": (Part.PLATE, Part.COUPLING, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.LEAD_SCREW,
                        Part.ACTUATOR_COILS, Part.HX711_CHIP, Part.LOADCELL),
}

#: the cause of each controller fault bit (the first that is set names the latch)
FAULT_CAUSES: tuple[tuple[Fault, str], ...] = (
    (Fault.ESTOP, "estop"), (Fault.FORCE_LIMIT, "force-limit"), (Fault.LOADCELL_REVERSED, "reversed-cell"),
    (Fault.WATCHDOG, "watchdog"), (Fault.LOADCELL_TIMEOUT, "loadcell-timeout"),
    (Fault.ACTUATOR_DIRECTION, "actuator-direction"), (Fault.ACTUATOR_TRAVEL, "actuator-travel"),
    (Fault.HOME_NOT_FOUND, "home-failed"), (Fault.HX711_RATE, "hx711-rate"),
    (Fault.DRUM_SLIP, "stall"), (Fault.CONTACT_STIFFNESS, "contact-stiffness"), (Fault.HX711_LINE, "hx711-line"),
    (Fault.HX711_CADENCE, "hx711-cadence"), (Fault.HX711_STUCK, "hx711-stuck"), (Fault.POSITION_LIMIT, "position-limit"),
    (Fault.CONTACT_LOST, "contact-lost"), (Fault.RESET, "reset"), (Fault.LOADCELL_SCALE, "loadcell-scale"),
    (Fault.LOADCELL_ZERO, "loadcell-zero"), (Fault.CONTACT_MISSING, "contact-missing"),
)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def operator_name() -> str:
    """Who is at this terminal (the login name; ``"operator"`` when it cannot be told)."""
    try:
        return getpass.getuser()
    except (OSError, KeyError, ImportError):  # no login name (a container without a passwd entry)
        return "operator"


@dataclass(frozen=True)
class Latch:
    """A latched condition: ``cause`` (a key of :data:`CAUSES`), ``detail`` (what was seen, in words), ``faults``
    (the controller's fault bits, 0 for host-detected causes), ``at_utc`` (ISO 8601 UTC), ``also`` (the other causes
    latched with it or while it was held: two faults at once are both named, logged and cleared together)."""

    cause: str
    detail: str
    faults: int = 0
    at_utc: str = field(default_factory=_utc_now)
    also: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "also", tuple(c for c in dict.fromkeys(self.also) if c != self.cause))

    @property
    def causes(self) -> tuple[str, ...]:
        """Every cause this latch holds, the first one first."""
        return (self.cause, *self.also)

    @property
    def label(self) -> str:
        return " and ".join(CAUSES.get(c, (c, ""))[0] for c in self.causes)

    @property
    def remedy(self) -> str:
        """What the operator does before acknowledging."""
        return "; ".join(dict.fromkeys(CAUSES.get(c, ("", "remove the cause"))[1] for c in self.causes))

    def with_(self, other: "Latch") -> "Latch":
        """This latch and ``other`` (seen while this one was held) as one: both causes, both details, every fault bit."""
        return Latch(self.cause, f"{self.detail}; and {other.label}: {other.detail}", int(self.faults) | int(other.faults),
                     self.at_utc, (*self.also, *other.causes))

    def adds_to(self, held: "Latch") -> bool:
        """Whether this latch names something ``held`` does not (another cause, another fault bit)."""
        return bool(set(self.causes) - set(held.causes)) or bool(int(self.faults) & ~int(held.faults))

    def describe(self) -> str:
        """One line: the cause, what was seen, what to do."""
        return f"{self.label}: {self.detail}; {self.remedy}, then acknowledge"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["also"] = list(self.also)
        return d


@dataclass(frozen=True)
class Acknowledgement:
    """An operator's acknowledgement of :attr:`latch`: ``reason`` (their words), ``by`` (who), ``at_utc``."""

    latch: Latch
    reason: str
    by: str
    at_utc: str = field(default_factory=_utc_now)

    def to_dict(self) -> dict[str, Any]:
        return {"clears": self.latch.to_dict(), "reason": self.reason, "by": self.by, "at_utc": self.at_utc}


@dataclass(frozen=True)
class ConfigResolution:
    """A configuration mismatch the controller latched (not a hazard: HX711_RATE, not :data:`rigctl.core.drum.
    CRUSH_FAULTS`) that the rig's configuration resolved when the rig opened: ``cause`` (a key of :data:`CAUSES`),
    ``faults`` (the bits cleared), ``by`` (what resolved it: ``"rig config"``), ``source`` (its file), ``reason`` (in
    words, e.g. ``"hx711 rate 10 SPS configured, measured 10 SPS"``), ``at_utc``. No operator acknowledgement; it
    moves nothing. Logged as ``kind: "resolved"`` (:class:`SafetyLog`, the run's session)."""

    cause: str
    faults: int
    by: str
    source: str
    reason: str
    at_utc: str = field(default_factory=_utc_now)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class LatchedFault(RuntimeError):
    """The rig holds a latched fault (:attr:`latch`): motion is refused until an operator acknowledges it."""

    def __init__(self, latch: Latch, what: str = "") -> None:
        self.latch = latch
        super().__init__(f"{what + ': ' if what else ''}{latch.describe()}")


class DrumStall(DrumError):
    """The drum does not turn although it is told to (blocked, a stepper that lost its steps): latched."""


def latch_from_faults(faults: int, detail: str = "") -> Latch:
    """The latch of the controller's fault bits ``faults`` (its cause: the first set bit of :data:`FAULT_CAUSES`)."""
    bits = Fault(int(faults))
    causes = [c for bit, c in FAULT_CAUSES if bit in bits] or ["reset"]
    words = detail or (FAULT_WORDS[bits].meaning if bits in FAULT_WORDS else describe_faults(int(bits)))
    return Latch(causes[0], words, int(bits), also=tuple(causes[1:]))


def latch_for(exc: BaseException) -> Latch | None:
    """The latch a failure stands for (None: a recoverable failure, retried)."""
    if isinstance(exc, LatchedFault):
        return exc.latch
    if isinstance(exc, DrumFault):
        return latch_from_faults(exc.faults, str(exc))
    if isinstance(exc, DrumReset):
        return Latch("reset", str(exc))
    if isinstance(exc, DrumStall):
        return Latch("stall", str(exc))
    return None


class SafetyLatch:
    """The rig's latch (one per :class:`rigctl.acquisition.rig.Rig`). Thread-safe.

    Attributes
    ----------
    latch : the condition latched now, or None.
    history : every latch and acknowledgement since the rig opened, in order.
    listeners : callables receiving each :class:`Latch` when it trips and each :class:`Acknowledgement` (the run
        engine writes them into the session's event log; faces show them).
    """

    def __init__(self) -> None:
        self.latch: Latch | None = None
        self.history: list[Latch | Acknowledgement] = []
        self.listeners: list[Callable[[Latch | Acknowledgement], Any]] = []
        self._lock = threading.Lock()
        self.cleared = threading.Condition(self._lock)

    @property
    def latched(self) -> bool:
        return self.latch is not None

    def trip(self, latch: Latch) -> Latch:
        """Latch ``latch``; returns the one held. A latch already held stays the first cause; a second fault (another
        cause or fault bit) joins it (:meth:`Latch.with_`): both are named, shown and logged, and one acknowledgement
        clears both once neither persists."""
        with self._lock:
            held = self.latch
            if held is not None:
                if not latch.adds_to(held):
                    return held
                latch = held.with_(latch)
            self.latch = latch
            self.history.append(latch)
        log.error("LATCHED: %s", latch.describe())
        self._tell(latch)
        return latch

    def refuse(self, what: str) -> None:
        """Raise :class:`LatchedFault` when latched (``what``: the motion refused)."""
        latch = self.latch
        if latch is not None:
            raise LatchedFault(latch, f"{what} refused")

    def clear(self, reason: str, by: str) -> Acknowledgement:
        """Record the acknowledgement of the latch held and clear it (the rig has made the controller safe and ready
        first: :meth:`rigctl.acquisition.rig.Rig.acknowledge`). ValueError when nothing is latched or no reason."""
        reason, by = str(reason).strip(), str(by).strip()
        if not reason or not by:
            raise ValueError("an acknowledgement needs a reason and who gives it")
        with self._lock:
            if self.latch is None:
                raise ValueError("nothing is latched: no fault to acknowledge")
            ack = Acknowledgement(self.latch, reason, by)
            self.latch = None
            self.history.append(ack)
            self.cleared.notify_all()
        log.warning("acknowledged by %s (%s): %s", by, reason, ack.latch.label)
        self._tell(ack)
        return ack

    def wait_cleared(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` (wall time) for the latch to clear; True when clear."""
        with self._lock:
            return self.cleared.wait_for(lambda: self.latch is None, timeout_s)

    def _tell(self, item: Latch | Acknowledgement) -> None:
        for fn in list(self.listeners):
            try:
                fn(item)
            except Exception:  # noqa: BLE001 - a face's listener never breaks the latch
                log.exception("safety listener failed")


def safety_log_path() -> Path:
    """The rig's own safety log: ``$XDG_STATE_HOME/rigctl/safety.jsonl`` (``~/.local/state/rigctl/safety.jsonl``)."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rigctl" / "safety.jsonl"


#: how much of the end of the rig's log :func:`unacknowledged_latch` reads, bytes (memory bounded by this, never by
#: the file's size)
LOG_TAIL_BYTES = 1 << 20


def unacknowledged_latch(rig: dict[str, Any], path: str | os.PathLike[str] | None = None) -> Latch | None:
    """The last latch the rig's own log (:func:`safety_log_path`) holds for the controller ``rig`` names (its
    ``mode`` and ``drum`` port) with no acknowledgement after it, or None. A latch any face saw (a reset under
    load, a stall, a watchdog) is held for every later face until an operator acknowledges it (issue 76: a reset
    latch lived in the face that saw it, and the next ``rigctl acquire`` ran without anyone acknowledging it).
    Reads at most the log's last :data:`LOG_TAIL_BYTES`; a line it cannot read is skipped; no log: None."""
    log_path = Path(path) if path is not None else safety_log_path()
    key = (rig.get("mode"), rig.get("drum"))
    try:
        with open(log_path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - LOG_TAIL_BYTES))
            tail = f.read(LOG_TAIL_BYTES)
    except OSError:
        return None
    pending: Latch | None = None
    for raw in tail.splitlines():
        try:
            entry = json.loads(raw)
            if not isinstance(entry, dict) or not isinstance(entry.get("rig"), dict):
                continue
            if (entry["rig"].get("mode"), entry["rig"].get("drum")) != key:
                continue
            if entry.get("kind") == "latched":
                pending = Latch(str(entry["cause"]), str(entry.get("detail", "")), int(entry.get("faults", 0)),
                                str(entry.get("at_utc", "")), tuple(str(c) for c in entry.get("also", ())))
            elif entry.get("kind") == "acknowledged":
                pending = None
        except (ValueError, KeyError, TypeError):
            continue
    return pending


class SafetyLog:
    """A listener of a :class:`SafetyLatch` that writes every latch and acknowledgement at once (flushed and synced)
    into the rig's own log, one JSON object a line: ``kind`` ("latched" | "acknowledged" | "resolved": a
    :class:`ConfigResolution` the rig writes at open), ``rig`` (what names the
    rig: its kind and ports), then :meth:`Latch.to_dict` or :meth:`Acknowledgement.to_dict`. Whatever face acted,
    with or without a run: the run's session gets the same through the run engine. A log that cannot be written is
    a warning, never a broken latch.

    Parameters
    ----------
    rig : what names the rig in each line (e.g. ``{"mode": "hardware", "drum": "/dev/ttyACM0"}``).
    path : the log file (default :func:`safety_log_path`, read when each line is written).
    """

    def __init__(self, rig: dict[str, Any], path: str | os.PathLike[str] | None = None) -> None:
        self.rig = dict(rig)
        self.path = None if path is None else Path(path)
        self._lock = threading.Lock()

    def __call__(self, item: Latch | Acknowledgement | ConfigResolution) -> None:
        kind = ("acknowledged" if isinstance(item, Acknowledgement) else
                "resolved" if isinstance(item, ConfigResolution) else "latched")
        line = json.dumps({"kind": kind, "rig": self.rig, **item.to_dict()}, default=str)
        path = self.path or safety_log_path()
        try:
            with self._lock:
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "a", encoding="utf-8") as f:
                    f.write(line + "\n")
                    f.flush()
                    os.fsync(f.fileno())
        except OSError as exc:
            log.warning("the rig's safety log %s cannot be written (%s): %s", path, exc.strerror or exc, line)
