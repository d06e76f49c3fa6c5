"""The drum controller's logic (Arduino Mega 2560 firmware, ``docs/wire-protocol.md`` section 2), without a port.

:class:`MegaController` holds every holding and input register with its range column and the speed/force limits
(illegal value -> exception 03, unknown address -> 02, other functions -> 01; a function-16 write is checked as a
whole before any register changes), the commands and states, the CONSTANT and RAMP speed profiles, a PI force loop
on actuator velocity against the load cell, settle detection (FORCE_TOLERANCE_G for SETTLE_TIME_MS), the
force-limit fault (actuator backs off at once), the 10 ms heartbeat, tare, home, clear fault, and the calibration
registers kept in an emulated EEPROM (in memory, or a JSON file) with a checksum.

The firmware's protection outside ``loop()`` (docs/wire-protocol.md 2.4-2.8, docs/firmware.md) is modelled with the
same contract: after any reset (:meth:`MegaController.reset`: power-on, external, brown-out, watchdog) the state is
NOT_HOMED, the drivers are disabled and RUN/PRESS are refused until HOME succeeds; the power-up tare is taken only
with the home switch closed and HOME tares at the switch; RESET_CAUSE, BOOT_COUNT (EEPROM) and STATUS_FLAGS; the
e-stop input (:meth:`MegaController.set_estop`: ESTOP latched at once, motors stopped, not homed); a force below
-2 x FORCE_TOLERANCE_G while pressing faults LOADCELL_REVERSED; HOME gives up after its travel limit or timeout
(HOME_NOT_FOUND; :meth:`MegaController.break_home_switch` for the test); the signed 32-bit load-cell scale; a bad
EEPROM checksum falls back to the defaults and says so; :meth:`MegaController.hang_loop` stands for a hung
``loop()``: the outputs keep running (the firmware's step ISRs would) until the 120 ms watchdog stops them and, 120 ms
later, resets the controller. While hung, register requests get exception 04 (server device failure), where the
firmware would not answer at all. The physics is
:class:`rigctl.simulation.model.RigModel` (drum step rate and actuator velocity in, load cell and drum state out);
whoever owns the simulation clock calls :meth:`MegaController.step`.

Two boards use it: :class:`rigctl.simulation.virtual_mega.VirtualMega` serves it as a Modbus RTU server on a pty
(with the host-silence watchdog checked in the server's loop), and the in-process backend
(:mod:`rigctl.simulation.inprocess`) calls :meth:`MegaController.read_registers` / :meth:`write_registers`
directly, on a simulated clock.
"""

from __future__ import annotations

import collections
import functools
import logging
import threading
import time
from pathlib import Path

import numpy as np
from pymodbus.constants import ExcCodes

from rigctl import firmware
from rigctl.devices import wire
from rigctl.devices.wire import (
    Command,
    DrumState,
    Fault,
    HoldingRegister as HR,
    InputRegister as IR,
    ResetCause,
    StatusFlag,
)
from rigctl.simulation.controller_eeprom import EmulatedEeprom
from rigctl.simulation.controller_home import HOME_SPEED_MM_S, HomeAndDirection
from rigctl.simulation.drum_index import DrumIndex
from rigctl.simulation.force_loop import ContactProbe, force_pi_update, stiffness_max_g_per_mm
from rigctl.simulation.model import FORCE_PI_INTEGRATE_BAND_G, RigModel

log = logging.getLogger(__name__)

__all__ = ["MegaController", "LOADCELL_TIMEOUT_MS", "HOME_SPEED_MM_S"]

#: actuator calibration the simulated mechanics are built with (ACTUATOR_STEPS_PER_MM default)
_TRUE_ACTUATOR_STEPS_PER_MM = wire.HOLDING_RANGE[HR.ACTUATOR_STEPS_PER_MM][2]
_ENGAGED = (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING)
LOADCELL_TIMEOUT_MS = 200
#: the force loop's output clamp and the retract (back-off) speed, commanded mm/s: the firmware's ACT_MAX_SPEED_MM_S
#: (drum_config.h; equal by tests/test_wire_spec.py)
FORCE_LOOP_MAX_SPEED_MM_S = 5.0
#: the AVR watchdog's timeout (firmware: WDTO_120MS, interrupt first, reset at the second timeout), ms
AVR_WATCHDOG_MS = 120


def _u16(x: float) -> int:
    return int(round(x)) & 0xFFFF


@functools.cache
def installed_build_id() -> str | None:
    """The build id rigctl's firmware build gives the installed sources (:func:`rigctl.firmware.build_id`), what a Mega
    flashed by ``rigctl firmware --flash`` reports in BUILD_ID_0 .. _2 (spec 2.2); None when the installed package
    holds no firmware sources. Hashed once per process (~30 ms): the virtual board is "flashed" when first made."""
    try:
        return firmware.build_id()
    except OSError:
        return None


