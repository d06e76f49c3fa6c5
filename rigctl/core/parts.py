"""The rig's parts an operator's advice can send them to, and how often a lab meets each one's failure (issue 75
item 4): the FMEA's occurrence rating (O, 1-10) of each :class:`Part`, one home (:data:`PARTS`; docs/safety.md's
"Occurrence" table is it, verbatim). Every advice (``rigctl.core.drum.FaultWords.causes`` for each controller fault
bit, ``rigctl.acquisition.safety.CAUSE_PARTS`` for each host latch cause) names its parts most likely first
(:func:`less_likely_first`), except where :data:`ADVICE_ORDER_EXCEPTIONS` says why; :func:`named_at` finds where its
words name a part, so the structure is held to the words the operator reads (tests/core/test_core_advice_causes.py).
"""

from __future__ import annotations

import enum
from typing import NamedTuple

__all__ = ["Part", "PartRating", "PARTS", "ADVICE_ORDER_EXCEPTIONS", "less_likely_first", "named_at"]


class Part(enum.Enum):
    """A part of the rig (or a setting) an advice can send the operator to (issue 75 item 4): the FMEA's parts, each
    with its occurrence rating and the words an advice names it by in :data:`PARTS`. An advice's causes
    (:attr:`FaultWords.causes`, ``rigctl.acquisition.safety.CAUSE_PARTS``) are a tuple of these, in the order its
    words name them: the most likely first (:func:`less_likely_first`)."""

    PLATE = "plate"
    HX711_RATE_PIN = "hx711-rate-pin"
    LOADCELL_ZERO = "loadcell-zero"
    LOAD_ON_SENSOR = "load-on-sensor"
    COUPLING = "coupling"
    HX711_WIRES = "hx711-wires"
    LOADCELL_WIRING = "loadcell-wiring"
    CALIBRATION = "calibration"
    SETPOINT = "setpoint"
    HOST_LINK = "host-link"
    E_STOP = "e-stop"
    DRUM_DRIVE = "drum-drive"
    LEAD_SCREW = "lead-screw"
    HOME_SWITCH = "home-switch"
    RIG_CONFIG = "rig-config"
    DRUM_BLOCKED = "drum-blocked"
    ACTUATOR_COILS = "actuator-coils"
    DRUM_COILS = "drum-coils"
    DRIVER = "driver"
    CONTROLLER_POWER = "controller-power"
    HX711_CHIP = "hx711-chip"
    LOADCELL = "loadcell"


class PartRating(NamedTuple):
    """A :class:`Part`'s row of the FMEA's occurrence ratings (docs/safety.md, "Occurrence"): ``words`` (the part and
    how it fails, for the table), ``occurrence`` (the FMEA's O, 1-10: how often a lab meets that failure; 10 every
    week, 1 hardly ever), ``names`` (the phrases, case-sensitive, an advice names it by: the first found in an advice
    is where it names the part), ``source`` (where the rating comes from: a public issue thread, a note, or
    "judgement")."""

    words: str
    occurrence: int
    names: tuple[str, ...]
    source: str


