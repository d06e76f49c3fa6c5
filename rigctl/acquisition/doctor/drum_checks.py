"""Doctor checks of the drum controller (Mega): firmware against the installed sources, reset cause and boot count,
the HX711's rate, the load cell's zero, scale and polarity, the force loop's step response, the drum speed measured
from the index.

The checks speak to the controller through its typed contract (:class:`rigctl.core.interfaces.DrumController`:
status, settings by register name, settle band), never through registers. A check that needs a value this
controller does not report (a register its firmware lacks, docs/wire-protocol.md section 2) reports ``skip`` naming
it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.acquisition.doctor.base import Check, CheckResult, DoctorContext, Skip, failed, last_report, passed
from rigctl.acquisition.doctor.measure import row_correlations, step_response
from rigctl.acquisition.rigconfig import load_rig_config
from rigctl.core.drum import (
    ACTUATOR_DIRECTION_CAUSES,
    CRUSH_NOTE,
    DRUM_CIRCUMFERENCE_MM,
    DRUM_DIAMETER_MM,
    DRUM_MICROSTEPS,
    DRUM_SPEED_TOLERANCE,
    DRUM_STEPS_PER_REV,
    HAND_PRESSES,
    DrumState,
    fault_advice,
    hand_press_verdict,
)
from rigctl.core.interfaces import MassPlacer

__all__ = ["CHECKS", "ACTUATOR_DIRECTION_FIX", "ACTUATOR_REVERSED_FIX", "CELL_REVERSED_FIX", "NOISY_PRESS_FIX",
           "hand_press_change_g", "hand_presses_g",
           "DRUM_DIRECTION_FIX", "POLARITY_SETPOINT_G", "STEP_SETPOINT_G", "REFERENCE_MASS_G",
           "MAX_OVERSHOOT_PCT", "MAX_SETTLING_S"]

#: setpoint of the polarity check's press, g (the smallest of the paper's forces)
POLARITY_SETPOINT_G = 250.0
#: setpoint of the step-response check, g (the middle of the paper's 250/500/1000 g)
STEP_SETPOINT_G = 500.0
#: a step response overshooting more than this fails: at 1000 g it would be 1300 g, near the 1500 g force limit
MAX_OVERSHOOT_PCT = 30.0
#: ... and one that has not settled within the tolerance this long after contact fails (a trial waits for FORCE_SETTLED)
MAX_SETTLING_S = 3.0
#: how long the step-response trace runs after contact, s
STEP_TRACE_S = 6.0
#: status polling period of the traces, s (~50 Hz, as a trial's trace)
POLL_S = 0.02
#: the drum speeds the index check runs at, mm/s (the paper's slowest and fastest)
DRUM_SPEED_CHECK_MM_S = (40.0, 120.0)
#: the index check counts edges from this long after RUN (controller time), s: the drum reaches 120 mm/s in 0.3 s at
#: its 400 mm/s^2 ramp (drum_config.h DRUM_ACCEL_MM_S2)
DRUM_SPINUP_S = 1.0

#: the drum-direction check: the drum's speed, mm/s, the taxel capture after the spin-up, s, and the correlation between
#: the front and the back taxel row below which the plate shows too little texture to tell the direction
DIRECTION_SPEED_MM_S = 40.0
DIRECTION_CAPTURE_S = 2.0
#: the plate the check mounts on a simulated rig (circular ridges, 2 mm high, 15 mm apart; a real rig's operator
#: mounts a textured plate)
DIRECTION_PLATE = "C"
DIRECTION_MIN_CORRELATION = 0.5
#: ... and the least difference between the forwards and the backwards correlation that decides
DIRECTION_MIN_MARGIN = 0.2
#: how to fix a drum that turns backwards
DRUM_DIRECTION_FIX = ("the drum turns backwards: power off and swap one coil pair of the drum motor at its driver "
                      "(1A <-> 1B), or invert the driver's direction setting (e.g. a TMC2209's GCONF shaft bit over "
                      "UART); the firmware drives DIR high for forwards (docs/hardware/wiring.md#actuator-direction)")

#: the fix for a force loop that does not settle
FORCE_LOOP_FIX = ("set the HX711 board's RATE pin high (80 SPS; many boards ship at 10 SPS) and check the contact "
                  "stiffness against the force-loop gains (docs/hardware)")


def status_value(ctx: DoctorContext, field: str, register: str) -> Any:
    """``field`` of the controller's status, or raise :class:`Skip` naming the ``register`` behind it."""
    value = getattr(ctx.rig().drum.read_status(), field, None)
    if value is None:
        raise Skip(f"the drum controller does not report {register} (docs/wire-protocol.md 2.2)")
    return value


class FirmwareClock:
    """The drum controller's own time, s: its HEARTBEAT (+1 every 10 ms of the controller's clock, 16 bits)
    unwrapped across reads. Traces are timed on it, so a step response measured on the firmware under simavr (which
    runs slower than the wall clock) or on a loaded host is the controller's, not the host's."""

    def __init__(self) -> None:
        self._last: int | None = None
        self._ticks = 0

    def __call__(self, status: Any) -> float:
        hb = int(status.heartbeat) & 0xFFFF
        if self._last is not None:
            self._ticks += (hb - self._last) & 0xFFFF
        self._last = hb
        return self._ticks * 0.01


