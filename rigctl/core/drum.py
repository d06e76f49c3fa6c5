"""The drum controller in the rig's terms: states, faults, status, limits, setpoints, geometry and errors.

Every layer shares these (the device client decodes registers into them, the acquisition layer and the operator
layer decide with them, the CLI and the GUI show them), so they live in :mod:`rigctl.core` and import nothing else
of rigctl's. The numbers of the state codes and fault bits are the wire spec's (``docs/wire-protocol.md`` tables
2.4 and 2.5); ``rigctl.devices.wire`` re-exports these enums and ``tests/test_wire_spec.py`` checks them against the
spec and the firmware header.

Adding to the controller (a register, a status field, a state, a fault bit):

- a state or fault bit: a member of :class:`DrumState` / :class:`Fault` here, with its words in
  :data:`STATE_TEXT` / :data:`FAULT_WORDS`; the spec's table and the header first.
- a status field: a field *with a default* at the end of :class:`DrumStatus` (units in its name, a ``#:`` comment
  saying what it is), decoded in ``rigctl.devices.drum.DrumStatus.from_registers``; a default keeps every other
  backend and test that builds a status valid.

Limits (the one home): the rig's protocol range (:data:`MAX_SPEED_MM_S`, :data:`MAX_FORCE_G`: what any protocol,
manual setpoint or script may ask for) and the controller's own SPEED_LIMIT / FORCE_LIMIT registers
(:class:`DrumLimits`, read from the controller). A setpoint is accepted when it lies in both:
:meth:`DrumLimits.speed_range` / :meth:`DrumLimits.force_range` give that range as a :class:`SetpointRange` with
its unit and the name of the limit that binds (as ophyd-async's signal metadata carries limits with the value),
and :meth:`SetpointRange.check` raises :class:`SetpointRangeError` before anything is sent.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable

from rigctl.core.parts import Part

__all__ = [
    "DrumState", "Fault", "SpeedProfile", "ResetCause", "StatusFlag", "DrumStatus", "DrumLimits", "SettleBand", "ForceLoopConfig",
    "SetpointRange",
    "MAX_SPEED_MM_S", "MAX_FORCE_G", "PROTOCOL_LIMITS", "CONTACT_STIFFNESS_MAX_G_PER_MM",
    "DRUM_DIAMETER_MM", "DRUM_STEPS_PER_REV", "DRUM_MICROSTEPS", "DRUM_CIRCUMFERENCE_MM", "DRUM_SPEED_TOLERANCE",
    "DRUM_MARKS_PER_REV", "DRUM_SLIP_TOLERANCE",
    "STATE_TEXT", "FAULT_WORDS", "ACTUATOR_DIRECTION_CAUSES", "CRUSH_FAULTS", "CRUSH_NOTE",
    "FaultWords", "describe_state", "describe_faults", "fault_advice",
    "HAND_PRESSES", "HAND_PRESS_AGREE", "HAND_PRESS_STEP", "hand_press_verdict",
    "PRESSING_G", "HOME_TOLERANCE_MM", "actuator_words", "status_line",
    "DrumError", "DrumTimeout", "DrumWaitAborted", "DrumFault", "DrumReset", "SetpointRangeError", "Clock",
]

#: the stiffest contact (sensor pad + mount + plate, g per mm of actuator travel) a rig config accepts: the rig as
#: built's mount (docs/hardware/wiring.md, "Sensor mount"). A precondition, not a measurement: the drum's runout
#: (0.02 mm) against it is 100 g, what 1.1 x FORCE_LIMIT leaves above the driver's stall (1,550 g), and the contact
#: probe's speed is derived from it (the header's RIGCTL_PROBE_BLIND_G / this: rigctl.devices.wire.PROBE_TRAVEL_UM).
#: Plates stiffer than this are refused by the rig config and the fault injector (issue 75: a 55,430 g/mm plate
#: swapped in reached 2,025 g with the stall on, the runout alone adding ~1,100 g)
CONTACT_STIFFNESS_MAX_G_PER_MM = 5000.0


# ----------------------------------------------------------------------------------------------------------------
# states, faults, profiles (spec tables 2.4, 2.5; SPEED_PROFILE values)
# ----------------------------------------------------------------------------------------------------------------
class DrumState(enum.IntEnum):
    """Controller states (spec table 2.4)."""

    IDLE = 0
    HOMING = 1
    SEEKING_FORCE = 2
    FORCE_SETTLED = 3
    RUNNING = 4
    FAULT = 5
    NOT_HOMED = 6


class Fault(enum.IntFlag):
    """Latched fault bits (spec table 2.5)."""

    FORCE_LIMIT = 1 << 0
    WATCHDOG = 1 << 1
    LOADCELL_TIMEOUT = 1 << 2
    ACTUATOR_TRAVEL = 1 << 3
    ESTOP = 1 << 4
    LOADCELL_REVERSED = 1 << 5
    HOME_NOT_FOUND = 1 << 6
    POSITION_LIMIT = 1 << 7
    HX711_RATE = 1 << 8
    ACTUATOR_DIRECTION = 1 << 9
    DRUM_SLIP = 1 << 10
    CONTACT_STIFFNESS = 1 << 11
    HX711_STUCK = 1 << 12
    HX711_LINE = 1 << 13
    HX711_CADENCE = 1 << 14
    CONTACT_LOST = 1 << 15
    RESET = 1 << 16  # FAULT_BITS_HI bit 0 (firmware 1.5)
    LOADCELL_SCALE = 1 << 17  # FAULT_BITS_HI bit 1 (firmware 1.6)
    LOADCELL_ZERO = 1 << 18  # FAULT_BITS_HI bit 2 (firmware 1.7)
    CONTACT_MISSING = 1 << 19  # FAULT_BITS_HI bit 3 (firmware 1.9)


#: the reading's scale check (docs/wire-protocol.md 2.12): the probe's stiffness over the one stored with the
#: calibration must lie within 100 / (100 + SCALE_CHECK_PCT) .. (100 + SCALE_CHECK_PCT) / 100, else LOADCELL_SCALE
SCALE_CHECK_PCT = 15


class ResetCause(enum.IntFlag):
    """Bits of the RESET_CAUSE input register (spec table 2.7: the MCU's MCUSR at boot)."""

    POWER_ON = 1 << 0
    EXTERNAL = 1 << 1
    BROWN_OUT = 1 << 2
    WATCHDOG = 1 << 3


class StatusFlag(enum.IntFlag):
    """Bits of the STATUS_FLAGS input register (spec table 2.8)."""

    CALIBRATION_DEFAULTS = 1 << 0
    HOMED = 1 << 1
    DRIVERS_ENABLED = 1 << 2
    ESTOP_OPEN = 1 << 3
    HOME_SWITCH = 1 << 4
    TARED = 1 << 5


class SpeedProfile(enum.IntEnum):
    """The drum's speed profiles (values of the SPEED_PROFILE holding register)."""

    CONSTANT = 0
    RAMP = 1


#: what each state means, for the operator (spec table 2.4)
STATE_TEXT: dict[DrumState, str] = {
    DrumState.IDLE: "Idle - drum at rest, actuator released",
    DrumState.HOMING: "Homing - actuator moving to its home switch",
    DrumState.SEEKING_FORCE: "Seeking force - pressing towards the setpoint",
    DrumState.FORCE_SETTLED: "Force settled - on target, drum at rest",
    DrumState.RUNNING: "Running - drum turning, force loop holding",
    DrumState.FAULT: "FAULT - drum stopped, motion refused until CLEAR_FAULT",
    DrumState.NOT_HOMED: "Not homed - reset, e-stopped or homing failed: HOME before pressing",
}
class FaultWords(NamedTuple):
    """A fault bit in words: ``label`` (a few words, for a status line), ``meaning`` (spec table 2.5's, for an error
    message), ``advice`` (what happened and what to do, for the operator), ``causes`` (the parts the advice sends
    the operator to, in the order its words name them: most likely first,
    :func:`rigctl.core.parts.less_likely_first`; issue 75 item 4)."""

    label: str
    meaning: str
    advice: str
    causes: tuple[Part, ...] = ()


#: the hand press that tells a reversed load cell from a right one, in one place (issue 75 item 4): repeated, and a
#: wire is changed only on presses that agree. One press on a noisy DOUT line read -528, -1,745 and -824 g for a 200 g
#: mass on a good cell, and the advice had A+/A- swapped (the advice walker's fresh seed 736172): HAND_PRESSES
#: presses of the same weight, each within HAND_PRESS_AGREE of it and all one sign (:func:`hand_press_verdict`)
HAND_PRESSES = 3
#: how far each hand press may read from the weight pressed and still count, as a fraction of it
HAND_PRESS_AGREE = 0.5
#: the hand press in words, for every advice that asks for it (FAULT_WORDS, the rig's latch causes, the doctor)
HAND_PRESS_STEP = (
    f"press the load cell by hand {HAND_PRESSES} times with the same weight (a 200 g mass) and read FORCE_G after "
    f"each: only presses that all read about that weight (within half of it) and all the same way tell anything; "
    f"presses that disagree or are far from it are a noisy reading, not a wiring: change no wire, check the HX711's "
    f"DOUT and SCK wires; presses that agree with each other but read far from the weight are the reading's scale: "
    f"change no wire, check the excitation leads' joints (E+, E-) and recalibrate with the mass")


def hand_press_verdict(changes_g: "list[float] | tuple[float, ...]", weight_g: float) -> str:
    """What :data:`HAND_PRESSES` hand presses of ``weight_g`` read as changes of FORCE_G (g) say: ``"fall"`` (every
    one fell by the weight within :data:`HAND_PRESS_AGREE` of it: the cell reads reversed), ``"rise"`` (every one rose
    so: the cell is right), ``"unclear"`` (fewer presses, or presses that disagree or are far from the weight: a noisy
    reading, no wire to change)."""
    lo, hi = (1.0 - HAND_PRESS_AGREE) * weight_g, (1.0 + HAND_PRESS_AGREE) * weight_g
    if len(changes_g) < HAND_PRESSES:
        return "unclear"
    if all(lo <= -c <= hi for c in changes_g):
        return "fall"
    if all(lo <= c <= hi for c in changes_g):
        return "rise"
    return "unclear"


#: the two wirings behind ACTUATOR_DIRECTION and how to tell them apart before changing either (issue 55): a
#: reversed load cell reads the force falling as the actuator presses, so after a reset under load, backing off (or
#: HOME) reads as a rise; swapping the motor's coils then would drive HOME into the sensor
ACTUATOR_DIRECTION_CAUSES = (
    "Tell the causes apart before changing any wire, the most likely first. With nothing touching the sensor, read "
    "FORCE_G (the status line): far from 0 g, the load cell's zero moved since its calibration (a mount changed, a "
    "cable pulled): recalibrate it (rigctl calibrate loadcell) and change no wire. Else " + HAND_PRESS_STEP + " (rigctl "
    "doctor --check actuator-direction does it on a simulated rig). If they all fall, the cell reads "
    "reversed (A+/A- swapped at the HX711): swap A+ and A- and leave the motor alone (swapping its coils would drive "
    "HOME into the sensor). If they all rise, the cell is right, and that alone does not make the motor wrong: "
    "acknowledge and watch the lead screw while the start's HOME creeps (it proves its way and stops where it is "
    "wrong). If it moves the right way, change no wire: check the home switch and its wire and the HX711's wires "
    "again (a reading that jumps by itself). Only if you see it close the gap to the sensor where it should open it, "
    "power off and swap one coil pair of the actuator motor (1A/1B). Then HOME")
#: the parts ACTUATOR_DIRECTION's advice names, in its order (:data:`ACTUATOR_DIRECTION_CAUSES`)
_ACTUATOR_DIRECTION_PARTS = (Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.HOME_SWITCH,
                             Part.ACTUATOR_COILS)

#: the crush class (issue 55): the faults that mean the sensor was, or could have been, pressed past what the rig
#: allows (too much force, a force path that cannot be believed: the actuator's direction, a reversed cell, a contact
#: stiffer than the loop holds). Opening the rig never clears one: the operator acknowledges it with a reason once the
#: cause is fixed (:func:`fault_advice` says so). A fault bit added for a lying reading belongs here too
CRUSH_FAULTS = (Fault.FORCE_LIMIT | Fault.LOADCELL_REVERSED | Fault.ACTUATOR_DIRECTION | Fault.CONTACT_STIFFNESS
                | Fault.POSITION_LIMIT | Fault.HX711_STUCK | Fault.HX711_LINE | Fault.HX711_CADENCE | Fault.CONTACT_LOST
                | Fault.LOADCELL_SCALE | Fault.LOADCELL_ZERO | Fault.CONTACT_MISSING)

#: what :func:`fault_advice` adds to a crush-class fault
CRUSH_NOTE = ("a crush-class fault: opening the rig never clears it; acknowledge it with a reason once the cause is "
              "fixed")

#: every fault bit in words (spec table 2.5); a new bit gets its entry here
FAULT_WORDS: dict[Fault, FaultWords] = {
    Fault.FORCE_LIMIT: FaultWords(
        "force limit exceeded", "measured force exceeded FORCE_LIMIT_G",
        "the measured force went above the controller's FORCE_LIMIT; the actuator backed off at once. In the order a "
        "lab meets them: check the plate and the sensor (a stiffer plate or mount than before), FORCE_G with nothing "
        "on the sensor (far from 0 g: the load cell's zero moved, recalibrate), the actuator's coupling (a set screw "
        "that slips lets the screw jump forward when the motor holds) and the HX711's DOUT and SCK wires (a reading "
        "that jumps by itself), then lower the force setpoint; if it latches again, check that the lead screw turns "
        "freely (a motor losing steps makes the probe take the contact for softer than it is).",
        (Part.PLATE, Part.LOADCELL_ZERO, Part.COUPLING, Part.HX711_WIRES, Part.SETPOINT, Part.LEAD_SCREW)),
    Fault.WATCHDOG: FaultWords(
        "host watchdog expired", "host went silent for longer than WATCHDOG_MS",
        "the controller heard nothing from the host for WATCHDOG_MS while the drum turned or the force loop held, "
        "and stopped (a crashed or killed program, a pulled USB cable).",
        (Part.HOST_LINK,)),
    Fault.LOADCELL_TIMEOUT: FaultWords(
        "load cell not responding", "the load cell gave no reading for 200 ms",
        "the load cell amplifier (HX711) gave no reading for 200 ms. Check its DOUT and SCK wires and its supply "
        "(VCC, GND), then the board itself.",
        (Part.HX711_WIRES, Part.HX711_CHIP)),
    Fault.ACTUATOR_TRAVEL: FaultWords(
        "actuator end of travel before reaching force",
        "actuator reached its end of travel without reaching the force setpoint",
        "the actuator reached its end of travel without reaching the force setpoint. In the order a lab meets them: "
        "no plate, or the sensor is too far away (mount a plate, check the gap); the actuator's coupling slipping (its "
        "steps count on, the screw stays: check its set screws); the load cell reading no load (an open bridge or "
        "excitation wire: check A+, A-, E+, E- at the HX711); the actuator turning the wrong way (a coil pair swapped: "
        "it drives into its rear stop while its steps count on; the start's HOME proves its way); the cell itself "
        "broken.",
        (Part.PLATE, Part.COUPLING, Part.LOADCELL_WIRING, Part.ACTUATOR_COILS, Part.LOADCELL)),
    Fault.ESTOP: FaultWords(
        "e-stop", "the e-stop input opened (pressed, or its wire is broken): drivers disabled",
        "the e-stop was pressed (or its normally-closed wire is broken): the stepper drivers were disabled at once "
        "and the drum and actuator stopped where they were. Release it, CLEAR_FAULT, then HOME (the position was "
        "lost).",
        (Part.E_STOP,)),
    Fault.LOADCELL_REVERSED: FaultWords(
        "load cell reversed",
        "the force read negative while pressing: the load cell is mounted or wired the other way round, or its "
        "scale has the wrong sign",
        "the force went below -2 x FORCE_TOLERANCE_G while pressing. Tell the causes apart before changing any "
        "wire, the most likely first. With nothing touching the sensor, read FORCE_G (the status line): far from 0 g, "
        "the load cell's zero moved since its calibration (a tare taken under load, a mount changed): recalibrate it "
        "(rigctl calibrate loadcell) and change no wire. Else " + HAND_PRESS_STEP + ". If they all fall, the cell is mounted "
        "or wired the other way round: swap A+ and A- at the HX711 (or turn the cell over), then recalibrate. If "
        "they all rise, the cell and its wires are right and its scale is not (a wrong calibration mass): change no "
        "wire, recalibrate it (rigctl calibrate loadcell).",
        (Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.CALIBRATION)),
    Fault.HOME_NOT_FOUND: FaultWords(
        "home switch not found",
        "HOME did not reach the home switch within its travel limit or timeout (a broken switch or wire, a stalled "
        "actuator)",
        "HOME gave up after 25 mm or 10 s without the home switch closing: check the home switch and its wire, then "
        "that the actuator moves (its lead screw turns freely, its driver is enabled), then CLEAR_FAULT and HOME.",
        (Part.HOME_SWITCH, Part.LEAD_SCREW, Part.DRIVER)),
    Fault.HX711_RATE: FaultWords(
        "load-cell rate mismatch",
        "the load cell amplifier's measured rate is not the one the force loop is set for",
        "the HX711 converts at another rate than HX711_RATE_SPS (most boards ship at 10 SPS, RATE pin low; the "
        "default gains are for 80 SPS). Set the board's RATE pin high (80 SPS), or accept 10 SPS with its slower "
        "gains (DrumClient.set_hx711_rate(10), or a force_loop block in the rig config), then CLEAR_FAULT. A 10 SPS "
        "board latches this at every power-up: seen again with no power cycle of yours, the controller reset by "
        "itself (check its power and reset line: a brown-out also loses what it was writing to its EEPROM).",
        (Part.HX711_RATE_PIN, Part.RIG_CONFIG, Part.CONTROLLER_POWER)),
    Fault.ACTUATOR_DIRECTION: FaultWords(
        "actuator turns the wrong way or load cell reversed",
        "the actuator moved the wrong way or the load cell reads reversed: HOME's switch did not open when leaving "
        "home, or the load on the cell (|raw - zero|, sign-free) grew while it moved home or backed off",
        "the load cell's reading rose while the firmware drove the actuator home or backed it off (or HOME's switch "
        "did not open): it was stopped where it stood. " + ACTUATOR_DIRECTION_CAUSES + "; rigctl doctor checks it.",
        _ACTUATOR_DIRECTION_PARTS),
    Fault.DRUM_SLIP: FaultWords(
        "drum slipped or stalled",
        "the drum turned less than its steps say: more steps than one speed-mark interval allows passed without a "
        "mark (a stall, a slipping coupling, a stepper losing steps)",
        "the drum's speed marks came late or stopped while the stepper was stepped: the drum slips (a loose "
        "coupling or grub screw, a belt, too little motor current for the load) or stalls (something blocks it). "
        "Fix the drive and free the drum, then CLEAR_FAULT; the trial in progress was not recorded.",
        (Part.DRUM_DRIVE, Part.DRUM_BLOCKED)),
    Fault.CONTACT_STIFFNESS: FaultWords(
        "contact too stiff",
        "the contact stiffness the first press measured is more than the force loop holds with its gains",
        "the first press since the controller's reset measured the contact's stiffness (CONTACT_STIFFNESS_G_PER_MM) "
        "above what the force loop holds with its gains and the HX711's delay (STIFFNESS_MAX_G_PER_MM): it backed "
        "off, and PRESS and RUN are refused. In the order a lab meets them: a plate, sensor mount or pad stiffer than "
        "the loop holds (use a softer one); on the calibrated plate, the reading's scale too high (a loose excitation "
        "lead: check E+, E-; a wrong calibration mass: recalibrate), which the probe reads as a stiffer contact; else "
        "store slower gains (the rig config's force_loop block: the limit grows as Kp falls). Then CLEAR_FAULT.",
        (Part.PLATE, Part.LOADCELL_WIRING, Part.CALIBRATION, Part.RIG_CONFIG)),
    Fault.POSITION_LIMIT: FaultWords(
        "pressed past the contact's limit",
        "the actuator went further past the probed contact than FORCE_LIMIT_G allows at the measured stiffness, "
        "whatever the force read",
        "the actuator's position says the contact is pressed to the force limit (the travel past the contact the "
        "press probed, times its stiffness) while the load cell read less. In the order a lab meets them: the "
        "contact changed (a plate or mount swapped since the probe); the reading is lying (the HX711's DOUT or SCK "
        "wire loose, a wrong calibration mass); the actuator does not go where its steps say (a coil pair swapped: "
        "a reversed motor); a frozen HX711. It stopped where it stood (a back-off's direction is unproven; the "
        "start's HOME creeps and proves it). Check them in that order (rigctl doctor), then CLEAR_FAULT.",
        (Part.PLATE, Part.HX711_WIRES, Part.CALIBRATION, Part.ACTUATOR_COILS, Part.HX711_CHIP)),
    Fault.HX711_STUCK: FaultWords(
        "load-cell reading frozen",
        "the HX711 returned the same raw value too many times in a row (a real one at gain 128 never does: ~20-40 "
        "counts of noise)",
        "the HX711 gave the same 24 bits several readings in a row, which a working amplifier at gain 128 never "
        "does (its noise is 20-40 counts rms): the reading is frozen (a chip hung, a stuck data line). It backed "
        "off. Power-cycle the rig (a hung chip starts again), then check the HX711's DOUT and SCK wires, then "
        "CLEAR_FAULT.",
        (Part.HX711_CHIP, Part.HX711_WIRES)),
    Fault.HX711_LINE: FaultWords(
        "load-cell line fault",
        "the HX711 returned a saturation code (0x7FFFFF, 0x800000) or an all-zero / all-one word twice (a broken "
        "SCK or DOUT wire)",
        "the HX711 returned a code no working load cell gives: a clock or data line is broken (0x000000 or 0xFFFFFF "
        "read twice) or its input saturated (0x7FFFFF or 0x800000: a broken bridge wire, an input beyond range). It "
        "backed off. Check the HX711's SCK and DOUT wires, then the load cell's (E+, E-, A+, A-), then the cell "
        "itself; then CLEAR_FAULT.",
        (Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.LOADCELL)),
    Fault.HX711_CADENCE: FaultWords(
        "load-cell readings too fast",
        "the HX711's DOUT said 'ready' sooner than its measured rate allows (a clock wire that never clocks holds "
        "DOUT low)",
        "the HX711's data-ready came faster than its measured rate: its SCK wire is broken (DOUT stays low and "
        "every read returns the same bits) or DOUT is shorted low. It backed off. Check the HX711's SCK and DOUT "
        "wires, then CLEAR_FAULT.",
        (Part.HX711_WIRES,)),
    Fault.CONTACT_LOST: FaultWords(
        "contact lost while the force held",
        "the force loop held its force while the actuator's position left the probed contact (a reading that does "
        "not follow the contact)",
        "the load cell kept reading the force while the actuator moved back off the contact the press probed: the "
        "reading is not the contact's. In the order a lab meets them: something resting on the sensor or the "
        "actuator (the load cell loaded by something else); the HX711's DOUT or SCK wire loose; a frozen HX711. The "
        "trial is not recorded; it stopped where it stood (the channels disagree: a back-off's direction is "
        "unproven; the start's HOME creeps and proves it). Check them in that order, then CLEAR_FAULT.",
        (Part.LOAD_ON_SENSOR, Part.HX711_WIRES, Part.HX711_CHIP)),
    Fault.RESET: FaultWords(
        "controller reset",
        "the controller reset while its actuator was away from home (its warm-boot record), or powered up with the "
        "load cell loaded against its stored zero, or holds such a latch from before a power cycle",
        "the drum controller was reset (a brown-out, its reset line, a port opening, its own watchdog) while the "
        "actuator may have been pressing: it latched this itself, so every program that opens the rig finds it, and "
        "it moves nothing. Check the controller's power and reset line and that nothing presses the sensor, then "
        "CLEAR_FAULT; the start after it HOMEs from an unknown position (creeping, its way proven).",
        (Part.CONTROLLER_POWER,)),
    Fault.LOADCELL_SCALE: FaultWords(
        "load-cell scale disagrees with the calibration",
        "the contact's stiffness the press's probe measured (the reading's rise over the actuator's step count) "
        "disagrees with the one stored with the calibration by more than SCALE_CHECK_PCT: the plate or mount changed, "
        "the actuator lost steps, the reading did not follow the press, or the reading's scale is wrong",
        "the probe measured the contact's stiffness (the reading's rise over the steps the actuator was sent) more than "
        "15 % off the one stored when the scale was verified, and backed off before pressing. In the order a lab meets "
        "them: a plate, sensor or mount changed since the calibration (a contact of another stiffness); the actuator's "
        "coupling slipping (check its set screws: a slipping coupling moves less than it counts); the reading not "
        "following the press (watch FORCE_G while pressing the cell by hand: a value that jumps or never changes is "
        "the HX711's DOUT or SCK wire); the reading's scale (a loose excitation lead: check E+, E-, A+, A-; a wrong "
        "calibration mass), which makes the reading and the force limit off by as much; the lead screw binding or the "
        "motor losing steps (check that it turns freely); the cell itself (overloaded, creeping, of another range). "
        "Fix what you found, then recalibrate with the reference mass (rigctl calibrate loadcell or the GUI's "
        "calibration tab, which stores the contact's stiffness again). Then CLEAR_FAULT.",
        (Part.PLATE, Part.COUPLING, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.CALIBRATION, Part.LEAD_SCREW,
         Part.LOADCELL)),
    Fault.LOADCELL_ZERO: FaultWords(
        "load-cell reading off its zero with nothing pressing",
        "a press from home at rest found the settled reading off the tare by more than PRESS_DIR_G (8 g), or the "
        "probe's steps raised less than a quarter of the load the contact's stored stiffness says they press: the "
        "reading moved with no step",
        "the load cell read a force with the actuator at home and nothing moving (or the press's probe found no load "
        "rising where the reading showed the contact): the reading is not the contact's, and a press on it would "
        "hold the wrong force or none. It latched before pressing (the actuator stays where it is, or backs off from "
        "the probe). First look for something resting on the sensor or the actuator (a hand, a tool, debris between "
        "drum and sensor): remove it. Else, in the order a lab meets them: the plate or mount changed since the "
        "calibration (a softer contact raises less load per step than the stored stiffness: recalibrate, which "
        "stores the new contact); the cell's zero moved (the cell overloaded or knocked, its mount's screws): check "
        "its mount; its wiring (the HX711's DOUT and SCK wires, the cell's "
        "cable and its E+, E-, A+, A- joints). Then CLEAR_FAULT: the start HOMEs (its way proven) and tares the cell "
        "again at home; if this latches again with nothing on the sensor, the cell itself is failing: replace it and "
        "recalibrate.",
        (Part.LOAD_ON_SENSOR, Part.PLATE, Part.LOADCELL_ZERO, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.LOADCELL)),
    Fault.CONTACT_MISSING: FaultWords(
        "no force where the contact was",
        "a press's approach went PROBE_LOCATED_MARGIN_UM (plus the probe's contact load's travel) past where the last "
        "probe located the contact and the reading never showed it: a press commanded with no force rise",
        "the press went past where its last probe found the contact and the load cell read no force: either the "
        "reading is dead or the actuator did not get there. It stopped where it stands (its steps did not do what "
        "they say, so a back-off could press as well). In the order a lab meets them: the plate or sample removed "
        "or changed since the last press (mount it: the start's HOME forgets the old contact); the actuator's "
        "coupling slipping (check its set screws); the HX711's DOUT and SCK wires; the load cell's wires reading no "
        "load (an open bridge or excitation lead: check A+, A-, E+, E- at the HX711, and watch FORCE_G rise while you "
        "press the cell by hand); the lead screw binding or the motor losing steps (check that it turns freely); a "
        "coil pair swapped (the motor turns the wrong way); a frozen HX711; the cell itself broken. Then CLEAR_FAULT: "
        "the start HOMEs from where it stands, creeping, and proves its way.",
        (Part.PLATE, Part.COUPLING, Part.HX711_WIRES, Part.LOADCELL_WIRING, Part.LEAD_SCREW, Part.ACTUATOR_COILS,
         Part.HX711_CHIP, Part.LOADCELL)),
}


def describe_state(state: int) -> str:
    """The state in words (:data:`STATE_TEXT`); an unknown code as ``"state <n>"``."""
    try:
        s = DrumState(int(state))
    except ValueError:
        return f"state {int(state)}"
    return STATE_TEXT.get(s, s.name)


def _bits(faults: int) -> list[Fault]:
    return [bit for bit in Fault if int(faults) & int(bit)]


def describe_faults(faults: int) -> str:
    """The set fault bits by name with their words, e.g. ``"FORCE_LIMIT (measured force exceeded FORCE_LIMIT_G)"``;
    ``"none"`` when clear. Unknown bits are named by number."""
    parts = [f"{bit.name} ({FAULT_WORDS[bit].meaning})" if bit in FAULT_WORDS else str(bit.name)
             for bit in _bits(faults)]
    known = sum(int(b) for b in Fault)
    if int(faults) & ~known:
        parts.append(f"unknown fault bits 0x{int(faults) & ~known:x}")
    return ", ".join(parts) if parts else "none"


def fault_advice(faults: int) -> str:
    """Each latched fault bit with its meaning and what to do, one sentence each (``""`` when clear); a crush-class
    bit (:data:`CRUSH_FAULTS`) is named as such (:data:`CRUSH_NOTE`)."""
    return " ".join(f"{FAULT_WORDS[bit].label.capitalize()}: {FAULT_WORDS[bit].advice}"
                    + (f" ({CRUSH_NOTE}.)" if bit in CRUSH_FAULTS else "") for bit in _bits(faults)
                    if bit in FAULT_WORDS)


#: a tared load-cell reading at or above this is force on the sensor (the actuator presses it), g: above the HX711's
#: noise and a plate's drag at rest (FORCE_TOLERANCE_G's default is 15 g)
PRESSING_G = 20.0
#: the sensor counts as released (the word "released" on every face) only below this force read, g
RELEASED_G = 5.0
#: the actuator is back at home (the sensor released) within this much of it, mm (as ``wait_released``'s default)
HOME_TOLERANCE_MM = 0.05

#: the states in which the controller itself holds force on the sensor (the force loop runs)
_ENGAGED_STATES = frozenset({DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING})


def actuator_words(st: "DrumStatus") -> str:
    """Where the actuator is and what it does, in words, from one status (not its state's name): the truth after a
    stop, whatever the state says.

    - drivers off (an e-stop, a stop category 0: they stop where they stand) away from home or under load:
      ``"drivers off, actuator where it stopped, pressing 508 g"`` (or ``"..., 2.4 mm out, sensor free"``);
    - drivers on, on the way home: ``"actuator backing off, pressing 120 g"`` (or ``"actuator backing off"``);
    - home and the load cell below :data:`RELEASED_G`: ``"actuator released"`` (never otherwise);
    - home with a few grams read: ``"actuator home, load cell reads 12 g"``.

    Force ``st.force_g`` counts as pressing from :data:`PRESSING_G`; home is within :data:`HOME_TOLERANCE_MM`."""
    pressing = float(st.force_g) >= PRESSING_G
    away = float(st.actuator_mm) > HOME_TOLERANCE_MM and not st.home_switch
    if not (pressing or away):
        if abs(float(st.force_g)) < RELEASED_G:
            return "actuator released"
        return f"actuator home, load cell reads {float(st.force_g):.0f} g"
    load = f"pressing {float(st.force_g):.0f} g" if pressing else "sensor free"
    if not st.drivers_enabled:
        where = "actuator where it stopped" + ("" if pressing else f", {float(st.actuator_mm):.1f} mm out")
        return f"drivers off, {where}, {load}"
    return "actuator backing off" + (f", {load}" if pressing else "")


def status_line(st: "DrumStatus", latch: str | None = None, *, short: bool = False) -> str:
    """The controller's status in one line for the operator, every face's words (the GUI's state line and top strip,
    ``rigctl serve``'s ``/status``): its state, the drum, the actuator's truth (:func:`actuator_words`) and, with
    ``latch`` (the host's latch label, e.g. ``"e-stop"``), what holds the rig.

    E.g. ``"FAULT (e-stop) - drum stopped, drivers off, actuator where it stopped, pressing 508 g"``, ``"Running -
    drum 80 mm/s, force loop holding 498 g"``, ``"Idle - drum at rest, actuator released"``. ``short``: the state and
    the numbers only, for a narrow strip (``"FAULT, pressing 508 g"``, ``"Running 80 mm/s, 498 g"``; no latch label)."""
    try:
        state: DrumState | None = DrumState(int(st.state))
    except ValueError:
        state = None
    name = describe_state(int(st.state)).split(" - ")[0]
    engaged = int(st.state) in _ENGAGED_STATES
    if short:  # (the top strip's room: "Drum: Seeking force 120 mm/s, 1000 g")
        if engaged:
            return f"{name} {float(st.speed_mm_s):.0f} mm/s, {float(st.force_g):.0f} g"
        if float(st.force_g) >= PRESSING_G:
            return f"{name}, pressing {float(st.force_g):.0f} g"
        return name
    if latch and state == DrumState.FAULT:
        name = f"{name} ({latch})"
    if engaged:
        if state == DrumState.RUNNING:
            drum = f"drum {float(st.speed_mm_s):.0f} mm/s"
        else:
            drum = "drum at rest" if abs(float(st.speed_mm_s)) < 0.5 else f"drum {float(st.speed_mm_s):.0f} mm/s"
        verb = "holding" if state != DrumState.SEEKING_FORCE else "pressing towards the setpoint at"
        return f"{name} - {drum}, force loop {verb} {float(st.force_g):.0f} g"
    if state == DrumState.HOMING:
        return f"{name} - actuator moving to its home switch" + (
            f", pressing {float(st.force_g):.0f} g" if float(st.force_g) >= PRESSING_G else "")
    moving = abs(float(st.speed_mm_s)) >= 0.5
    drum = f"drum slowing ({float(st.speed_mm_s):.0f} mm/s)" if moving else (
        "drum stopped" if state in (DrumState.FAULT, DrumState.NOT_HOMED) else "drum at rest")
    text = f"{name} - {drum}, {actuator_words(st)}"
    if state == DrumState.NOT_HOMED:
        text += "; HOME before pressing"
    return text


# ----------------------------------------------------------------------------------------------------------------
# status
# ----------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DrumStatus:
    """One snapshot of the controller's state, in physical units (spec table 2.2).

    Fields added later (new input registers) come with a default, so that any backend building a status keeps
    working (see the module docstring).
    """

    force_g: float  #: measured load-cell force, g (tared)
    speed_mm_s: float  #: actual drum surface speed, mm/s
    speed_target_mm_s: float  #: speed the profile asks for now, mm/s
    angle_deg: float  #: drum angle since the index mark, degrees 0-359.99
    revolutions: int  #: completed revolutions, wraps at 65536
    actuator_mm: float  #: actuator travel from home, mm (positive towards the sensor)
    state: DrumState  #: the controller state
    faults: Fault  #: latched fault bits (cleared by CLEAR_FAULT)
    firmware: tuple[int, int]  #: (major, minor)
    heartbeat: int  #: +1 every 10 ms, wraps at 65536
    loadcell_raw: int  #: raw HX711 counts (signed 24-bit)
    force_setpoint_active_g: float  #: setpoint the force loop holds now, g (0 when released)
    hx711_rate_sps: float = 0.0  #: the HX711's rate measured at boot, samples/s (0 until measured; spec 2.9)
    index_source: str = "steps"  #: what marks the drum index now: "sensor" (the index sensor) or "steps" (fallback)
    index_period_s: float = 0.0  #: one drum revolution by the index sensor, s (0 before two sensor edges)
    index_steps: int = 0  #: drum microsteps sent in that revolution (steps_per_rev x microsteps if the driver agrees)
    index_count: int = 0  #: index-sensor edges since power-up, wraps at 65536
    #: time between the last two speed marks (1 / DRUM_MARKS_PER_REV of a revolution), s (0 before two marks)
    mark_period_s: float = 0.0
    mark_steps: int = 0  #: drum microsteps sent between the last two speed marks (0 before two marks)
    mark_count: int = 0  #: speed marks since power-up, wraps at 65536
    reset_cause: ResetCause = ResetCause(0)  #: what caused the controller's last reset (spec table 2.7)
    boot_count: int = 0  #: the controller's boots so far (EEPROM), wraps at 65536: a change = it was reset
    flags: StatusFlag = StatusFlag(0)  #: status bits (spec table 2.8)
    #: the contact's stiffness the first press since the reset measured, g/mm (0 = not yet; spec 2.10)
    contact_stiffness_g_per_mm: int = 0
    #: the stiffest contact the force loop holds with its gains now, g/mm (spec 2.10; 0 from older firmware)
    stiffness_max_g_per_mm: int = 0
    #: the firmware's build id: 12 hex digits of the sources' SHA-256 it was built from (spec 2.2, BUILD_ID_0 .. _2);
    #: None for a build without one (a plain make, the Arduino IDE)
    build_id: str | None = None

    @property
    def homed(self) -> bool:
        """HOME has succeeded since the last reset, e-stop or failed HOME."""
        return StatusFlag.HOMED in self.flags

    @property
    def calibration_defaults(self) -> bool:
        """The controller's EEPROM calibration was missing or failed its checksum at boot: defaults in use."""
        return StatusFlag.CALIBRATION_DEFAULTS in self.flags

    @property
    def estop_open(self) -> bool:
        """The e-stop input reads open now."""
        return StatusFlag.ESTOP_OPEN in self.flags

    @property
    def home_switch(self) -> bool:
        """The actuator's home switch reads closed now: the actuator is at (or behind) home, whatever its step
        count says."""
        return StatusFlag.HOME_SWITCH in self.flags

    @property
    def drivers_enabled(self) -> bool:
        """The stepper drivers are enabled (EN active) now."""
        return StatusFlag.DRIVERS_ENABLED in self.flags

    def index_speed_mm_s(self, diameter_mm: float) -> float | None:
        """Drum surface speed measured by the index sensor, mm/s: ``pi * diameter_mm / index_period_s`` (the real
        drum's speed, whatever the step count says); None before two sensor edges."""
        if self.index_period_s <= 0:
            return None
        return math.pi * float(diameter_mm) / self.index_period_s

    @property
    def faulted(self) -> bool:
        """The controller is in FAULT (a fault latched; drum stopped; the actuator backs off, or stays where it stopped
        when the drivers are off: :func:`status_line`)."""
        return self.state == DrumState.FAULT

    def describe(self) -> str:
        """The state in words with the actuator's truth (:func:`status_line`), and the latched faults if any (one
        line)."""
        text = status_line(self)
        return f"{text}; faults: {describe_faults(self.faults)}" if int(self.faults) else text


# ----------------------------------------------------------------------------------------------------------------
# limits and setpoints
# ----------------------------------------------------------------------------------------------------------------
#: the rig's protocol range: every speed / force setpoint (protocol, manual, script) is checked against it before
#: anything moves, mm/s and g. The controller's own limits (SPEED_LIMIT, FORCE_LIMIT registers, :class:`DrumLimits`)
#: may be lower.
MAX_SPEED_MM_S = 150.0
MAX_FORCE_G = 1500.0


class SetpointRangeError(ValueError):
    """A setpoint outside its allowed range was refused before anything was sent to the rig.

    Attributes
    ----------
    name : str     what was set (e.g. ``"speed"``)
    value : float  the refused value, in ``unit``
    unit : str     e.g. ``"mm/s"``, ``"g"``
    low, high : float  the allowed range, in ``unit``
    reason : str   which limit binds (e.g. ``"rig limit"``, ``"SPEED_LIMIT_0P1MMS"``), may be empty
    """

    def __init__(self, name: str, value: float, unit: str, low: float, high: float, reason: str = "") -> None:
        self.name, self.value, self.unit, self.low, self.high, self.reason = name, value, unit, low, high, reason
        extra = f" ({reason})" if reason else ""
        super().__init__(f"{name} {value:g} {unit} is outside the allowed range {low:g}-{high:g} {unit}{extra}")


@dataclass(frozen=True)
class SetpointRange:
    """The values a setpoint may take, with its unit and the limit that sets the top.

    ``low < value <= high`` when ``low_exclusive`` (a trial's speed and force: 0 moves nothing), else
    ``low <= value <= high``. ``source`` names the binding upper limit ("rig's protocol range" or "controller's
    hard limit").
    """

    name: str
    unit: str
    low: float
    high: float
    source: str = ""
    low_exclusive: bool = True

    def contains(self, value: float) -> bool:
        """True when ``value`` may be sent (NaN never)."""
        v = float(value)
        if math.isnan(v):
            return False
        return (v > self.low if self.low_exclusive else v >= self.low) and v <= self.high

    def problem(self, value: float) -> str | None:
        """Why ``value`` is refused, one line (None when accepted)."""
        if self.contains(value):
            return None
        v = float(value)
        if not (v > self.low if self.low_exclusive else v >= self.low):
            return f"{self.name} {v:g} {self.unit}: must be {'above' if self.low_exclusive else 'at least'} " \
                   f"{self.low:g} {self.unit}"
        return f"{self.name} {v:g} {self.unit}: above the {self.source or 'limit'} of {self.high:g} {self.unit}"

    def check(self, value: float) -> float:
        """Return ``float(value)``; raise :class:`SetpointRangeError` when it is outside the range."""
        if not self.contains(value):
            raise SetpointRangeError(self.name, float(value), self.unit, self.low, self.high, self.source)
        return float(value)


@dataclass(frozen=True)
class DrumLimits:
    """The controller's hard limits (its SPEED_LIMIT and FORCE_LIMIT registers), mm/s and g.

    The accepted setpoint ranges are the lower of these and the rig's protocol range (:data:`MAX_SPEED_MM_S`,
    :data:`MAX_FORCE_G`): :meth:`speed_range`, :meth:`force_range`.
    """

    speed_mm_s: float
    force_g: float

    def speed_range(self) -> SetpointRange:
        """Accepted trial / manual speeds: above 0, at most the lower of both limits, mm/s."""
        return _range("speed", "mm/s", MAX_SPEED_MM_S, float(self.speed_mm_s))

    def force_range(self) -> SetpointRange:
        """Accepted force setpoints: above 0, at most the lower of both limits, g."""
        return _range("force", "g", MAX_FORCE_G, float(self.force_g))

    def check(self, *, speed_mm_s: float | None = None, force_g: float | None = None) -> None:
        """Raise :class:`SetpointRangeError` for the first of the given setpoints outside its range."""
        if speed_mm_s is not None:
            self.speed_range().check(speed_mm_s)
        if force_g is not None:
            self.force_range().check(force_g)

    def problems(self, *, speed_mm_s: float | None = None, force_g: float | None = None) -> list[str]:
        """Why the given setpoints are refused, one line each (empty when both are accepted)."""
        out = []
        if speed_mm_s is not None and (p := self.speed_range().problem(speed_mm_s)):
            out.append(p)
        if force_g is not None and (p := self.force_range().problem(force_g)):
            out.append(p)
        return out


def _range(name: str, unit: str, protocol_max: float, controller_max: float) -> SetpointRange:
    if controller_max < protocol_max:
        return SetpointRange(name, unit, 0.0, controller_max, "controller's hard limit")
    return SetpointRange(name, unit, 0.0, protocol_max, "rig's protocol range")


#: the rig's protocol range alone (a controller whose limits are at least as wide): what protocols are checked
#: against before a rig is open
PROTOCOL_LIMITS = DrumLimits(MAX_SPEED_MM_S, MAX_FORCE_G)


@dataclass(frozen=True)
class SettleBand:
    """When the force loop counts as on target: ``abs(force - setpoint) <= force_tolerance_g`` for
    ``settle_time_ms`` (the FORCE_TOLERANCE_G and SETTLE_TIME_MS registers)."""

    force_tolerance_g: float
    settle_time_ms: int


@dataclass(frozen=True)
class ForceLoopConfig:
    """The force loop's settings in physical units (spec 2.1 and 2.9; the registers' defaults and ranges:
    ``rigctl.devices.drum.default_force_loop``).

    Attributes
    ----------
    hx711_rate_sps : int
        The HX711 rate the loop accepts to run at (10 or 80); a measured rate 20 % away latches HX711_RATE.
    kp_80sps_mm_s_per_g, ki_80sps_mm_s_per_g_s : float
        PI gains at 80 SPS: actuator velocity (mm/s) per g of force error, and per g*s of its integral.
    kp_10sps_mm_s_per_g, ki_10sps_mm_s_per_g_s : float
        The same at 10 SPS.
    """

    hx711_rate_sps: int
    kp_80sps_mm_s_per_g: float
    ki_80sps_mm_s_per_g_s: float
    kp_10sps_mm_s_per_g: float
    ki_10sps_mm_s_per_g_s: float

    def to_dict(self) -> dict[str, float]:
        """JSON-able, the keys of the rig config's ``force_loop`` block (:mod:`rigctl.acquisition.rigconfig`)."""
        return {"hx711_rate_sps": int(self.hx711_rate_sps), "kp_80sps_mm_s_per_g": self.kp_80sps_mm_s_per_g,
                "ki_80sps_mm_s_per_g_s": self.ki_80sps_mm_s_per_g_s, "kp_10sps_mm_s_per_g": self.kp_10sps_mm_s_per_g,
                "ki_10sps_mm_s_per_g_s": self.ki_10sps_mm_s_per_g_s}


# ----------------------------------------------------------------------------------------------------------------
# geometry (spec 2.6; the firmware header's RIGCTL_DRUM_*_DEF, checked by tests/test_wire_spec.py)
# ----------------------------------------------------------------------------------------------------------------
#: drum diameter, mm; stepper full steps per revolution; microsteps per full step (spec 2.6)
DRUM_DIAMETER_MM = 100.0
DRUM_STEPS_PER_REV = 200
DRUM_MICROSTEPS = 16
#: drum circumference, mm (pi x diameter): one revolution of the plate
DRUM_CIRCUMFERENCE_MM = math.pi * DRUM_DIAMETER_MM
#: how far the drum speed the index sensor measures (and the microsteps per revolution it counts) may be from the
#: setpoint (the firmware's steps_per_rev x microsteps) before a trial is flagged ``drum_speed_mismatch`` and the
#: doctor's drum-speed check fails: another microstep setting is a factor of 2 or more, missed steps a few %. The
#: sensor counts revolutions: a drum of another diameter than the firmware's turns at the expected rate and is not
#: seen (speeds in mm/s use the firmware's diameter)
DRUM_SPEED_TOLERANCE = 0.03
#: speed marks per drum revolution (a slotted disc and its sensor, spec 2.6; the firmware's
#: RIGCTL_DRUM_MARKS_PER_REV): the drum's speed and its slip are measured once per mark, 39 mm of surface apart,
#: six times inside a 240 mm trial
DRUM_MARKS_PER_REV = 8
#: how much more than one mark interval's microsteps may pass without a mark before the controller latches
#: DRUM_SLIP (RIGCTL_DRUM_SLIP_TOLERANCE_PCT): the measurement's own error is +-1 step of 400 on the simulated
#: rigs (docs/firmware.md, "Speed marks"); a disc's slots cut to +-0.5 degree add +-1.1 %
DRUM_SLIP_TOLERANCE = 0.05


# ----------------------------------------------------------------------------------------------------------------
# errors of any drum controller (the Modbus client adds ModbusExceptionError in rigctl.devices.errors)
# ----------------------------------------------------------------------------------------------------------------
class DrumError(Exception):
    """Base class of the drum controller's errors (I/O failure, exception response, timeout, fault)."""


class DrumTimeout(DrumError):
    """The drum controller did not answer, or did not reach the awaited state in time."""


class DrumWaitAborted(DrumError):
    """A wait on the drum controller ended early because its caller stopped (a STOP, a Ctrl-C): the state awaited
    may no longer come at all (HOME stopped leaves NOT_HOMED, never IDLE), and the wait does not run its timeout out."""


class DrumFault(DrumError):
    """The drum controller latched a fault (state FAULT); ``faults`` holds the :class:`Fault` bits."""

    def __init__(self, faults: int, message: str = "") -> None:
        self.faults = Fault(int(faults))
        super().__init__((message + ": " if message else "") + f"drum controller fault: {describe_faults(faults)}")


class DrumReset(DrumError):
    """The drum controller reset while the host used it (BOOT_COUNT changed, or it reports NOT_HOMED unasked): a
    brown-out, its watchdog, a reset pulse. Whatever it was doing stopped; it must be homed (and tared) again."""


@runtime_checkable
class Clock(Protocol):
    """The host clock a controller's waits run on: ``now()`` in s (monotonic), ``sleep(s)``. The wall clock
    (``time.monotonic``), or the in-process backend's simulated clock (a sleep advances the simulation)."""

    def now(self) -> float:
        """The time now, s (monotonic)."""
        ...

    def sleep(self, s: float) -> None:
        """Wait ``s`` s (simulated: advance the simulation by ``s``)."""
        ...
