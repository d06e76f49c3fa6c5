"""The drum controller's logic (Arduino Mega 2560 firmware, ``docs/wire-protocol.md`` section 2), without a port.

:class:`MegaController` holds every holding and input register with its range column and the speed/force limits
(illegal value -> exception 03, unknown address -> 02, other functions -> 01; a function-16 write is checked as a
whole before any register changes), the commands and states, the CONSTANT and RAMP speed profiles, a PI force loop
on actuator velocity against the load cell, settle detection (FORCE_TOLERANCE_G for SETTLE_TIME_MS), the
force-limit fault (actuator backs off at once), the 10 ms heartbeat, tare, home, clear fault, and the calibration
registers kept in an emulated EEPROM (in memory, or a JSON file). The physics is
:class:`rigctl.simulation.model.RigModel` (drum step rate and actuator velocity in, load cell and drum state out);
whoever owns the simulation clock calls :meth:`MegaController.step`.

Two boards use it: :class:`rigctl.simulation.virtual_mega.VirtualMega` serves it as a Modbus RTU server on a pty
(with the host-silence watchdog checked in the server's loop), and the in-process backend
(:mod:`rigctl.simulation.inprocess`) calls :meth:`MegaController.read_registers` / :meth:`write_registers`
directly, on a simulated clock.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
from pymodbus.constants import ExcCodes

from rigctl.devices import wire
from rigctl.devices.wire import Command, DrumState, Fault, HoldingRegister as HR, InputRegister as IR
from rigctl.simulation.model import (
    FORCE_PI_INTEGRATE_BAND_G,
    FORCE_PI_KI_MM_S_PER_G_S,
    FORCE_PI_KP_MM_S_PER_G,
    RigModel,
)

log = logging.getLogger(__name__)

__all__ = ["MegaController", "LOADCELL_TIMEOUT_MS"]

#: actuator calibration the simulated mechanics are built with (ACTUATOR_STEPS_PER_MM default)
_TRUE_ACTUATOR_STEPS_PER_MM = wire.HOLDING_RANGE[HR.ACTUATOR_STEPS_PER_MM][2]
_ENGAGED = (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING)
_CALIBRATION = (HR.LOADCELL_SCALE_X100, HR.ACTUATOR_STEPS_PER_MM)
LOADCELL_TIMEOUT_MS = 200


def _u16(x: float) -> int:
    return int(round(x)) & 0xFFFF


class MegaController:
    """The drum controller's registers, commands and control loop on a :class:`RigModel` (no port, no thread).

    Parameters
    ----------
    model : RigModel
        The physics it drives.
    eeprom_path : path or None
        JSON file emulating the EEPROM (calibration registers); None keeps it in memory.

    Attributes
    ----------
    requests : int
        Valid requests addressed to device 1 so far (:meth:`note_request`).
    write_requests : int
        Write requests that reached the register map, accepted or refused (for tests: "nothing was sent").
    writes : deque of (function_code, address, values)
        The last 1000 of them.
    """

    def __init__(self, model: RigModel, *, eeprom_path=None):
        self.model = model
        self.eeprom_path = Path(eeprom_path) if eeprom_path else None
        self._lock = threading.RLock()
        self.holding = {reg: rng[2] for reg, rng in wire.HOLDING_RANGE.items()}
        self.eeprom = {reg: self.holding[reg] for reg in _CALIBRATION}
        self._load_eeprom()
        self.state = DrumState.IDLE
        self.faults = Fault(0)
        self.requests = 0
        self.write_requests = 0
        self.writes: collections.deque[tuple[int, int, list[int]]] = collections.deque(maxlen=1000)
        self._last_request = time.monotonic()
        self._heartbeat_ms = 0
        self._t_s = 0.0
        self._run_t0 = 0.0
        self._integ = 0.0
        self._on_target_ms = 0
        self._retracting = False  # actuator backing off to home (STOP, fault)
        self._homing = False
        self._loadcell_ok = True  # fault-injection hook: False = the HX711 stops answering
        self._loadcell_silent_ms = 0
        self._speed_target = 0.0  # mm/s
        self._outputs = (0.0, 0.0)  # drum step rate (microsteps/s), actuator velocity (mm/s)
        self._tare_raw = model.loadcell_raw  # the firmware tares at boot (actuator home)
        self._force_g = 0.0
        self._echo = 0
        self.max_step_ms = 10
        # compile the model's kernels now, not in the first control period
        model.advance(1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
        self._tare_raw = model.loadcell_raw
        self._update_force()

    # ------------------------------------------------------------------ EEPROM
    def _load_eeprom(self) -> None:
        if self.eeprom_path and self.eeprom_path.exists():
            data = json.loads(self.eeprom_path.read_text())
            for reg in _CALIBRATION:
                if reg.name in data:
                    self.eeprom[reg] = int(data[reg.name])
        for reg in _CALIBRATION:
            self.holding[reg] = self.eeprom[reg]

    def _save_eeprom(self) -> None:
        for reg in _CALIBRATION:
            self.eeprom[reg] = self.holding[reg]
        if self.eeprom_path:
            self.eeprom_path.write_text(json.dumps({reg.name: self.eeprom[reg] for reg in _CALIBRATION}))

    # ------------------------------------------------------------------ requests and the watchdog
    def note_request(self) -> None:
        """A valid request to device 1 arrived: count it and feed the host-silence watchdog."""
        with self._lock:
            self.requests += 1
            self._last_request = time.monotonic()  # any valid request feeds the watchdog

    def read_registers(self, func_code: int, address: int, count: int):
        """Function 03 (holding) / 04 (input): a list of ``count`` raw uint16 values, or a pymodbus ``ExcCodes``."""
        return self._read(func_code, address, count)

    def write_registers(self, func_code: int, address: int, values: list[int]):
        """Function 06 / 16: None when applied, or a pymodbus ``ExcCodes`` (nothing changed)."""
        return self._write(func_code, address, values)

    def _watchdog_due(self) -> bool:
        h = self.holding
        if self.state == DrumState.FAULT:
            return False
        turning = abs(self.model.drum_speed_mm_s) > 0.05 or self._speed_target > 0
        if not (self.state in _ENGAGED or turning):
            return False  # a host that only monitors never trips it
        return time.monotonic() - self._last_request > h[HR.WATCHDOG_MS] / 1000.0

    def _actuator_position_mm(self) -> float:
        """Where the controller believes the actuator is, mm: its step count over ACTUATOR_STEPS_PER_MM (the
        firmware knows no other position; the true one differs when that calibration is wrong)."""
        return self.model.actuator_mm * _TRUE_ACTUATOR_STEPS_PER_MM / self.holding[HR.ACTUATOR_STEPS_PER_MM]


    def _read(self, func_code: int, address: int, count: int):
        with self._lock:
            if func_code == 6:  # echo of a single-register write (COMMAND itself reads back 0 afterwards)
                return [self._echo]
            if func_code == 3:
                if address < 0 or address + count > wire.N_HOLDING:
                    return ExcCodes.ILLEGAL_ADDRESS
                return [0 if HR(a) == HR.COMMAND else self.holding[HR(a)] for a in range(address, address + count)]
            if func_code == 4:
                if address < 0 or address + count > wire.N_INPUT:
                    return ExcCodes.ILLEGAL_ADDRESS
                regs = self._input_registers()
                return regs[address: address + count]
            return ExcCodes.ILLEGAL_FUNCTION

    def _input_registers(self) -> list[int]:
        m = self.model
        raw = m.loadcell_raw & 0xFFFFFFFF
        act_mm = self._actuator_position_mm()
        regs = [0] * wire.N_INPUT
        regs[IR.FORCE_G] = _u16(max(-32768, min(32767, self._force_g)))
        regs[IR.SPEED_0P1MMS] = _u16(m.drum_speed_mm_s * 10)
        regs[IR.DRUM_ANGLE_0P01DEG] = int(m.angle_deg * 100) % 36000
        regs[IR.DRUM_REVOLUTIONS] = m.revolutions & 0xFFFF
        regs[IR.ACTUATOR_POSITION_0P01MM] = _u16(max(-32768, min(32767, act_mm * 100)))
        regs[IR.STATE] = int(self.state)
        regs[IR.FAULT_BITS] = int(self.faults)
        regs[IR.FIRMWARE_VERSION] = wire.MEGA_FIRMWARE_VERSION[0] * 256 + wire.MEGA_FIRMWARE_VERSION[1]
        regs[IR.HEARTBEAT] = (self._heartbeat_ms // 10) & 0xFFFF
        regs[IR.SPEED_TARGET_0P1MMS] = _u16(self._speed_target * 10)
        regs[IR.LOADCELL_RAW_HI] = raw >> 16
        regs[IR.LOADCELL_RAW_LO] = raw & 0xFFFF
        regs[IR.FORCE_SETPOINT_ACTIVE_G] = self.holding[HR.FORCE_SETPOINT_G] if self.state in _ENGAGED else 0
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
                reg = HR(address + i)
                low, high, _ = wire.HOLDING_RANGE[reg]
                if not low <= value <= high:
                    return ExcCodes.ILLEGAL_VALUE
                if reg == HR.COMMAND:
                    command = Command(value)
                else:
                    new[reg] = value
            written = {HR(address + i) for i in range(len(values))}
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
            if command is not None:
                self._execute(command)
            return None

    # ------------------------------------------------------------------ commands
    def _command_allowed(self, cmd: Command, holding) -> bool:
        s = self.state
        if cmd in (Command.NONE, Command.STOP, Command.SAVE_CALIBRATION):
            return True
        if cmd in (Command.RUN, Command.PRESS):
            return s not in (DrumState.FAULT, DrumState.HOMING)
        if cmd == Command.STOP_DRUM:
            return s in _ENGAGED
        if cmd in (Command.TARE, Command.HOME):
            return s == DrumState.IDLE and self._force_g < holding[HR.FORCE_TOLERANCE_G] * 2
        if cmd == Command.CLEAR_FAULT:
            return self._force_g <= holding[HR.FORCE_LIMIT_G] and self._loadcell_ok
        return False

    def _execute(self, cmd: Command) -> None:
        if cmd == Command.RUN:
            if self.state not in _ENGAGED:
                self._engage()
            self.state = DrumState.RUNNING
            self._run_t0 = self._t_s
        elif cmd == Command.STOP:
            # a latched fault stays until CLEAR_FAULT; the rig is made safe either way
            self._release(DrumState.FAULT if self.state == DrumState.FAULT else DrumState.IDLE)
        elif cmd == Command.TARE:
            self._tare_raw = self.model.loadcell_raw
            self._update_force()
        elif cmd == Command.HOME:
            self.state = DrumState.HOMING
            self._homing = True
            self._retracting = False
        elif cmd == Command.CLEAR_FAULT:
            self.faults = Fault(0)
            if self.state == DrumState.FAULT:
                self.state = DrumState.IDLE
        elif cmd == Command.PRESS:
            if self.state not in _ENGAGED:
                self._engage()
        elif cmd == Command.STOP_DRUM:
            self.state = DrumState.SEEKING_FORCE
        elif cmd == Command.SAVE_CALIBRATION:
            self._save_eeprom()

    def _engage(self) -> None:
        self.state = DrumState.SEEKING_FORCE
        self._integ = 0.0
        self._on_target_ms = 0
        self._retracting = False
        self._homing = False

    def _release(self, state: DrumState) -> None:
        self.state = state
        self._retracting = True
        self._homing = False
        self._integ = 0.0

    def _fault(self, bits: Fault) -> None:
        self.faults |= bits
        self._release(DrumState.FAULT)
        log.warning("virtual Mega fault: %s", bits)

    # ------------------------------------------------------------------ control loop
    def _update_force(self) -> None:
        scale = self.holding[HR.LOADCELL_SCALE_X100] / 100.0
        self._force_g = (self.model.loadcell_raw - self._tare_raw) / scale

    def set_loadcell_alive(self, alive: bool) -> None:
        """Fault-injection hook: ``False`` makes the simulated HX711 stop answering (LOADCELL_TIMEOUT after 200 ms)."""
        with self._lock:
            self._loadcell_ok = bool(alive)
            self._loadcell_silent_ms = 0

    def step(self, n_ms: int):
        """Advance the rig by ``n_ms`` ms under the current outputs, then run the controller.

        Returns the model's ``(samples (n, 18) uint16, sync_in (n,) bool)`` for the taxel streamer. Long steps are
        cut into control periods of at most :attr:`max_step_ms` ms.
        """
        if n_ms <= self.max_step_ms:
            with self._lock:
                rate, vel = self._outputs
            out = self.model.advance(n_ms, drum_step_rate_hz=rate, actuator_velocity_mm_s=vel)
            self.control_step(n_ms)
            return out
        # after a scheduling hiccup: catch up in control periods, as the firmware's loop would have run
        samples, sync = [], []
        left = int(n_ms)
        while left > 0:
            k = min(left, self.max_step_ms)
            s, y = self.step(k)
            samples.append(s)
            sync.append(y)
            left -= k
        return np.concatenate(samples), np.concatenate(sync)

    def control_step(self, n_ms: int) -> None:
        """One pass of the Mega's control logic after ``n_ms`` ms of physics (reads the model, sets outputs)."""
        if n_ms <= 0:
            return
        dt = n_ms / 1000.0
        m = self.model
        mech = m.config.mechanics
        with self._lock:
            self._t_s += dt
            self._heartbeat_ms += n_ms
            h = self.holding
            if self._loadcell_ok:
                self._loadcell_silent_ms = 0
                self._update_force()
            else:
                self._loadcell_silent_ms += n_ms
            f = self._force_g
            engaged = self.state in _ENGAGED
            # --- faults (the host watchdog: check_watchdog, in the Modbus server's loop)
            if f > h[HR.FORCE_LIMIT_G] and not (self.state == DrumState.FAULT and Fault.FORCE_LIMIT in self.faults):
                self._fault(Fault.FORCE_LIMIT)  # latches in any state, also beside another fault (spec 2.5)
            elif self._loadcell_silent_ms >= LOADCELL_TIMEOUT_MS and self.state != DrumState.FAULT:
                self._fault(Fault.LOADCELL_TIMEOUT)
            elif engaged and self._actuator_position_mm() >= mech.actuator_travel_mm - 1e-3 and \
                    f < h[HR.FORCE_SETPOINT_G] - h[HR.FORCE_TOLERANCE_G]:
                self._fault(Fault.ACTUATOR_TRAVEL)
            engaged = self.state in _ENGAGED
            # --- drum speed profile
            limit = h[HR.SPEED_LIMIT_0P1MMS] / 10.0
            if self.state == DrumState.RUNNING:
                if h[HR.SPEED_PROFILE] == wire.SpeedProfile.RAMP:
                    frac = min(1.0, (self._t_s - self._run_t0) * 1000.0 / h[HR.RAMP_DURATION_MS])
                    v0, v1 = h[HR.RAMP_START_SPEED_0P1MMS] / 10.0, h[HR.RAMP_END_SPEED_0P1MMS] / 10.0
                    target = v0 + (v1 - v0) * frac
                else:
                    target = h[HR.SPEED_SETPOINT_0P1MMS] / 10.0
                target = min(target, limit)
            else:
                target = 0.0
            self._speed_target = target
            rate = target * m.config.drum.steps_per_mm
            # --- actuator: force PI loop, back-off or homing
            vmax = mech.actuator_max_speed_mm_s
            cal = h[HR.ACTUATOR_STEPS_PER_MM] / _TRUE_ACTUATOR_STEPS_PER_MM  # true mm per commanded mm
            if engaged:
                sp = h[HR.FORCE_SETPOINT_G]
                e = sp - f
                if abs(e) < FORCE_PI_INTEGRATE_BAND_G:
                    self._integ += e * dt
                vel = float(np.clip(FORCE_PI_KP_MM_S_PER_G * e + FORCE_PI_KI_MM_S_PER_G_S * self._integ, -vmax, vmax))
                vel *= cal
                if abs(e) <= h[HR.FORCE_TOLERANCE_G]:
                    self._on_target_ms += n_ms
                else:
                    self._on_target_ms = 0
                if self.state == DrumState.SEEKING_FORCE and self._on_target_ms >= h[HR.SETTLE_TIME_MS] and \
                        abs(m.drum_speed_mm_s) < 0.05:
                    self.state = DrumState.FORCE_SETTLED
            elif self._retracting or self._homing:
                vel = -vmax
                if m.actuator_mm <= 1e-6:
                    vel = 0.0
                    if self._homing:
                        m.home_actuator()
                        self._homing = False
                        if self.state == DrumState.HOMING:
                            self.state = DrumState.IDLE
                    self._retracting = False
            else:
                vel = 0.0
            self._outputs = (rate, vel)

    # ------------------------------------------------------------------ inspection (tests)
    def snapshot(self) -> dict:
        """State of the controller for tests and logs."""
        with self._lock:
            return {"state": self.state, "faults": self.faults, "force_g": self._force_g,
                    "holding": dict(self.holding), "requests": self.requests, "outputs": self._outputs}