def _poll(ctx: DoctorContext, limit_s: float):
    """Yield ``(t_s, status)`` every :data:`POLL_S` (host clock) until ``limit_s`` of controller time have passed."""
    drum = ctx.rig().drum
    clock = ctx.clock
    fw = FirmwareClock()
    while True:
        ctx.check_cancel()
        st = drum.read_status()
        t = fw(st)
        yield t, st
        if t >= limit_s:
            return
        clock.sleep(POLL_S)


def _not_faulted(ctx: DoctorContext) -> None:
    """Raise :class:`Skip` when the controller has a fault latched (a check that moves the rig cannot run)."""
    st = ctx.rig().drum.read_status()
    if st.state == DrumState.FAULT:
        raise Skip(f"the drum controller is in FAULT ({_fault_names(st.faults)}): see controller-faults")


def check_controller_faults(ctx: DoctorContext) -> CheckResult:
    st = ctx.rig().drum.read_status()
    if st.state != DrumState.FAULT and not int(st.faults):
        return passed("controller-faults", f"none latched (state {st.state.name})")
    names = [f for f in type(st.faults) if f in st.faults and f.value]
    advice = fault_advice(st.faults)
    return failed("controller-faults", f"latched: {_fault_names(st.faults)} (state {st.state.name})",
                  advice or "clear the fault's cause, then CLEAR_FAULT", faults=[f.name for f in names])


#: what to do about ACTUATOR_DIRECTION before the load cell's polarity is known: both causes and how to tell them
#: apart (a coil swap is advised only once the cell is known to read right; docs/hardware/wiring.md)
ACTUATOR_DIRECTION_FIX = ACTUATOR_DIRECTION_CAUSES + f"; {CRUSH_NOTE} (docs/hardware/wiring.md, actuator direction)"
#: ... once the cell read a hand press as a rise: the cell is right; the motor is wrong only if it is seen to turn the
#: wrong way (a zero that moved since calibration, a noisy DOUT line or a stuck home switch latch the same fault with a
#: good motor: the advice walker, issue 75 item 4)
ACTUATOR_REVERSED_FIX = ("the load cell reads a press as a rise, so the cell is right; that alone does not make the "
                         "motor wrong. Acknowledge and watch the lead screw while the start's HOME creeps (it proves "
                         "its way and stops where it is wrong): only if you see it close the gap to the sensor where "
                         "it should open it, power off and swap one coil pair of the actuator motor at its driver "
                         "(1A <-> 1B), then HOME; if it moves the right way, change no wire: check the home switch, "
                         "its wire and the HX711's DOUT and SCK wires, and the load cell's zero (rigctl calibrate loadcell); "
                         f"{CRUSH_NOTE} (docs/hardware/wiring.md, actuator direction)")
#: ... once it read the press as a fall: the cell is reversed, the motor is right
CELL_REVERSED_FIX = ("the load cell reads a press as a fall: the cell is reversed, not the actuator. Power off and "
                     "swap the cell's signal wires A+ and A- at the HX711 (or turn the cell over); leave the actuator "
                     "motor's coils as they are (swapping them would drive HOME into the sensor); then HOME and "
                     f"calibrate again; {CRUSH_NOTE}")
#: ... once the hand presses disagreed (issue 75, 736172: -528, -1,745 and -824 g for 200 g on a noisy DOUT line)
NOISY_PRESS_FIX = ("the hand presses do not agree with each other or with the weight: the reading is noisy or does not "
                   "follow the cell, which no wire swap mends: change no wire; check the HX711's DOUT and SCK wires "
                   f"and its power, then press again; {CRUSH_NOTE} (docs/hardware/wiring.md, actuator direction)")
#: the hand press the doctor makes on a simulated rig (a mass rested on the cell), g, and how long it waits for the
#: HX711 to show it (4 periods of its sinc^4 filter at 10 SPS and the conversion after), s
HAND_PRESS_G = 200.0
HAND_PRESS_WAIT_S = 1.0


def _mean_force_g(ctx: DoctorContext, n: int = 5) -> float:
    drum, clock = ctx.rig().drum, ctx.clock
    forces = []
    for _ in range(n):
        forces.append(float(drum.read_status().force_g))
        clock.sleep(POLL_S)
    return float(np.mean(forces))


def hand_press_change_g(ctx: DoctorContext) -> float | None:
    """The load cell pressed by hand, as an operator would to tell a reversed cell from a reversed actuator: the
    change of FORCE_G, g, while :data:`HAND_PRESS_G` rests on the cell (a simulated rig's
    :class:`rigctl.core.interfaces.MassPlacer`); None on a rig the doctor cannot press (hardware: the operator
    does, :data:`ACTUATOR_DIRECTION_FIX`)."""
    backend = ctx.rig().backend
    if not isinstance(backend, MassPlacer):
        return None
    before = _mean_force_g(ctx)
    backend.place_mass(HAND_PRESS_G)
    try:
        ctx.clock.sleep(HAND_PRESS_WAIT_S)
        pressed = _mean_force_g(ctx)
    finally:
        backend.place_mass(0.0)
    return pressed - before


