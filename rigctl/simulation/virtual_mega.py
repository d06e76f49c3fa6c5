"""The simulated drum controller (Arduino Mega 2560): a Modbus RTU server on a pty with the Mega's control logic.

Implements ``docs/wire-protocol.md`` section 2 from the board's side: every holding and input register, the range
column and the speed/force limits (illegal value -> exception 03, unknown address -> 02, other functions -> 01; a
function-16 write is checked as a whole before any register changes), the commands and states, the CONSTANT and
RAMP speed profiles, a PI force loop on actuator velocity against the load cell, settle detection
(FORCE_TOLERANCE_G for SETTLE_TIME_MS), the force-limit fault (actuator backs off at once), the host-silence
watchdog (any valid request to device 1 feeds it), the 10 ms heartbeat, tare, home, clear fault, and the calibration
registers kept in an emulated EEPROM (in memory, or a JSON file).

The Modbus side is pymodbus' own :class:`pymodbus.server.ModbusSerialServer` (RTU framer, device id 1, 115200 8N1)
on one end of a :class:`rigctl.simulation.pty.PtyBridge`; the client opens :attr:`VirtualMega.path`. The physics is
:class:`rigctl.simulation.model.RigModel` (drum step rate and actuator velocity in, load cell and drum state out);
whoever owns the simulation clock calls :meth:`VirtualMega.step` (the rig's physics thread), or
:meth:`VirtualMega.start` runs its own real-time control loop.

The host-silence watchdog is checked in the Modbus server's own thread (its asyncio loop), as the firmware checks it
in the same main loop that handles frames (``arduino/mega_drum/mega_drum.cpp``: a frame is handled, and feeds the
watchdog, within about a millisecond of its last byte; ``ctl_tick`` never sees a request that has arrived but is not
handled). A Python thread, unlike the Mega, can be starved for hundreds of ms on a loaded machine (GIL, CPU), so
the check also refuses to call the host silent while request bytes wait anywhere between the client's port and the
server (:meth:`rigctl.simulation.pty.PtyBridge.bytes_to_board`): the silence the watchdog measures is the host's,
not the simulator's. (The price under such starvation: a host that really was silent for just over the timeout
and then spoke again before the simulator got to check may go unnoticed.)
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusBaseDeviceContext, ModbusServerContext
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer

from rigctl.devices import wire
from rigctl.devices.wire import Command, DrumState, Fault, HoldingRegister as HR, InputRegister as IR
from rigctl.simulation.model import (
    FORCE_PI_INTEGRATE_BAND_G,
    FORCE_PI_KI_MM_S_PER_G_S,
    FORCE_PI_KP_MM_S_PER_G,
    RigModel,
)
from rigctl.simulation.pty import PtyBridge
from rigctl.simulation.virtual_uno import paced_loop

log = logging.getLogger(__name__)

#: actuator calibration the simulated mechanics are built with (ACTUATOR_STEPS_PER_MM default)
_TRUE_ACTUATOR_STEPS_PER_MM = wire.HOLDING_RANGE[HR.ACTUATOR_STEPS_PER_MM][2]
_ENGAGED = (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING)
_CALIBRATION = (HR.LOADCELL_SCALE_X100, HR.ACTUATOR_STEPS_PER_MM)
LOADCELL_TIMEOUT_MS = 200
#: period of the watchdog check in the Modbus server's loop, s
WATCHDOG_CHECK_S = 0.01


def _u16(x: float) -> int:
    return int(round(x)) & 0xFFFF


class _MegaContext(ModbusBaseDeviceContext):
    """pymodbus device context that hands every register access to the :class:`VirtualMega`."""

    def __init__(self, mega: "VirtualMega"):
        self.mega = mega

    def reset(self):  # pragma: no cover - pymodbus API
        pass

    def getValues(self, func_code, address, count=1):
        return self.mega._read(func_code, address, count)

    def setValues(self, func_code, address, values):
        return self.mega._write(func_code, address, values)


class VirtualMega:
    """Virtual drum controller.

    Parameters
    ----------
    model : RigModel
        The physics it drives (shared with the virtual Uno in :class:`rigctl.simulation.rig.SimulatedRig`).
    link : path or None
        Stable path the client opens (symlink to the pty).
    eeprom_path : path or None
        JSON file emulating the EEPROM (calibration registers); None keeps it in memory.

    Attributes
    ----------
    requests : int
        Valid requests addressed to device 1 so far.
    write_requests : int
        Write requests that reached the register map, accepted or refused (for tests: "nothing was sent").
    writes : deque of (function_code, address, values)
        The last 1000 of them.
    """

    def __init__(self, model: RigModel, link=None, *, eeprom_path=None):
        self.model = model
        self.bridge = PtyBridge(link)
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
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._server_thread: threading.Thread | None = None
        self._clock_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.max_step_ms = 10
        # compile the model's kernels now, not in the first control period
        model.advance(1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
        self._tare_raw = model.loadcell_raw
        self._update_force()

    # ------------------------------------------------------------------ lifecycle
    @property
    def path(self) -> str:
        """The path a Modbus master opens (115200 8N1, RTU, device id 1)."""
        return self.bridge.client_path

    def start(self, *, clock: bool = True, control_period_s: float = 0.005) -> "VirtualMega":
        """Start the Modbus server thread and, with ``clock=True``, a real-time control loop (200 Hz default)."""
        ready = threading.Event()
        errors: list[BaseException] = []

        def serve():
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self._loop = loop

            async def main():
                try:
                    self._server = ModbusSerialServer(
                        ModbusServerContext(devices={wire.DRUM_DEVICE_ID: _MegaContext(self)}, single=False),
                        framer=FramerType.RTU, port=self.bridge.board_path, baudrate=wire.DRUM_BAUD, bytesize=8,
                        parity="N", stopbits=1, ignore_missing_devices=True, trace_pdu=self._trace_pdu,
                    )
                    await self._server.serve_forever(background=True)
                except BaseException as exc:  # reported to start()
                    errors.append(exc)
                    ready.set()
                    return
                watchdog = asyncio.ensure_future(self._watchdog_loop())
                ready.set()
                try:
                    await self._server.serving
                finally:
                    watchdog.cancel()

            loop.run_until_complete(main())
            loop.close()

        self._server_thread = threading.Thread(target=serve, name="virtual-mega-modbus", daemon=True)
        self._server_thread.start()
        ready.wait(5)
        if errors:
            raise RuntimeError(f"virtual Mega's Modbus server failed to start: {errors[0]}") from errors[0]
        if clock:
            self._stop.clear()
            self._clock_thread = threading.Thread(
                target=paced_loop, args=(self._stop, control_period_s, self.step), name="virtual-mega-control",
                daemon=True)
            self._clock_thread.start()
        return self

    def close(self) -> None:
        """Stop the control loop and the server, close the ptys."""
        self._stop.set()
        if self._clock_thread is not None:
            self._clock_thread.join(timeout=2)
            self._clock_thread = None
        if self._server is not None and self._loop is not None:
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout=3)
            except Exception:  # noqa: BLE001 - best effort at shutdown
                log.debug("server shutdown", exc_info=True)
        if self._server_thread is not None:
            self._server_thread.join(timeout=3)
            self._server_thread = None
        self.bridge.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

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

    # ------------------------------------------------------------------ Modbus register map
    def _trace_pdu(self, sending: bool, pdu):
        if not sending and pdu is not None and getattr(pdu, "dev_id", None) == wire.DRUM_DEVICE_ID:
            with self._lock:
                self.requests += 1
                self._last_request = time.monotonic()  # any valid request feeds the watchdog
        return pdu

    async def _watchdog_loop(self) -> None:
        while True:
            await asyncio.sleep(WATCHDOG_CHECK_S)
            try:
                self.check_watchdog()
            except Exception:  # noqa: BLE001 - keep checking; the error is logged
                log.exception("watchdog check failed")

    def _watchdog_due(self) -> bool:
        h = self.holding
        if self.state == DrumState.FAULT:
            return False
        turning = abs(self.model.drum_speed_mm_s) > 0.05 or self._speed_target > 0
        if not (self.state in _ENGAGED or turning):
            return False  # a host that only monitors never trips it
        return time.monotonic() - self._last_request > h[HR.WATCHDOG_MS] / 1000.0

    def check_watchdog(self) -> bool:
        """Trip the host-silence watchdog (spec 2.5) if it is due; returns True if it tripped.

        Called every :data:`WATCHDOG_CHECK_S` from the Modbus server's loop, so a request the server has read is
        always handled (and has fed the watchdog) before the check. Not due while request bytes that the server has
        not read yet are on their way (the host spoke; the firmware would have handled them by now).
        """
        with self._lock:
            if not self._watchdog_due():
                return False
        if self.bridge.bytes_to_board():
            return False
        with self._lock:
            if not self._watchdog_due():
                return False
            self._fault(Fault.WATCHDOG)
            return True

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
        act_mm = m.actuator_mm * _TRUE_ACTUATOR_STEPS_PER_MM / self.holding[HR.ACTUATOR_STEPS_PER_MM]
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
            if f > h[HR.FORCE_LIMIT_G] and self.state != DrumState.FAULT:
                self._fault(Fault.FORCE_LIMIT)
            elif self._loadcell_silent_ms >= LOADCELL_TIMEOUT_MS and self.state != DrumState.FAULT:
                self._fault(Fault.LOADCELL_TIMEOUT)
            elif engaged and m.actuator_mm >= mech.actuator_travel_mm - 1e-3 and \
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