class MegaController(HomeAndDirection, EmulatedEeprom):
    """The drum controller's registers, commands and control loop on a :class:`RigModel` (no port, no thread).

    Parameters
    ----------
    model : RigModel
        The physics it drives.
    eeprom_path : path or None
        JSON file emulating the EEPROM (calibration registers); None keeps it in memory.
    factory_calibrated : bool
        Write the calibration record (the defaults: the model's true scale) at the first start of an erased EEPROM,
        as the simulated rigs do; False keeps a freshly flashed board's erased EEPROM (a corrupt record stays).

    Attributes
    ----------
    requests : int
        Valid requests addressed to device 1 so far (:meth:`note_request`).
    write_requests : int
        Write requests that reached the register map, accepted or refused (for tests: "nothing was sent").
    writes : deque of (function_code, address, values)
        The last 1000 of them.
    build_id : str or None
        The build id it reports (BUILD_ID_0 .. _2, spec 2.2): the installed sources', as if flashed by rigctl
        (:func:`installed_build_id`). Set another (12 hex digits) for a board flashed from other sources, None for a
        build without one (a plain make, the Arduino IDE); ValueError for anything else.
    """

    def __init__(self, model: RigModel, *, eeprom_path=None, factory_calibrated: bool = False):
        self.model, self._now = model, time.monotonic  # the watchdog's clock, s (VirtualMega.use_clock)
        self.eeprom_path = Path(eeprom_path) if eeprom_path else None
        self._lock = threading.RLock()
        #: the emulated EEPROM: the calibration record (None = erased) and the boot counter
        self.eeprom: dict = {"calibration": None, "boot_count": 0xFFFF}
        self._read_eeprom_file()
        self.requests = 0
        self.write_requests = 0
        self.writes: collections.deque[tuple[int, int, list[int]]] = collections.deque(maxlen=1000)
        self._t_s = 0.0
        self._loadcell_ok = True  # fault-injection hook: False = the HX711 stops answering
        self._loadcell_silent_ms = 0
        self._warm_boots: int = 0  # warm resets since the last cold boot (BOOT_COUNT's low byte: RAM, spec 2.7)
        self._home_switch_ok = True  # fault-injection hook: False = the home switch never closes (a broken wire)
        self._hx_sck_broken = False  # fault-injection hook: SCK never clocks, DOUT held low, every read 0
        self.estop_open = False  # the e-stop input reads open (a pressed contact, a broken wire)
        self.max_step_ms = 10
        self._drive = (model.config.drum.true_steps_per_mm, model.config.mechanics.actuator_max_speed_mm_s)  # (step)
        self.build_id = installed_build_id()
        # compile the model's kernels now, not in the first control period
        model.advance(1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
        self._power_up(ResetCause.POWER_ON)
        self._boot()
        if factory_calibrated and self.eeprom["calibration"] is None:
            self._save_eeprom()  # the first start of an erased EEPROM: the record written, taken as valid from now

    @property
    def build_id(self) -> str | None:
        return wire.build_id_from_words(self._build_id_words)

    @build_id.setter
    def build_id(self, value: str | None) -> None:
        self._build_id_words = wire.build_id_words(value)

    def _power_up(self, cause: ResetCause) -> None:
        """What the MCU does from its reset vector to loop(): calibration from EEPROM (or the defaults, flagged), the
        boot counter counted (EEPROM at a cold boot, RAM at a warm reset), NOT_HOMED with the drivers disabled; the
        step count's zero is where the actuator stands; the load cell is tared only if the home switch is closed; the
        HX711's rate is timed again from the next conversions."""
        model = self.model
        self.holding = {a: wire.holding_range(a)[2] for a in range(wire.N_HOLDING)}  # reserved addresses: 0
        calib = self._valid_calibration()
        self.calibration_defaults = calib is None
        #: the tare's raw zero stored with the calibration (spec 2.11: HOME's sign-free direction check), or None
        self._zero_raw: int | None = None
        if calib is not None:
            self._set_scale(self.holding, calib["scale_x100"])
            self.holding[HR.ACTUATOR_STEPS_PER_MM] = calib["actuator_steps_per_mm"]
            self._zero_raw = calib.get("zero_raw")
        if cold := bool(ResetCause(cause) & wire.COLD_RESETS):  # BOOT_COUNT: EEPROM at a cold boot only (spec 2.7)
            self.eeprom["boot_count"] = (self.eeprom["boot_count"] + 1) & 0xFFFF
            self._write_eeprom_file()
        self._warm_boots = 0 if cold else self._warm_boots + 1  # RAM, which survives a warm reset
        self.reset_cause = ResetCause(cause)
        self.state = DrumState.NOT_HOMED
        self.faults = Fault(0)
        self.homed, self.tared = False, False
        self._tare_pending, self._tare_raw = True, 0  # taken at the first reading, only with the home switch closed
        self._steps_true_mm = 0.0  # the actuator's step count (in true mm of its lead screw): 0 wherever it stands
        self._last_request = self._now()
        self._heartbeat_ms, self._run_t0, self._integ = 0, 0.0, 0.0
        self._pi_out = 0.0  # actuator velocity the force loop set at the last reading, mm/s
        self._on_target_ms = 0
        self._retracting = False  # actuator backing off to home (STOP, fault)
        self._homing, self._home_travel_mm, self._home_ms = False, 0.0, 0
        self._home_phase = 0  # the firmware's HOME_SEEK, HOME_LEAVE, HOME_RETURN
        self._home_phase_mm = 0.0  # commanded travel in this phase (the step count), + towards the sensor
        self._home_leave_mm = 0.0
        self._move_ref_raw: int | None = None  # lowest untared reading since HOME or a back-off began (no zero known)
        self._move_d_min: float | None = None  # the lowest |raw - zero| since HOME or a back-off began, g (spec 2.11)
        self._home_d_start: float | None = None  # |raw - zero| when HOME began, g
        self._home_creep = False  # HOME from an unknown position creeps until the force proves the way (2.11)
        self._move_skip = 0  # readings a back-off skips (the firmware's move_skip: the HX711's settling)
        self._press_dir_hist: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=wire.PRESS_DIR_READINGS + wire.PRESS_DIR_LAG_READINGS + 1)  # (steps, force_g) per reading
        self._press_dir_age: int | None = None  # readings since the force loop's own motion proved the way (2.11)
        self._press_dir_held = False  # proven by the probe's step or since it was done, nothing against it since
        self._press_dir_leave = False  # the press left the closed home switch homed and has not reached the contact
        # the reading's plausibility (spec 2.11): the last raw value, how many in a row, line codes in a row
        self._prev_raw: int | None = None
        self._same_raw = 0
        self._line_codes = 0
        self._hung_ms: int | None = None
        self._last_raw = model.loadcell_raw  # the raw value of the last reading taken (the HX711's latest at boot)
        self._speed_target = 0.0  # mm/s
        self._outputs = (0.0, 0.0)  # drum step rate (microsteps/s), actuator velocity (mm/s)
        self.drivers_enabled = False
        self._force_g, self._echo = 0.0, 0
        # HX711 rate timed at boot (spec 2.9), as the firmware's ctl_hx711_ready
        self._hx_seen = model.hx711_conversions
        self._hx_edges = 0
        self._hx_last_s = 0.0
        self._hx_sum_s = 0.0
        self._hx_rate_sps = 0.0  # 0 until measured
        self._hx_period_s = 0.0
        # drum index (spec 2.6): the step count the firmware keeps, and the index sensor on the real drum
        self._index = DrumIndex(model.config.drum)
        self._probe, self._predicted_g = ContactProbe(), 0.0  # spec 2.10
        if self.estop_open:
            self._estop()
        if self._home_switch():  # the first HX711 reading (12.5 ms after boot on the firmware)
            self._tare()
        self._update_force()

    def _boot(self) -> None:
        """Run the board's boot at rest until the HX711's rate is timed (the first 6 DOUT-ready edges: 75 ms at
        80 SPS, 600 ms at 10 SPS of simulated time), as the firmware does before a host can reach it."""
        while self._hx_edges <= wire.HX711_RATE_PERIODS + 1:
            self.step(self.model.ms_to_next_conversion())

    def reset(self, cause: ResetCause | int = ResetCause.EXTERNAL) -> None:
        """Reset the MCU (``cause``: the MCUSR bits it would see, e.g. EXTERNAL for the reset button, BROWN_OUT,
        WATCHDOG): the physics (the actuator where it stands, a load on the cell) is untouched."""
        with self._lock:
            self._power_up(ResetCause(cause))
        log.warning("virtual Mega reset (%s)", ResetCause(cause))

    # ------------------------------------------------------------------ the load-cell scale (32-bit, signed)
    @property
    def scale_x100(self) -> int:
        """The load-cell scale, counts per g x 100 (signed)."""
        return wire.join_s32(self.holding[HR.LOADCELL_SCALE_X100_HI], self.holding[HR.LOADCELL_SCALE_X100_LO])

    @staticmethod
    def _set_scale(holding: dict, value: int) -> None:
        holding[HR.LOADCELL_SCALE_X100_HI], holding[HR.LOADCELL_SCALE_X100_LO] = wire.split_s32(value)
        holding[HR.LOADCELL_SCALE_X100] = value if 1 <= value <= 0xFFFF else 0

    @staticmethod
    def _scale_ok(value: int) -> bool:
        lo, hi = wire.LOADCELL_SCALE_X100_ABS_RANGE
        return lo <= abs(value) <= hi

    # ------------------------------------------------------------------ requests and the watchdog
    def note_request(self) -> None:
        """A valid request to device 1 arrived: count it and feed the host-silence watchdog."""
        with self._lock:
            self.requests += 1
            self._last_request = self._now()  # any valid request feeds the watchdog

    def read_registers(self, func_code: int, address: int, count: int):
        """Function 03 (holding) / 04 (input): a list of ``count`` raw uint16 values, or a pymodbus ``ExcCodes``."""
        if self._hung_ms is not None:
            return ExcCodes.DEVICE_FAILURE
        return self._read(func_code, address, count)

    def write_registers(self, func_code: int, address: int, values: list[int]):
        """Function 06 / 16: None when applied, or a pymodbus ``ExcCodes`` (nothing changed)."""
        if self._hung_ms is not None:
            return ExcCodes.DEVICE_FAILURE
        return self._write(func_code, address, values)

    def _watchdog_guards(self) -> bool:
        """The host watchdog guards the rig now: not faulted, the drum turns or the force loop holds."""
        turning = abs(self.model.stepper_speed_mm_s) > 0.05 or self._speed_target > 0
        return self.state != DrumState.FAULT and (self.state in _ENGAGED or turning)

    def _watchdog_due(self) -> bool:
        return self._watchdog_guards() and self._now() - self._last_request > self.holding[HR.WATCHDOG_MS] / 1000.0

    def host_silent_for(self, silent_s: float) -> bool:
        """The host watchdog on the caller's clock (in-process injected silence): WATCHDOG after > WATCHDOG_MS."""
        with self._lock:
            if self._watchdog_guards() and silent_s * 1000.0 > self.holding[HR.WATCHDOG_MS]:
                self._fault(Fault.WATCHDOG)
                return True
            return False

    def _actuator_position_mm(self) -> float:
        """Where the controller believes the actuator is, mm: the steps sent (:meth:`step`) over ACTUATOR_STEPS_PER_MM,
        as the firmware counts them; wrong after a miscalibration, a reset away from home, a reversed motor."""
        return self._steps_true_mm * _TRUE_ACTUATOR_STEPS_PER_MM / self.holding[HR.ACTUATOR_STEPS_PER_MM]

    def _actuator_steps(self) -> float:
        """The firmware's step count (ACTUATOR_POSITION in steps): a calibration change does not move it."""
        return self._steps_true_mm * _TRUE_ACTUATOR_STEPS_PER_MM

    def _home_switch(self) -> bool:
        return self._home_switch_ok and self.model.actuator_mm <= 1e-6

    def _status_flags(self) -> int:
        flags = StatusFlag(0)
        for on, flag in ((self.calibration_defaults, StatusFlag.CALIBRATION_DEFAULTS),
                         (self.homed, StatusFlag.HOMED), (self.drivers_enabled, StatusFlag.DRIVERS_ENABLED),
                         (self.estop_open, StatusFlag.ESTOP_OPEN), (self._home_switch(), StatusFlag.HOME_SWITCH),
                         (self.tared, StatusFlag.TARED)):
            if on:
                flags |= flag
        return int(flags)

    def _read(self, func_code: int, address: int, count: int):
        with self._lock:
            if func_code == 6:  # echo of a single-register write (COMMAND itself reads back 0 afterwards)
                return [self._echo]
            if func_code == 3:
                if address < 0 or address + count > wire.N_HOLDING:
                    return ExcCodes.ILLEGAL_ADDRESS
                return [0 if a == HR.COMMAND else self.holding[a] for a in range(address, address + count)]
            if func_code == 4:
                if address < 0 or address + count > wire.N_INPUT:
                    return ExcCodes.ILLEGAL_ADDRESS
                regs = self._input_registers()
                return regs[address: address + count]
            return ExcCodes.ILLEGAL_FUNCTION

    def _input_registers(self) -> list[int]:
        m = self.model
        raw = self._last_raw & 0xFFFFFFFF
        act_mm = self._actuator_position_mm()
        regs = [0] * wire.N_INPUT
        regs[IR.FORCE_G] = _u16(max(-32768, min(32767, self._force_g)))
        d = m.config.drum  # the speed by the step rate, as the firmware knows it (not the real drum's)
        regs[IR.SPEED_0P1MMS] = _u16(m.stepper_speed_mm_s * d.true_steps_per_mm / d.steps_per_mm * 10)
        regs[IR.ACTUATOR_POSITION_0P01MM] = _u16(max(-32768, min(32767, act_mm * 100)))
        regs[IR.STATE] = int(self.state)
        regs[IR.FAULT_BITS] = int(self.faults)
        regs[IR.FIRMWARE_VERSION] = wire.MEGA_FIRMWARE_VERSION[0] * 256 + wire.MEGA_FIRMWARE_VERSION[1]
        regs[IR.HEARTBEAT] = (self._heartbeat_ms // 10) & 0xFFFF
        regs[IR.SPEED_TARGET_0P1MMS] = _u16(self._speed_target * 10)
        regs[IR.LOADCELL_RAW_HI] = raw >> 16
        regs[IR.LOADCELL_RAW_LO] = raw & 0xFFFF
        regs[IR.FORCE_SETPOINT_ACTIVE_G] = self.holding[HR.FORCE_SETPOINT_G] if self.state in _ENGAGED else 0
        regs[IR.HX711_RATE_0P01SPS] = int(round(self._hx_rate_sps * 100))
        self._index.input_registers(regs)
        regs[IR.CONTACT_STIFFNESS_G_PER_MM] = self._probe.stiffness_g_per_mm
        regs[IR.STIFFNESS_MAX_G_PER_MM] = stiffness_max_g_per_mm(self.holding, self._hx_period_s)
        regs[IR.RESET_CAUSE] = int(self.reset_cause)
        regs[IR.BOOT_COUNT] = wire.boot_count_register(self.eeprom["boot_count"], self._warm_boots)
        regs[IR.STATUS_FLAGS] = self._status_flags()
        for reg, word in zip(wire.BUILD_ID_REGISTERS, self._build_id_words, strict=True):
            regs[reg] = word
        return regs

    def _write(self, func_code: int, address: int, values: list[int]):
        with self._lock:
            self.write_requests += 1
            self.writes.append((func_code, address, list(values)))
            if func_code not in (6, 16):
                return ExcCodes.ILLEGAL_FUNCTION
            if address < 0 or address + len(values) > wire.N_HOLDING:
                return ExcCodes.ILLEGAL_ADDRESS
            new = dict(self.holding)
            command = None
            for i, value in enumerate(values):
                reg = address + i
                low, high, _ = wire.holding_range(reg)
                if not low <= value <= high:
                    return ExcCodes.ILLEGAL_VALUE
                if reg == HR.HX711_RATE_SPS and value not in wire.HX711_RATES_SPS:
                    return ExcCodes.ILLEGAL_VALUE
                if reg == HR.COMMAND:
                    command = Command(value)
                else:
                    new[reg] = value
            written = {address + i for i in range(len(values))}
            # the 32-bit scale: HI and LO together, in range; register 12 (its 16-bit view) must agree if written too
            pair = {HR.LOADCELL_SCALE_X100_HI, HR.LOADCELL_SCALE_X100_LO}
            if len(pair & written) == 1:
                return ExcCodes.ILLEGAL_VALUE
            if pair <= written:
                scale = wire.join_s32(new[HR.LOADCELL_SCALE_X100_HI], new[HR.LOADCELL_SCALE_X100_LO])
                if not self._scale_ok(scale) or (HR.LOADCELL_SCALE_X100 in written
                                                 and new[HR.LOADCELL_SCALE_X100] != scale):
                    return ExcCodes.ILLEGAL_VALUE
                self._set_scale(new, scale)
            elif HR.LOADCELL_SCALE_X100 in written:
                if not self._scale_ok(new[HR.LOADCELL_SCALE_X100]):
                    return ExcCodes.ILLEGAL_VALUE
                self._set_scale(new, new[HR.LOADCELL_SCALE_X100])
            for reg in wire.SPEED_REGISTERS:
                if reg in written and new[reg] > new[HR.SPEED_LIMIT_0P1MMS]:
                    return ExcCodes.ILLEGAL_VALUE
            if HR.FORCE_SETPOINT_G in written and new[HR.FORCE_SETPOINT_G] > new[HR.FORCE_LIMIT_G]:
                return ExcCodes.ILLEGAL_VALUE
            if command is not None and not self._command_allowed(command, new):
                return ExcCodes.ILLEGAL_VALUE
            # checked as a whole: apply
            force_changed = new[HR.FORCE_SETPOINT_G] != self.holding[HR.FORCE_SETPOINT_G]
            self.holding = new
            self._echo = values[0] if func_code == 6 else 0
            if force_changed and self.state in (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED):
                self.state = DrumState.SEEKING_FORCE
                self._on_target_ms = 0
            if self._hx_rate_sps and not self._hx711_rate_ok() and Fault.HX711_RATE not in self.faults:
                self._fault(Fault.HX711_RATE)  # a rate the HX711 does not have: the loop must not run
            if command is not None:
                self._execute(command)
            return None

    # ------------------------------------------------------------------ commands
    def _command_allowed(self, cmd: Command, holding) -> bool:
        s = self.state
        unloaded = self._force_g < holding[HR.FORCE_TOLERANCE_G] * 2
        if cmd in (Command.NONE, Command.STOP, Command.SAVE_CALIBRATION):
            return True
        if cmd in (Command.RUN, Command.PRESS):  # never after a reset, e-stop or failed HOME until HOME succeeds
            return s not in (DrumState.FAULT, DrumState.HOMING, DrumState.NOT_HOMED) and \
                self._hx711_rate_ok(holding) and self._probe.ok(holding, self._hx_period_s) and \
                not self.calibration_defaults  # no pressing on a guess (spec 2.11)
        if cmd == Command.STOP_DRUM:
            return s in _ENGAGED
        if cmd == Command.TARE:  # only at home (switch closed), with no load on the cell once a tare is known
            return s in (DrumState.IDLE, DrumState.NOT_HOMED) and self._home_switch() and (not self.tared or unloaded)
        if cmd == Command.HOME:  # from IDLE only released; from NOT_HOMED unless loaded past the limit (spec 2.11)
            if self._home_overloaded(holding):
                return False
            return s == DrumState.NOT_HOMED or (s == DrumState.IDLE and unloaded)
        if cmd == Command.CLEAR_FAULT:
            return ((not self.tared or self._force_g <= holding[HR.FORCE_LIMIT_G]) and self._loadcell_ok
                    and not self.estop_open and not (self._hx_rate_sps and not self._hx711_rate_ok(holding)))
        return False

    def _execute(self, cmd: Command) -> None:
        if cmd == Command.RUN:
            if self.state not in _ENGAGED:
                self._engage()
            self.state = DrumState.RUNNING
            self._run_t0 = self._t_s
        elif cmd == Command.STOP:
            # a latched fault stays until CLEAR_FAULT; the rig is made safe either way
            self._release(DrumState.FAULT if self.state == DrumState.FAULT else self._rest_state())
        elif cmd == Command.TARE:
            self._tare()
        elif cmd == Command.HOME:
            self.state = DrumState.HOMING
            self._homing = True
            self._retracting = False
            self._home_travel_mm = 0.0
            self._home_ms = 0
            self._home_phase = 0
            self._home_creep = not self.homed  # from an unknown position: creep (spec 2.11)
            self._probe.release()
            self._probe.forget()  # (the host's HOME after a plate change too)
            self._move_watch_start(0)
        elif cmd == Command.CLEAR_FAULT:
            self.faults = Fault(0)
            if self.state == DrumState.FAULT:
                self.state = self._rest_state()
        elif cmd == Command.PRESS:
            if self.state not in _ENGAGED:
                self._engage()
        elif cmd == Command.STOP_DRUM:
            self.state = DrumState.SEEKING_FORCE
        elif cmd == Command.SAVE_CALIBRATION:
            self._save_eeprom()

    def _engage(self) -> None:
        self.state = DrumState.SEEKING_FORCE
        self._press_dir_hist.clear()
        self._press_dir_age, self._press_dir_held = None, False
        self._press_dir_leave = self.homed and self._home_switch()  # HOME's switch proof stands until the contact
        self._probe.engage()
        self._integ = 0.0
        self._pi_out = 0.0
        self._on_target_ms = 0
        self._retracting = False
        self._homing = False

    def _rest_state(self) -> DrumState:
        return DrumState.IDLE if self.homed else DrumState.NOT_HOMED

    def _release(self, state: DrumState) -> None:
        """Stop pressing: back off to home if the position is known (homed), else stop where it stands."""
        self.state = state
        self._probe.release()  # the next press probes the contact again (spec 2.11)
        if self.homed and not self._retracting:
            self._move_watch_start(wire.HX711_RATE_PERIODS)
        self._retracting = self.homed
        self._homing = False
        self._integ = 0.0

    def _fault(self, bits: Fault) -> None:
        if self.state in _ENGAGED and not self._press_dir_proven:
            self.homed = False  # a latch while pressing backs off only the way the loop's motion proved (spec 2.11)
        self._press_dir_hist.clear()
        self._press_dir_age, self._press_dir_held, self._press_dir_leave = None, False, False
        self.faults |= bits
        self._probe.forget()  # after any fault the next press locates the contact from scratch (spec 2.11)
        self._release(DrumState.FAULT)
        log.warning("virtual Mega fault: %s", Fault(bits).name or f"0x{int(bits):x}")  # named, not a bare number

    def _estop(self) -> None:
        """The e-stop ISR: drivers disabled and motion stopped at once, ESTOP latched, the position no longer known."""
        self.homed = False
        self._fault(Fault.ESTOP)
        self._outputs = (0.0, 0.0)
        self._speed_target = 0.0
        self.drivers_enabled = False

    def _tare(self) -> None:
        self._tare_raw, self._tare_pending, self.tared = self._last_raw, False, True
        self._update_force()
        self._probe.forget_reading()

    # ------------------------------------------------------------------ control loop
    def _update_force(self) -> None:
        scale = self.scale_x100 / 100.0
        self._force_g = (self._last_raw - self._tare_raw) / scale

    def set_estop(self, opened: bool) -> None:
        """The e-stop input: ``True`` = open (contact pressed, or a broken wire), which trips ESTOP at once (the
        firmware acts in the input's interrupt, not in its control loop); ``False`` = closed again."""
        with self._lock:
            self.estop_open = bool(opened)
            if self.estop_open and Fault.ESTOP not in self.faults:
                self._estop()

    def break_home_switch(self, broken: bool = True) -> None:
        """Fault-injection hook: the home switch never closes (a broken wire); HOME must give up."""
        with self._lock:
            self._home_switch_ok = not broken

    def hang_loop(self) -> None:
        """Test hook: the firmware's ``loop()`` hangs. The outputs keep running as they are (the step ISRs), until
        the AVR watchdog's interrupt stops them after :data:`AVR_WATCHDOG_MS` and its reset follows after as long
        again (:meth:`reset` with WATCHDOG)."""
        with self._lock:
            self._hung_ms = 0

    def break_hx711_sck(self, broken: bool = True) -> None:
        """Fault-injection hook: the HX711's SCK wire is broken (``hx711-sck-broken``): it is never clocked, DOUT
        stays low after its conversion, and every read the firmware makes returns 0, as fast as it polls."""
        with self._lock:
            self._hx_sck_broken = bool(broken)

    def set_loadcell_alive(self, alive: bool) -> None:
        """Fault-injection hook: ``False`` makes the simulated HX711 stop answering (LOADCELL_TIMEOUT after 200 ms)."""
        with self._lock:
            self._loadcell_ok = bool(alive)
            self._loadcell_silent_ms = 0

    def step(self, n_ms: int, *, render: bool = True):
        """Advance the rig by ``n_ms`` ms under the current outputs, then run the controller.

        Returns the model's ``(samples (n, 18) uint16 or None, sync_in (n,) bool)`` for the taxel streamer (samples
        None: not rendered, ``render=False`` of ``RigModel.advance``; ``sync_in``: the index output, from the index
        sensor or the step count, ``DrumIndex.step``). The time is cut into control periods of at most
        :attr:`max_step_ms` ms that end at each HX711 conversion: the force loop acts on a reading in its ms (firmware).
        """
        if n_ms <= 0:
            return self.model.advance(0, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
        m = self.model  # the step pulses per mm at the driver's real setting; the actuator's steps sent, moved or not
        steps_per_mm, vmax = self._drive
        samples, sync = [], []
        left = int(n_ms)
        while left > 0:
            to_conversion, t0, travel0, act0 = m.step_start()
            k = 1 if self._hx_sck_broken else min(left, self.max_step_ms, to_conversion)  # (SCK broken: every ms)
            with self._lock:
                rate, vel = self._outputs
            s, y = m.advance(k, drum_step_rate_hz=rate, actuator_velocity_mm_s=vel, render=render)
            with self._lock:  # the step pulses sent: the stepper's travel at the driver's real setting
                y = self._index.step(y, m.last_stepper_mm, travel0, steps_per_mm, t0, m.last_marks)
                sent = min(max(vel, -vmax), vmax) * k / 1000.0
                act = m.actuator_mm
                if m.actuator_sign > 0 and self._home_switch_ok and act <= 1e-6 and sent < act - act0:
                    # the rear stop is the home switch, where the firmware stops on the step: a k-ms chunk counted
                    # steps past it never sent (a starved clock's long chunks put the count 0.06 mm off)
                    sent = act - act0
                self._steps_true_mm += sent
            self.control_step(k)
            samples.append(s)
            sync.append(y)
            left -= k
        if len(samples) == 1:
            return samples[0], sync[0]
        rendered = [s for s in samples if s is not None]
        return np.concatenate(rendered) if len(rendered) == len(samples) else None, np.concatenate(sync)

    # ------------------------------------------------------------------ HX711 rate and the force loop (spec 2.9)
    def _hx711_rate_ok(self, holding=None) -> bool:
        expected = (holding or self.holding)[HR.HX711_RATE_SPS]
        return bool(self._hx_rate_sps) and abs(self._hx_rate_sps - expected) <= wire.HX711_RATE_TOLERANCE * expected

    def _check_reading(self, raw: int) -> None:
        """A reading that can be lying is a fault (the firmware's ctl_loadcell, spec 2.11): a saturation code, an
        all-zero or all-one word twice in a row (HX711_LINE); HX711_STUCK_READINGS identical raw values in a row."""
        self._same_raw = self._same_raw + 1 if raw == self._prev_raw else 1
        self._prev_raw = raw
        self._line_codes = self._line_codes + 1 if raw in wire.HX711_LINE_CODES else 0
        if (raw in wire.HX711_SATURATION_CODES or self._line_codes >= 2) and Fault.HX711_LINE not in self.faults:
            self._fault(Fault.HX711_LINE)
        if self._same_raw >= wire.HX711_STUCK_READINGS and Fault.HX711_STUCK not in self.faults:
            self._fault(Fault.HX711_STUCK)

    def _hx711_ready(self, t_s: float) -> None:
        """A DOUT-ready edge at ``t_s``: the boot measurement of the rate (the firmware's ctl_hx711_ready: the periods
        are timed from the second edge; the first reading may have waited since before the sketch started); once the
        rate is known, an edge sooner than HX711_CADENCE_PCT % of the period after the last latches HX711_CADENCE."""
        if self._hx_rate_sps and self._hx_period_s > 0 and Fault.HX711_CADENCE not in self.faults and \
                (t_s - self._hx_last_s) * 100.0 < self._hx_period_s * wire.HX711_CADENCE_PCT:
            self._fault(Fault.HX711_CADENCE)
        if 2 <= self._hx_edges <= wire.HX711_RATE_PERIODS + 1:
            self._hx_sum_s += t_s - self._hx_last_s
        self._hx_last_s = t_s
        if self._hx_edges <= wire.HX711_RATE_PERIODS + 1:
            self._hx_edges += 1
        if self._hx_edges == wire.HX711_RATE_PERIODS + 2 and not self._hx_rate_sps and self._hx_sum_s > 0:
            self._hx_period_s = self._hx_sum_s / wire.HX711_RATE_PERIODS
            self._hx_rate_sps = round(100.0 / self._hx_period_s) / 100.0
            if not self._hx711_rate_ok():
                self._fault(Fault.HX711_RATE)

    def _force_pi(self, setpoint_g: float, force_g: float) -> float:
        """One PI update per HX711 reading, as the firmware's force_pi_update (the gains of HX711_RATE_SPS, time
        step the measured period, the integral grows only inside FORCE_PI_INTEGRATE_BAND_G and not while the output
        is clamped in the error's direction); actuator velocity, mm/s."""
        h = self.holding
        slow = h[HR.HX711_RATE_SPS] < 40
        kp = h[HR.FORCE_KP_10SPS_NMS_G if slow else HR.FORCE_KP_80SPS_NMS_G] * 1e-6
        ki = h[HR.FORCE_KI_10SPS_NMS_GS if slow else HR.FORCE_KI_80SPS_NMS_GS] * 1e-6
        out, self._integ = force_pi_update(self._integ, kp, ki, FORCE_LOOP_MAX_SPEED_MM_S, FORCE_PI_INTEGRATE_BAND_G,
                                           setpoint_g, force_g, self._hx_period_s)
        return out

    def _profile_target_mm_s(self) -> float:
        """The drum's surface speed the profile asks for now (CONSTANT or RAMP, within SPEED_LIMIT), mm/s."""
        h = self.holding
        if self.state != DrumState.RUNNING:
            return 0.0
        if h[HR.SPEED_PROFILE] == wire.SpeedProfile.RAMP:
            frac = min(1.0, (self._t_s - self._run_t0) * 1000.0 / h[HR.RAMP_DURATION_MS])
            v0, v1 = h[HR.RAMP_START_SPEED_0P1MMS] / 10.0, h[HR.RAMP_END_SPEED_0P1MMS] / 10.0
            target = v0 + (v1 - v0) * frac
        else:
            target = h[HR.SPEED_SETPOINT_0P1MMS] / 10.0
        return min(target, h[HR.SPEED_LIMIT_0P1MMS] / 10.0)

    def _take_reading(self, n_ms: int) -> bool:
        """The HX711's reading, when a new one is ready (the firmware's ctl_hx711_ready and ctl_loadcell up to the
        force): its timing, its plausibility, the tare at home, the force, the direction watch, the trip's
        prediction. A broken SCK holds DOUT low: the firmware "reads" 0 at every pass of loop(). True when read."""
        m = self.model
        conversions, sck_broken = m.hx711_conversions, self._hx_sck_broken
        new_reading = (conversions != self._hx_seen or sck_broken) and self._loadcell_ok
        if new_reading:
            if sck_broken:
                self._hx711_ready(self._t_s)
            else:
                period = m.config.mechanics.hx711_period_s
                for i in range(min(conversions - self._hx_seen, wire.HX711_RATE_PERIODS + 1), 0, -1):
                    self._hx711_ready(m.hx711_last_conversion_s - (i - 1) * period)
            self._loadcell_silent_ms = 0
            raw = self._last_raw = 0 if sck_broken else m.loadcell_raw
            self._check_reading(raw)
            if self._line_codes == 1:  # one all-zero or all-one word is doubtful, not a force (the firmware's
                self._pi_out = 0.0  # ctl_loadcell): the actuator holds for that period, nothing is judged on it
                self._hx_seen = conversions
                return False
            if self._tare_pending and self._home_switch():
                self._tare()
                if self.state == DrumState.HOMING and not self._homing:  # HOME done: at the switch, tared
                    self.homed = True
                    self.state = DrumState.IDLE
            self._update_force()
            self._watch_direction(raw)
            if self.state in _ENGAGED:
                self._watch_press_direction()
            self._predicted_g = self._probe.predicted_g(self._force_g, self.state in _ENGAGED)
        else:
            self._loadcell_silent_ms += n_ms
        self._hx_seen = conversions
        return new_reading

    def control_step(self, n_ms: int) -> None:
        """One pass of the Mega's control logic after ``n_ms`` ms of physics (reads the model, sets outputs)."""
        if n_ms <= 0:
            return
        dt = n_ms / 1000.0
        m = self.model
        mech = m.config.mechanics
        with self._lock:
            self._t_s += dt
            if self._hung_ms is not None:  # loop() hangs: only the watchdog runs
                self._hung_ms += n_ms
                if self._hung_ms >= 2 * AVR_WATCHDOG_MS:
                    self._power_up(ResetCause.WATCHDOG)
                    log.warning("virtual Mega: loop() hung, the AVR watchdog reset it")
                elif self._hung_ms >= AVR_WATCHDOG_MS:
                    self._outputs = (0.0, 0.0)  # the watchdog interrupt: drivers off, step timers stopped
                    self.drivers_enabled = False
                return
            self._heartbeat_ms += n_ms
            h = self.holding
            new_reading = self._take_reading(n_ms)
            f = self._force_g
            engaged = self.state in _ENGAGED
            # --- faults (the host watchdog: check_watchdog, in the Modbus server's loop)
            if self.tared and max(f, self._predicted_g) > h[HR.FORCE_LIMIT_G] and \
                    not (self.state == DrumState.FAULT and Fault.FORCE_LIMIT in self.faults):
                self._fault(Fault.FORCE_LIMIT)  # latches in any state, also beside another fault (spec 2.5)
            elif self._loadcell_silent_ms >= LOADCELL_TIMEOUT_MS and self.state != DrumState.FAULT:
                self._fault(Fault.LOADCELL_TIMEOUT)
            elif engaged and f < -2 * h[HR.FORCE_TOLERANCE_G]:
                self._fault(Fault.LOADCELL_REVERSED)  # pressing reads negative: a reversed cell (or scale)
            elif engaged and new_reading and self._probe.contact_lost(f, self._actuator_steps(),
                                                                       h[HR.FORCE_TOLERANCE_G]):
                self._stop_unproven(Fault.CONTACT_LOST)  # a held force the position says the contact does not carry
            elif engaged and self._actuator_position_mm() >= mech.actuator_travel_mm - 1e-3 and \
                    f < h[HR.FORCE_SETPOINT_G] - h[HR.FORCE_TOLERANCE_G]:
                self._fault(Fault.ACTUATOR_TRAVEL)
            limit = self._probe.position_limit_steps(h[HR.FORCE_LIMIT_G]) if self.state in _ENGAGED else None
            if limit is not None and self._actuator_steps() > limit:
                self._stop_unproven(Fault.POSITION_LIMIT)  # past the probed contact's limit, whatever the reading
            elif self.state in _ENGAGED and self._home_switch() and self._actuator_position_mm() > wire.HOME_PROOF_MM:
                self._press_dir_leave = False  # at home with the count out: the motor runs back, HOME's proof is void
            if self._index.take_slip() and Fault.DRUM_SLIP not in self.faults:
                self._fault(Fault.DRUM_SLIP)  # the drum's speed marks came late or stopped (spec 2.5)
            if probed := engaged and new_reading and self._probe.active and self.state in _ENGAGED:  # spec 2.10
                self._pi_out, too_stiff = self._probe.reading(f, self._actuator_position_mm(), h, self._hx_period_s,
                                                              FORCE_LOOP_MAX_SPEED_MM_S)
                if too_stiff:
                    self._fault(Fault.CONTACT_STIFFNESS)
                elif not self._probe.active:  # the probe's measuring step(s) raised the settled load: the way proven
                    self._press_dir_held = self._probe.step_rise_g >= wire.PRESS_DIR_G  # for the press (spec 2.11)
            engaged = self.state in _ENGAGED
            self._speed_target = target = self._profile_target_mm_s()
            rate = target * m.config.drum.steps_per_mm
            # --- actuator: force PI loop, back-off or homing
            cal = h[HR.ACTUATOR_STEPS_PER_MM] / _TRUE_ACTUATOR_STEPS_PER_MM  # true mm per commanded mm
            if engaged:
                sp = h[HR.FORCE_SETPOINT_G]
                e = sp - f
                if new_reading and not probed:  # the loop runs once per HX711 reading; its output holds in between
                    self._pi_out = self._force_pi(sp, f)
                if self._probe.step_done(self._actuator_position_mm()):
                    self._pi_out = 0.0
                elif self._pi_out > self._probe.speed_mm_s(self._hx_period_s, FORCE_LOOP_MAX_SPEED_MM_S) and \
                        self._probe.approach_cut(self._actuator_position_mm(), h):
                    self._pi_out = self._probe.speed_mm_s(self._hx_period_s, FORCE_LOOP_MAX_SPEED_MM_S)
                vel = self._pi_out * cal
                if abs(e) <= h[HR.FORCE_TOLERANCE_G] and not self._probe.active:
                    self._on_target_ms += n_ms
                else:
                    self._on_target_ms = 0
                if self.state == DrumState.SEEKING_FORCE and self._on_target_ms >= h[HR.SETTLE_TIME_MS] and \
                        abs(m.stepper_speed_mm_s) < 0.05:
                    self.state = DrumState.FORCE_SETTLED
            elif self._homing:
                vel = self._home_velocity(n_ms, cal)
            elif self._retracting:  # the firmware's ACT_MODE_RETRACT: back to home at the loop's clamp speed
                vel = -FORCE_LOOP_MAX_SPEED_MM_S * cal
                if self._actuator_position_mm() <= 1e-6 or self._home_switch():
                    vel = 0.0
                    self._retracting = False
            else:
                vel = 0.0
            self.drivers_enabled = Fault.ESTOP not in self.faults and not self.estop_open and (
                engaged or self._homing or self._retracting or self.state == DrumState.RUNNING
                or rate != 0.0 or abs(m.stepper_speed_mm_s) > 0.05 or vel != 0.0)
            if not self.drivers_enabled:
                rate, vel = 0.0, 0.0
            self._outputs = (rate, vel)

    # ------------------------------------------------------------------ inspection (tests)
    def snapshot(self) -> dict:
        """State of the controller for tests and logs."""
        with self._lock:
            return {"state": self.state, "faults": self.faults, "force_g": self._force_g,
                    "holding": dict(self.holding), "requests": self.requests, "outputs": self._outputs,
                    "homed": self.homed, "tared": self.tared, "drivers_enabled": self.drivers_enabled}