def hand_presses_g(ctx: DoctorContext, n: int = HAND_PRESSES) -> list[float] | None:
    """The advice's hand press repeated ``n`` times (:data:`rigctl.core.drum.HAND_PRESS_STEP`: a wire is changed only
    on presses that agree, :func:`rigctl.core.drum.hand_press_verdict`): each press's change of FORCE_G, g
    (:func:`hand_press_change_g`); None on a rig the doctor cannot press."""
    changes = []
    for _ in range(n):
        change = hand_press_change_g(ctx)
        if change is None:
            return None
        changes.append(change)
    return changes


def check_actuator_direction(ctx: DoctorContext) -> CheckResult:
    """HOME proves the actuator's direction (docs/wire-protocol.md 2.5): the home switch opened when HOME left home
    and closed when it came back, and the load cell's untared force did not rise meanwhile. HOMEs again if the
    controller is not homed (and not faulted). When the proof fails (ACTUATOR_DIRECTION), the cell's polarity is
    checked before a coil swap is advised: a reversed cell after a reset under load latches it too, and swapping
    the motor's coils then drives HOME into the sensor (issue 55): a hand press (:func:`hand_press_change_g`) that
    reads as a rise -> the actuator; as a fall -> the cell; not known (hardware) -> both, and how to tell."""
    drum = ctx.rig().drum
    st = drum.read_status()
    direction = getattr(type(st.faults), "ACTUATOR_DIRECTION", None)
    if direction is None:
        raise Skip("the drum controller's firmware has no ACTUATOR_DIRECTION fault (docs/wire-protocol.md 2.5): "
                   "flash the installed firmware")
    if st.state == DrumState.NOT_HOMED:
        drum.home()
        st = poll_until_not_homing(ctx)
    if direction in st.faults:
        seen = ("HOME's direction proof failed: the load cell's reading rose (or the home switch did not open) while "
                "the firmware drove the actuator home (ACTUATOR_DIRECTION)")
        changes = hand_presses_g(ctx)
        if changes is None:
            return failed("actuator-direction", f"{seen}: the actuator or the load cell is reversed",
                          ACTUATOR_DIRECTION_FIX)
        read = ", ".join(f"{c:+.0f}" for c in changes)
        said = f"{seen}; {len(changes)} presses of {HAND_PRESS_G:g} g on the load cell read {read} g"
        verdict = hand_press_verdict(changes, HAND_PRESS_G)
        if verdict == "rise":
            return failed("actuator-direction", f"{said}: the cell is right, so the actuator turns the wrong way or the "
                          "reading moved by itself", ACTUATOR_REVERSED_FIX, hand_press_change_g=min(changes))
        if verdict == "fall":
            return failed("actuator-direction", f"{said}: the load cell is reversed", CELL_REVERSED_FIX,
                          hand_press_change_g=max(changes))
        return failed("actuator-direction", f"{said}: they do not agree (a noisy reading, or a cell that does not "
                      "answer): change no wire", NOISY_PRESS_FIX, hand_press_change_g=changes[-1])
    if not st.homed:
        raise Skip(f"the controller is not homed (state {st.state.name}): see controller-faults")
    return passed("actuator-direction", "HOME left the home switch (it opened) and came back to it (it closed): the "
                  "actuator turns the way the firmware drives it")


def poll_until_not_homing(ctx: DoctorContext, limit_s: float = 15.0) -> Any:
    """Poll the controller until it leaves HOMING (or ``limit_s`` of controller time); the last status."""
    st = None
    for _, st in _poll(ctx, limit_s):
        if st.state != DrumState.HOMING:
            break
    return st


def _tolerance_g(ctx: DoctorContext) -> float:
    return float(ctx.rig().drum.settle_band().force_tolerance_g)


def check_firmware_version(ctx: DoctorContext) -> CheckResult:
    from rigctl import firmware

    want = firmware.source_versions()
    rig = ctx.rig()
    mega = tuple(rig.drum.read_status().firmware)
    banner = getattr(rig.stream, "banner", None) or {}
    uno = tuple(banner.get("firmware") or ())
    values = {"mega_firmware": list(mega), "uno_firmware": list(uno), "sources_mega": list(want["mega"]),
              "sources_uno": list(want["uno"])}
    wrong = [f"{b} reports {'.'.join(map(str, got)) or '?'}, the installed sources are "
             f"{'.'.join(map(str, want[b]))}" for b, got in (("mega", mega), ("uno", uno)) if got != want[b]]
    if wrong:
        return failed("firmware-version", "; ".join(wrong), "flash the installed firmware: rigctl firmware --flash "
                      "PORT --board mega|uno", **values)
    return passed("firmware-version", f"mega {mega[0]}.{mega[1]}, uno {uno[0]}.{uno[1]}: the installed sources' "
                  f"versions", **values)


#: the boards by the name ``rigctl firmware --board`` takes, in words
_BOARD_WORDS = {"mega": "the drum controller", "uno": "the taxel streamer"}