#: every part's occurrence rating, the one home (docs/safety.md's "Occurrence" table is this, verbatim:
#: tests/core/test_core_advice_causes.py); most likely first
PARTS: dict[Part, PartRating] = {
    Part.PLATE: PartRating(
        "the plate, sample, sensor pad or mount: changed, removed or swapped since the calibration or the probe", 8,
        ("plate",),
        "judgement: a protocol changes plates every session by hand (a run's plate change); LOADCELL_SCALE's own "
        "campaign row (a plate swap)"),
    Part.HX711_RATE_PIN: PartRating(
        "the HX711 board's RATE pin: at 10 SPS where the force loop is set for 80", 7, ("RATE pin",),
        "/work/shared/notes/bench-facts.md: many HX711 boards ship at 10 SPS (RATE pin low)"),
    Part.LOADCELL_ZERO: PartRating(
        "the load cell's zero: drift, a tare taken under load, a mount's preload changed", 7,
        ("far from 0 g", "zero moved", "zero or scale"),
        "bogde/HX711#51 (\"drift is pretty normal with load cells, due to temperature and mechanical settling\"); "
        "montalvo.com, causes and cures for load cell zero-drift (mounting preload)"),
    Part.LOAD_ON_SENSOR: PartRating(
        "something resting on the sensor or the actuator: a hand, a tool, debris", 6, ("resting on the sensor",),
        "judgement: the operator's hands and tools are at the sensor at every plate change"),
    Part.COUPLING: PartRating(
        "the actuator's coupling and its set screws: slipping, loose", 6, ("coupling",),
        "AndrewEllis93/Print-Tuning-Guide#14 (a loose set screw behind layer shifts); Caribou3d/CaribouCartesian#13 "
        "(grub screws that loosened by themselves)"),
    Part.HX711_WIRES: PartRating(
        "the HX711's DOUT and SCK wires: loose, broken, picking up interference", 6,
        ("DOUT and SCK", "SCK and DOUT", "DOUT or SCK"),
        "bogde/HX711#162 (header pins not soldered: spikes, no change with weight); ranenbg/Arduino-FFB-wheel#39 "
        "(\"probably some loose connection ... DT and CLK\")"),
    Part.LOADCELL_WIRING: PartRating(
        "the load cell's wires (E+, E-, A+, A-): swapped, an open joint, an excitation lead", 5, ("A+", "E+"),
        "dangrie158/opencushion#8 (erratic readings from a bridge wired wrong); ranenbg/Arduino-FFB-wheel#39 (A+/A- "
        "reversed); /work/shared/notes/bench-facts.md (A+/A- or E+/E- swapped reverses every reading)"),
    Part.CALIBRATION: PartRating(
        "the calibration: a wrong mass entered, a tare under load, a stale scale", 5, ("calibration mass",),
        "judgement: a person types the mass and places it; docs/safety.md common causes (a wrong calibration saved "
        "with a valid checksum)"),
    Part.SETPOINT: PartRating(
        "the force setpoint: near FORCE_LIMIT on a stiff contact", 5, ("setpoint",),
        "judgement: docs/safety.md (fault-free presses near the limit on stiff mounts latched FORCE_LIMIT, issue 75)"),
    Part.HOST_LINK: PartRating(
        "the host program and its USB link: killed, crashed, a cable pulled", 5, ("USB",),
        "/work/shared/notes/field-notes.md (pyserial #341: an unplugged USB serial device)"),
    Part.E_STOP: PartRating(
        "the e-stop and its normally-closed wire", 5, ("e-stop",),
        "judgement: pressed as meant by the operator; its wire broken far less often"),
    Part.DRUM_DRIVE: PartRating(
        "the drum's drive: its coupling or grub screw, a belt, its stepper's current", 5, ("grub screw", "its coupling"),
        "as the actuator's coupling (AndrewEllis93/Print-Tuning-Guide#14); judgement for the current"),
    Part.LEAD_SCREW: PartRating(
        "the lead screw and the actuator motor: binding, losing steps (too little current)", 4, ("lead screw",),
        "M-Prime/M_Prime_One#1 (a worn screw and nut jamming the axis); judgement"),
    Part.HOME_SWITCH: PartRating(
        "the home switch and its wire: stuck closed, broken", 4, ("home switch",),
        "judgement: a switch and a wire on the moving axis"),
    Part.RIG_CONFIG: PartRating(
        "the rig config's force_loop block: gains or rate for another board", 4, ("force_loop",),
        "judgement"),
    Part.DRUM_BLOCKED: PartRating(
        "something blocking the drum", 4, ("blocks it", "may block it"),
        "judgement"),
    Part.ACTUATOR_COILS: PartRating(
        "the actuator motor's coil pairs: one swapped (a connector turned, a rewiring)", 3, ("coil pair",),
        "judgement: wired once at the build; docs/safety.md (the walker found good motors rewired by advice, "
        "far more often than a bad one)"),
    Part.DRUM_COILS: PartRating(
        "the drum motor's coil pairs: one swapped", 3, ("coil pair of the drum",),
        "judgement: wired once at the build"),
    Part.DRIVER: PartRating(
        "the actuator's driver: its EN line stuck, its current set wrong", 3, ("driver",),
        "judgement"),
    Part.CONTROLLER_POWER: PartRating(
        "the controller's power and reset line: a brown-out, a reset pulse", 3, ("power and reset",),
        "/work/shared/notes/field-notes.md (ArduinoModbus #98: opening the port resets the board); judgement"),
    Part.HX711_CHIP: PartRating(
        "the HX711 chip itself: hung, failed", 2, ("Power-cycle", "power-cycle", "frozen HX711", "the board itself"),
        "ranenbg/Arduino-FFB-wheel#39 (\"low chance that HX711 or load cell died just like that\")"),
    Part.LOADCELL: PartRating(
        "the load cell itself: broken, overloaded, creeping, of another range", 2, ("cell itself", "broken cell"),
        "ranenbg/Arduino-FFB-wheel#39 (a failed cell is the unlikely cause); /work/shared/notes/bench-facts.md "
        "(a cell of another range)"),
}

#: where an advice deliberately names a less likely part before a likelier one, the one place that says so and why:
#: (the advice's key: a fault bit's name or a host latch cause, the part named early) -> why. Every other advice
#: names its parts most likely first (:func:`less_likely_first`)
ADVICE_ORDER_EXCEPTIONS: dict[tuple[str, Part], str] = {
    ("HX711_STUCK", Part.HX711_CHIP): "the power cycle is quick, harmless and changes no wire: it comes before "
                                      "looking at the wires, and clears a hung chip",
    ("hx711-stuck", Part.HX711_CHIP): "as HX711_STUCK's",
    ("LOADCELL_ZERO", Part.LOAD_ON_SENSOR): "looking at the sensor is quick and harmless, and what rests on it is "
                                            "what the next HOME's tare would take for the zero",
    ("loadcell-zero", Part.LOAD_ON_SENSOR): "as LOADCELL_ZERO's",
}


def less_likely_first(key: str, causes: tuple[Part, ...]) -> list[tuple[Part, Part]]:
    """The pairs ``(a, b)`` of ``causes`` (an advice's parts, in the order it names them; ``key`` its fault bit's name
    or host cause) where ``a`` is named before ``b`` but is less likely (:data:`PARTS` occurrence) and no
    :data:`ADVICE_ORDER_EXCEPTIONS` entry says why; ``[]``: most likely first, ties allowed."""
    return [(a, b) for i, a in enumerate(causes) for b in causes[i + 1:]
            if PARTS[a].occurrence < PARTS[b].occurrence and (key, a) not in ADVICE_ORDER_EXCEPTIONS]


def named_at(advice: str, part: Part) -> int:
    """Where ``advice`` first names ``part`` (the index of the first of its :attr:`PartRating.names` found), -1 when it
    does not."""
    found = [i for i in (advice.find(n) for n in PARTS[part].names) if i >= 0]
    return min(found) if found else -1