def check_firmware_build(ctx: DoctorContext) -> CheckResult:
    """Each board's build id (the sources' digest it was built from: the Mega's BUILD_ID_0 .. _2 input registers,
    docs/wire-protocol.md 2.2; the Uno's banner ``build=``, 1.4) against the installed sources' digest: a board
    flashed from other sources of the same version fails with the flash command, and so does a drum controller
    reporting build 0 (an image without an id: the Arduino IDE, ``make BUILD_ID=``; rigctl refuses to open it,
    :data:`rigctl.firmware.REQUIRED_BUILD_ID`); a taxel streamer without an id (a simulated Uno) is named."""
    from rigctl import firmware

    digest = firmware.source_digest()
    rig = ctx.rig()
    banner = getattr(rig.stream, "banner", None) or {}
    builds = {"mega": getattr(rig.drum.read_status(), "build_id", None), "uno": banner.get("build")}
    builds = {board: None if b is None else str(b).lower() for board, b in builds.items()}
    values = {"mega_build": builds["mega"], "uno_build": builds["uno"], "sources_digest": digest}
    without = [f"{_BOARD_WORDS[board]} ({board}) reports no build id" for board, b in builds.items() if b is None
               and board not in firmware.REQUIRED_BUILD_ID]
    wrong = [board for board, b in builds.items() if b is not None and not digest.startswith(b)]
    zero = [board for board, b in builds.items() if b is None and board in firmware.REQUIRED_BUILD_ID]
    if wrong or zero:
        said = [f"{_BOARD_WORDS[board]} ({board}) runs build {builds[board]}, the installed sources are "
                f"{digest[:len(str(builds[board]))]}" for board in wrong]
        said += [f"{_BOARD_WORDS[board]} ({board}) runs build 0 (an image without a build id: the Arduino IDE or "
                 f"make BUILD_ID=), the installed sources are {digest[:firmware.BUILD_ID_DIGITS]}" for board in zero]
        return failed("firmware-build", "; ".join(said),
                      "flash the installed firmware: " + " and ".join(f"rigctl firmware --flash PORT --board {board}"
                                                                      for board in (*wrong, *zero)), **values)
    same = [f"{board} build {b}" for board, b in builds.items() if b is not None]
    return passed("firmware-build", "; ".join([f"{' and '.join(same)} = the installed sources'", *without]), **values)


def _flag_names(value: Any) -> list[str]:
    """The set bits of an IntFlag value by name."""
    return [f.name for f in type(value) if f.value and f in value and f.name]


def check_reset_cause(ctx: DoctorContext) -> CheckResult:
    st = ctx.rig().drum.read_status()
    if not hasattr(st, "reset_cause") or not hasattr(st, "boot_count"):
        raise Skip("the drum controller does not report RESET_CAUSE and BOOT_COUNT (docs/wire-protocol.md 2.2)")
    causes = _flag_names(st.reset_cause)
    boots = int(st.boot_count)
    values: dict[str, Any] = {"reset_cause": causes, "boot_count": boots}
    # BOOT_COUNT (spec 2.7): high byte = power-ups and brown-outs (EEPROM), low byte = warm resets since (RAM)
    cold, warm = boots >> 8, boots & 0xFF
    since = ("a power-up or brown-out (RAM lost)" if warm == 0 else
             f"{warm} warm resets (reset pin, port opening, watchdog) since the last power-up")
    what = (f"last reset: {', '.join(causes) if causes else 'cause unknown (0: the stk500v2 bootloader clears it)'}; "
            f"{since}")
    before = last_report(ctx.mode, ctx.config_path)
    if before is not None:
        prev = next((r.values.get("boot_count") for r in before.results if r.name == "reset-cause"), None)
        if isinstance(prev, int):
            values["power_ups_since_last_doctor"] = (cold - (prev >> 8)) & 0xFF
            what += (f", {(cold - (prev >> 8)) & 0xFF} power-ups or brown-outs since the last doctor run "
                     f"({before.checked_utc})")
    if "WATCHDOG" in causes:
        return failed("reset-cause", what, "the controller's watchdog reset it: loop() hung. Note what the rig was "
                      "doing, check the motor wiring for interference (docs/hardware/wiring.md#power-and-grounding) "
                      "and report it with the firmware version", **values)
    if "BROWN_OUT" in causes:
        return failed("reset-cause", what, "the Mega's supply sagged below its brown-out level: power it from a "
                      "stable supply (not a weak USB hub), and set the BOD fuse to 4.3 V "
                      "(docs/hardware/wiring.md#brown-out-detection)", **values)
    return passed("reset-cause", what, **values)


def check_estop(ctx: DoctorContext) -> CheckResult:
    st = ctx.rig().drum.read_status()
    if not hasattr(st, "estop_open"):
        raise Skip("the drum controller does not report its e-stop input (STATUS_FLAGS, docs/wire-protocol.md 2.2)")
    values = {"estop_open": bool(st.estop_open), "drivers_enabled": bool(getattr(st, "drivers_enabled", False))}
    if st.estop_open:
        return failed("e-stop", "the e-stop input reads open (the button is pressed, or its normally-closed wire is "
                      "broken)", "release the e-stop (turn it); else check its NC3 contact and wire to the Mega "
                      "(docs/hardware/wiring.md#e-stop), then CLEAR_FAULT and HOME", **values)
    return passed("e-stop", "the e-stop input reads closed" + (", drivers enabled" if values["drivers_enabled"] else
                                                                ", drivers disabled"), **values)


def check_hx711_rate(ctx: DoctorContext) -> CheckResult:
    drum = ctx.rig().drum
    sps = float(status_value(ctx, "hx711_rate_sps", "HX711_RATE_0P01SPS"))
    if sps <= 0:
        raise Skip("the drum controller reports no measured HX711 rate (HX711_RATE_0P01SPS is 0: not measured yet, "
                   "or a firmware without it)")
    configured = drum.settings().get("HX711_RATE_SPS")
    values = {"hx711_rate_sps": sps, "configured_sps": configured}
    if sps < 40:
        return failed("hx711-rate", f"the HX711 converts at {sps:.1f} samples/s (RATE pin low)", "set the HX711 "
                      "board's RATE pin high for 80 SPS (docs/hardware/wiring.md#hx711-rate); the force loop at 10 SPS "
                      "is slow", **values)
    if configured and abs(sps / configured - 1) > 0.2:
        return failed("hx711-rate", f"the HX711 converts at {sps:.1f} samples/s, the force loop is set for "
                      f"{configured} (HX711_RATE_SPS)", f"write {round(sps)} to HX711_RATE_SPS if that rate is "
                      "intended, else fix the board's RATE pin", **values)
    return passed("hx711-rate", f"{sps:.1f} samples/s measured at boot" + (f", the force loop is set for {configured}"
                  if configured else ""), **values)


def check_loadcell_zero(ctx: DoctorContext) -> CheckResult:
    rig = ctx.rig()
    drum = rig.drum
    st = drum.read_status()
    if st.state != DrumState.IDLE or st.actuator_mm > 0.05:
        raise Skip(f"the actuator is not at home (state {st.state.name}, {st.actuator_mm:g} mm)")
    tol = _tolerance_g(ctx)
    clock = ctx.clock
    forces = []
    for _ in range(25):
        forces.append(drum.read_status().force_g)
        clock.sleep(POLL_S)
    zero = float(np.mean(forces))
    noise = float(np.std(forces))
    if abs(zero) > tol:
        return failed("loadcell-zero", f"the load cell reads {zero:+.1f} g at home (tolerance {tol} g)",
                      "tare at home (the actuator released): rigctl calibrate loadcell, or the GUI's calibration tab; a reading "
                      "that drifts back: check the cell's mounting and wiring", zero_g=zero, noise_g=noise)
    return passed("loadcell-zero", f"{zero:+.1f} g at home (sd {noise:.1f} g, tolerance {tol} g)", zero_g=zero,
                  noise_g=noise)


def _board_counts_per_g(settings: dict[str, int]) -> float | None:
    """The controller's load-cell scale, counts per g: the 32-bit signed LOADCELL_SCALE_X100_HI/_LO when the
    controller has them, else the 16-bit LOADCELL_SCALE_X100; None if neither."""
    if "LOADCELL_SCALE_X100_HI" in settings and "LOADCELL_SCALE_X100_LO" in settings:
        raw = (settings["LOADCELL_SCALE_X100_HI"] << 16) | settings["LOADCELL_SCALE_X100_LO"]
        return (raw - (1 << 32) if raw & 0x80000000 else raw) / 100.0
    x100 = settings.get("LOADCELL_SCALE_X100")
    return None if not x100 else x100 / 100.0


def check_loadcell_scale(ctx: DoctorContext) -> CheckResult:
    drum = ctx.rig().drum
    cal = load_rig_config(ctx.config_path).get("loadcell") or {}
    if getattr(drum.read_status(), "calibration_defaults", False):
        if "counts_per_g" not in cal and ctx.simulated:
            raise Skip("a fresh simulated controller has no EEPROM calibration and the rig config none: calibrate "
                       "to check it")
    # a simulated controller starts with an empty EEPROM every time: only its scale can be compared
    if getattr(drum.read_status(), "calibration_defaults", False) and not ctx.simulated:
        lost = " (the rig config holds one: the EEPROM lost it)" if "counts_per_g" in cal else ""
        return failed("loadcell-scale", f"the Mega's EEPROM calibration was missing or failed its checksum at boot: it "
                      f"runs on the default scale{lost}", "calibrate the load cell (rigctl calibrate loadcell, or the "
                      "GUI's calibration tab), which saves it to the EEPROM", calibration_defaults=True)
    if "counts_per_g" not in cal:
        raise Skip("the rig config holds no load-cell calibration: calibrate first")
    board = _board_counts_per_g(drum.settings())
    if board is None:
        raise Skip("the drum controller does not report its load-cell scale")
    want = float(cal["counts_per_g"])
    values = {"board_counts_per_g": board, "config_counts_per_g": want}
    if abs(board - want) > max(0.01, 0.001 * abs(want)):
        return failed("loadcell-scale", f"the Mega uses {board:g} counts/g, the rig config's calibration {want:g} (the "
                      "EEPROM was lost, or another cell was calibrated)", "calibrate the load cell again (rigctl "
                      "calibrate loadcell, or the GUI's calibration tab), which saves it to the EEPROM and the rig config", **values)
    return passed("loadcell-scale", f"{board:g} counts/g = the rig config's calibration", **values)


#: the doctor's reference mass, g (a lab's calibration mass: the paper's middle force), and how far its reading may be
#: off, in % of the mass (the scale's own rounding and the HX711's noise are far below it; the stiffness check of
#: every press, docs/wire-protocol.md 2.12, allows 15 %: this one finds what that one lets through)
REFERENCE_MASS_G = 500.0
REFERENCE_MASS_TOLERANCE_PCT = 2.0
REFERENCE_MASS_FIX = ("recalibrate the load cell with the reference mass (rigctl calibrate loadcell --mass-g 500, or "
                      "the GUI's calibration tab: it stores the scale and the contact's stiffness together); if it "
                      "reads wrong "
                      "again, check the cell, its excitation and signal wires and that it is the cell of the rig's "
                      "range")


def check_reference_mass(ctx: DoctorContext) -> CheckResult:
    """The load cell reads a known mass right (issue 75 item 6): :data:`REFERENCE_MASS_G` on the cell (a simulated
    rig's :class:`rigctl.core.interfaces.MassPlacer`; on hardware the operator, when the doctor was given a way to
    ask: ``ctx.place_mass``), FORCE_G within :data:`REFERENCE_MASS_TOLERANCE_PCT`; and the contact's stiffness
    stored with the calibration, which every press's probe checks the scale against (none stored: that check is off,
    a failure)."""
    rig = ctx.rig()
    drum = rig.drum
    st = drum.read_status()
    if st.state != DrumState.IDLE or st.actuator_mm > 0.05:
        raise Skip(f"the actuator is not at home (state {st.state.name}, {st.actuator_mm:g} mm)")
    backend = rig.backend
    place = ctx.place_mass or (backend.place_mass if isinstance(backend, MassPlacer) else None)
    if place is None:
        raise Skip(f"on hardware the operator puts the {REFERENCE_MASS_G:g} g reference mass on the load cell: run "
                   "rigctl doctor at a terminal, which asks for it")
    mass = REFERENCE_MASS_G
    before = _mean_force_g(ctx)
    place(mass)
    try:
        ctx.clock.sleep(HAND_PRESS_WAIT_S)  # the HX711 settles 4 periods after the mass lands
        read = _mean_force_g(ctx) - before
    finally:
        place(0.0)
        # the mass just taken off: the HX711 settles (4 periods) before the next check's press, whose start judges
        # the reading against the tare (LOADCELL_ZERO, wire-protocol 2.13: 432 g read 0 ms after the lift latched it)
        ctx.clock.sleep(HAND_PRESS_WAIT_S)
    stored = drum.calibration_stiffness()
    off_pct = 100.0 * (read - mass) / mass
    values = {"mass_g": mass, "read_g": read, "off_pct": off_pct, "stored_stiffness_g_per_mm": stored}
    what = f"{mass:g} g reads {read:.1f} g ({off_pct:+.1f} %)"
    if abs(off_pct) > REFERENCE_MASS_TOLERANCE_PCT:
        return failed("reference-mass", f"{what}: the reading's scale is off (tolerance "
                      f"{REFERENCE_MASS_TOLERANCE_PCT:g} %)", REFERENCE_MASS_FIX, **values)
    if not stored:
        return failed("reference-mass", f"{what}, but no contact stiffness is stored with the calibration: the "
                      "check of the scale at every press (docs/wire-protocol.md 2.12) is off", REFERENCE_MASS_FIX,
                      **values)
    return passed("reference-mass", f"{what}; {stored} g/mm stored with the calibration for every press's check",
                  **values)


def _fault_names(faults: Any) -> str:
    return "|".join(f.name for f in type(faults) if f in faults and f.value) or str(int(faults))


def _press(ctx: DoctorContext, setpoint_g: float) -> float:
    """PRESS at ``setpoint_g`` (the controller not faulted, else :class:`Skip`); returns the force tolerance, g."""
    _not_faulted(ctx)
    drum = ctx.rig().drum
    tol = _tolerance_g(ctx)
    drum.set_force(setpoint_g)
    drum.press()
    return tol


def check_loadcell_polarity(ctx: DoctorContext) -> CheckResult:
    drum = ctx.rig().drum
    tol = _press(ctx, POLARITY_SETPOINT_G)
    lowest = 0.0
    reversed_fix = ("the load cell reads negative while pressing: swap the cell's signal wires (A+/A-, usually green/"
                    "white) at the HX711, or turn the cell over; then calibrate again")
    for _t, st in _poll(ctx, 15.0):
        lowest = min(lowest, st.force_g)
        if st.state == DrumState.FAULT:
            drum.stop()
            names = _fault_names(st.faults)
            if lowest < -2 * tol or "LOADCELL_REVERSED" in names:
                return failed("loadcell-polarity", f"fault {names} while pressing, the force went to {lowest:.0f} g",
                              reversed_fix, lowest_force_g=lowest)
            return failed("loadcell-polarity", f"fault {names} while pressing (force {st.force_g:.0f} g at "
                          f"{st.actuator_mm:.2f} mm)", fault_advice(st.faults) or "clear the fault's cause, then check "
                          "again", lowest_force_g=lowest)
        if st.force_g < -2 * tol:
            drum.stop()
            return failed("loadcell-polarity", f"the force went to {st.force_g:.0f} g while the actuator pressed "
                          f"{st.actuator_mm:.2f} mm towards the sensor", reversed_fix, lowest_force_g=lowest)
        if st.force_g > POLARITY_SETPOINT_G / 2:
            drum.stop()
            return passed("loadcell-polarity", f"the force rises as the actuator presses ({st.force_g:.0f} g at "
                          f"{st.actuator_mm:.2f} mm)", force_g=st.force_g, actuator_mm=st.actuator_mm)
    drum.stop()
    return failed("loadcell-polarity", f"the force did not rise within 15 s of PRESS (lowest {lowest:.0f} g)",
                  "check the HX711's wiring (pin table: PIN_HX_DOUT, PIN_HX_SCK) and the load cell's excitation",
                  lowest_force_g=lowest)


def check_force_step(ctx: DoctorContext) -> CheckResult:
    drum = ctx.rig().drum
    tol = _press(ctx, STEP_SETPOINT_G)
    t, f, x = [], [], []
    contact = None
    for now, st in _poll(ctx, 15.0 + STEP_TRACE_S):
        t.append(now)
        f.append(st.force_g)
        x.append(st.actuator_mm)
        if st.state == DrumState.FAULT:
            drum.stop()
            return failed("force-step", f"fault {_fault_names(st.faults)} during the {STEP_SETPOINT_G:g} g step "
                          f"(force {st.force_g:.0f} g)", FORCE_LOOP_FIX)
        if contact is None and st.force_g > 0.1 * STEP_SETPOINT_G:
            contact = now
        if contact is None and now > 15.0:
            drum.stop()
            raise Skip("no contact within 15 s of PRESS (see loadcell-polarity)")
        if contact is not None and now - contact >= STEP_TRACE_S:
            break
    drum.stop()
    r = step_response(np.array(t), np.array(f), np.array(x), STEP_SETPOINT_G, tol)
    values = {"setpoint_g": STEP_SETPOINT_G, "tolerance_g": tol, "overshoot_pct": r.overshoot_pct,
              "settling_time_s": r.settling_time_s, "residual_pp_g": r.residual_pp_g,
              "stiffness_g_per_mm": r.stiffness_g_per_mm, "samples": len(t)}
    k = "" if math.isnan(r.stiffness_g_per_mm) else f" at {r.stiffness_g_per_mm:.0f} g/mm"
    what = (f"0 -> {STEP_SETPOINT_G:g} g{k}: overshoot {r.overshoot_pct:.0f} %, "
            + (f"settled in {r.settling_time_s:.2f} s" if r.settled else "not settled")
            + f", last 1 s {r.residual_pp_g:.0f} g peak-to-peak (controller time, {len(t)} readings)")
    if not r.settled or r.settling_time_s > MAX_SETTLING_S or r.overshoot_pct > MAX_OVERSHOOT_PCT:
        return failed("force-step", what, FORCE_LOOP_FIX, **values)
    return passed("force-step", what, **values)


class _Faulted(Exception):
    """The controller latched a fault during a check (``status`` the status that showed it)."""

    def __init__(self, status: Any) -> None:
        super().__init__(_fault_names(status.faults))
        self.status = status


def _index_speed(ctx: DoctorContext, speed_mm_s: float) -> tuple[float, int]:
    """Run the drum at ``speed_mm_s`` (pressing at the polarity setpoint) and return the drum speed the index sensor
    measured over a whole revolution after the speed is steady, mm/s, and the microsteps sent in it. Raises
    :class:`Skip` / RuntimeError when the sensor gives no edges."""
    drum = ctx.rig().drum
    drum.set_speed(speed_mm_s)
    _press(ctx, POLARITY_SETPOINT_G)
    drum.wait_force_settled(timeout_s=30.0)
    drum.run()
    rev_s = DRUM_CIRCUMFERENCE_MM / speed_mm_s
    start = None
    for t, st in _poll(ctx, DRUM_SPINUP_S + 3.5 * rev_s):
        if st.state == DrumState.FAULT:
            raise _Faulted(st)
        if t < DRUM_SPINUP_S:
            continue
        if start is None:
            start = st.index_count
        elif (st.index_count - start) & 0xFFFF >= 2 and st.index_period_s > 0:
            speed = st.index_speed_mm_s(DRUM_DIAMETER_MM)
            assert speed is not None
            return float(speed), int(st.index_steps)
    raise RuntimeError(f"no two index-sensor edges in 3.5 drum revolutions at {speed_mm_s:g} mm/s")


def check_drum_direction(ctx: DoctorContext) -> CheckResult:
    """The drum turns forwards: pressing at the polarity setpoint with the drum at :data:`DIRECTION_SPEED_MM_S`, the
    texture reaches the first layer's front row (row 0) before its back row, (rows - 1) x pitch / speed earlier; a
    drum turning backwards reverses that lag (:func:`.measure.row_correlations`). Neither the index sensor nor the
    speed-mark disc can tell (both symmetric)."""
    rig = ctx.rig()
    layout = rig.layout
    layer = layout.layers[0]
    if layer.rows < 2:
        raise Skip("the sensor's first layer has one row: no lag between rows shows the drum's direction")
    if ctx.simulated:  # a plate with ridges: the simulated rigs start with the smooth plate A
        rig.mount_texture(DIRECTION_PLATE)
    drum = rig.drum
    drum.set_speed(DIRECTION_SPEED_MM_S)
    _press(ctx, POLARITY_SETPOINT_G)
    drum.wait_force_settled(timeout_s=30.0)
    drum.run()
    for _, st in _poll(ctx, DRUM_SPINUP_S):
        if st.state == DrumState.FAULT:
            return failed("drum-direction", f"fault {_fault_names(st.faults)} while the drum turned",
                          fault_advice(st.faults) or "clear the fault's cause, then check again")
    n = int(round(DIRECTION_CAPTURE_S * layout.sample_rate_hz))
    stream = ctx.taxel_stream()
    stream.begin_capture()
    try:
        stream.wait_capture(n, timeout_s=3 * DIRECTION_CAPTURE_S + 5.0)
    finally:
        cap = stream.end_capture()
    drum.stop()
    grid = cap.samples[:, : layer.n_channels].reshape(len(cap.samples), layer.rows, layer.cols)
    lag = (layer.rows - 1) * layout.pitch_mm / DIRECTION_SPEED_MM_S * layout.sample_rate_hz
    try:
        forward, backward = row_correlations(grid[:, 0, :], grid[:, -1, :], lag)
    except ValueError:
        raise Skip(f"the taxel stream delivered {len(cap.samples)} frames in {DIRECTION_CAPTURE_S:g} s of the drum "
                   "turning: too few to tell its direction") from None
    values = {"lag_s": lag / layout.sample_rate_hz, "forward_correlation": round(forward, 3),
              "backward_correlation": round(backward, 3)}
    what = (f"the back taxel row repeats the front one {lag / layout.sample_rate_hz * 1000:.0f} ms later with a "
            f"correlation of {forward:.2f} (forwards), {lag / layout.sample_rate_hz * 1000:.0f} ms earlier with "
            f"{backward:.2f} (backwards), at {DIRECTION_SPEED_MM_S:g} mm/s")
    if max(forward, backward) < DIRECTION_MIN_CORRELATION or abs(forward - backward) < DIRECTION_MIN_MARGIN:
        raise Skip(f"{what}: too little texture to tell the drum's direction (mount a textured plate)")
    if backward > forward:
        return failed("drum-direction", what, DRUM_DIRECTION_FIX, **values)
    return passed("drum-direction", what, **values)


def check_drum_speed(ctx: DoctorContext) -> CheckResult:
    _not_faulted(ctx)
    st = ctx.rig().drum.read_status()
    if not hasattr(st, "index_count"):
        raise Skip("the drum controller does not report the index sensor (INDEX_COUNT, docs/wire-protocol.md 2.6)")
    expected_steps = DRUM_STEPS_PER_REV * DRUM_MICROSTEPS
    values: dict[str, Any] = {"expected_steps_per_rev": expected_steps}
    lines, bad = [], []
    for v in DRUM_SPEED_CHECK_MM_S:
        try:
            measured, steps = _index_speed(ctx, v)
        except _Faulted as exc:
            return failed("drum-speed", f"fault {_fault_names(exc.status.faults)} while the drum turned at {v:g} mm/s",
                          fault_advice(exc.status.faults) or "clear the fault's cause, then check again", **values)
        except RuntimeError as exc:
            return failed("drum-speed", str(exc), "check the index sensor's wiring (pin table: PIN_INDEX_SENSOR) and "
                          "its magnet or flag on the drum", **values)
        err = measured / v - 1.0
        values[f"speed_at_{v:g}_mm_s"] = measured
        values[f"steps_per_rev_at_{v:g}_mm_s"] = steps
        lines.append(f"{v:g} -> {measured:.1f} mm/s ({err * 100:+.1f} %, {steps} microsteps/rev)")
        if abs(err) > DRUM_SPEED_TOLERANCE:
            bad.append(v)
            break  # a drum already too fast at 40 mm/s is not run at 120
    what = "; ".join(lines)
    if bad:
        fix = ("set the drum driver to 16 microsteps (its MS pins, docs/hardware/wiring.md#microsteps)"
               if any(values[f"steps_per_rev_at_{v:g}_mm_s"] != expected_steps for v in bad) else
               "the drum turns the expected microsteps per revolution at another rate: the step timing is off (the "
               "Mega's 16 MHz crystal, a firmware built for another F_CPU): flash the installed firmware and check the "
               "board")
        return failed("drum-speed", what + f"; expected {expected_steps} microsteps/rev", fix, **values)
    return passed("drum-speed", what, **values)


CHECKS = (
    Check("firmware-version", check_firmware_version, title="firmware version = the installed sources'"),
    Check("firmware-build", check_firmware_build, title="firmware build hash = the installed sources'"),
    Check("controller-faults", check_controller_faults, title="no fault latched in the drum controller"),
    Check("reset-cause", check_reset_cause, title="reset cause and boot count"),
    Check("e-stop", check_estop, title="the e-stop input reads closed"),
    Check("hx711-rate", check_hx711_rate, title="HX711 rate (80 SPS)"),
    Check("loadcell-scale", check_loadcell_scale, title="load-cell scale = the rig config's calibration"),
    Check("actuator-direction", check_actuator_direction, moves=True, title="actuator turns the way HOME drives it"),
    # (needs the actuator homed, which opening never does: the doctor's start HOMEs it, as for the checks that move)
    Check("loadcell-zero", check_loadcell_zero, moves=True, title="load cell reads zero at home"),
    Check("reference-mass", check_reference_mass, moves=True,
          title="load cell reads the reference mass; the contact's stiffness stored"),
    Check("loadcell-polarity", check_loadcell_polarity, moves=True, title="load cell polarity"),
    Check("force-step", check_force_step, moves=True, title="force step response"),
    Check("drum-speed", check_drum_speed, moves=True, title="drum speed from the index at 40 and 120 mm/s"),
    Check("drum-direction", check_drum_direction, moves=True, title="drum turns forwards (taxel rows' lag)"),
)
