"""The model rig's drum controller: the Mega's own ``controller.c``, run on the host, with the glue around it.

The rules (register map and its checks, commands and states, the profiles, the force loop, the probe, HOME, the
direction checks, every fault: docs/wire-protocol.md section 2) are the firmware's ``arduino/mega_drum/controller.c``
with ``force_pi.c`` and ``steprate.c``, built for the host and called through cffi (:mod:`rigctl.simulation.mega_c`):
one source, which the Mega runs and the model rig runs. :class:`MegaController` is only what ``mega_drum.cpp`` is on the
board, on :class:`rigctl.simulation.model.RigModel`'s physics instead of pins and timers:

- ``loop()``'s 1 kHz ticks (``ctl_tick``, with the step count the actuator's step timer made), each HX711 reading
  (``ctl_hx711_ready`` at the conversion's time, ``ctl_loadcell``), the home switch and the e-stop input, and the
  outputs applied (the drum's step timer set by steprate.c, the actuator's velocity, the drivers' EN);
- the step ISRs and the drum's index and speed marks (:class:`rigctl.simulation.drum_index.DrumIndex`);
- the e-stop's interrupt (motion stopped at once, ESTOP latched), the AVR watchdog of a hung ``loop()`` (outputs run on
  until its interrupt stops them after :data:`AVR_WATCHDOG_MS`, the reset as long again);
- ``setup()``: the calibration from the EEPROM (:class:`rigctl.simulation.controller_eeprom.EmulatedEeprom`), the reset
  cause, the boot counter; the build id (BUILD_ID_0 .. _2, settable: :attr:`MegaController.build_id`);
- ``modbus_slave.c``'s address checks before ``ctl_read_holding`` / ``ctl_read_input`` / ``ctl_write_holding``, and
  ``ctl_feed_watchdog`` at every request (:meth:`MegaController.note_request`).

Time: the physics advances in control periods of at most :attr:`MegaController.max_step_ms` ms that end at each HX711
conversion (:meth:`MegaController.step`); at the end of each the controller runs that period's ticks one ms after
another (as ``loop()`` catches up its ticks) and then the reading, and its outputs drive the next period. The
controller's clock restarts at every reset, as the Mega's ``tick_ms`` does.

The host watchdog is controller.c's (``ctl_tick``); whether the host is silent is the link's to say: the glue counts
the host as heard while :meth:`MegaController.host_link` says it is (a request on its way through a loaded machine's
ptys is not silence: :class:`rigctl.simulation.virtual_mega.VirtualMega`'s check; in-process, a clock that only moves
when the host speaks: ``host-silence`` cuts it), and from then on ``ctl_tick`` measures the silence from the last
request handled.

Two boards use it: :class:`rigctl.simulation.virtual_mega.VirtualMega` serves it as a Modbus RTU server on a pty, and
the in-process backend (:mod:`rigctl.simulation.inprocess`) calls :meth:`MegaController.read_registers` /
:meth:`MegaController.write_registers` directly, on a simulated clock.
"""

from __future__ import annotations

import collections
import functools
import logging
import threading
import time
from typing import Any

import numpy as np
from pymodbus.constants import ExcCodes

from rigctl import firmware
from rigctl.devices import wire
from rigctl.devices.wire import DrumState, Fault, HoldingRegister as HR, ResetCause
from rigctl.simulation import mega_c
from rigctl.simulation.controller_eeprom import EmulatedEeprom
from rigctl.simulation.drum_index import DrumIndex
from rigctl.simulation.mega_eeprom import factory_stiffness
from rigctl.simulation.model import RigModel

log = logging.getLogger(__name__)

__all__ = ["MegaController", "AVR_WATCHDOG_MS", "installed_build_id"]

#: actuator calibration the simulated mechanics are built with (ACTUATOR_STEPS_PER_MM default)
_TRUE_ACTUATOR_STEPS_PER_MM = wire.HOLDING_RANGE[HR.ACTUATOR_STEPS_PER_MM][2]
#: the AVR watchdog's timeout (firmware: WDTO_120MS, interrupt first, reset at the second timeout), ms
AVR_WATCHDOG_MS = 120
_ESTOP = int(Fault.ESTOP)
_BOOT_READINGS = wire.HX711_RATE_PERIODS + 1  # ctl_t.hx_edges past this: the rate is timed
_BOOT_MAX_MS = 2000  # a boot whose HX711 never answers stops waiting for its rate after this


@functools.cache
def installed_build_id() -> str | None:
    """The build id rigctl's firmware build gives the installed sources (:func:`rigctl.firmware.build_id`), what a Mega
    flashed by ``rigctl firmware --flash`` reports in BUILD_ID_0 .. _2 (spec 2.2); None when the installed package
    holds no firmware sources. Hashed once per process (~30 ms): the virtual board is "flashed" when first made."""
    try:
        return firmware.build_id()
    except OSError:
        return None


class MegaController:
    """The drum controller (controller.c through cffi) and ``mega_drum.cpp``'s glue on a :class:`RigModel`.

    Parameters
    ----------
    model : RigModel
        The physics it drives.
    eeprom_path : path or None
        JSON file emulating the EEPROM (calibration record, boot counter); None keeps it in memory.
    factory_calibrated : bool
        Write the calibration record (the defaults: the model's true scale) at the first start of an erased EEPROM,
        as the simulated rigs do; False keeps a freshly flashed board's erased EEPROM (a corrupt record stays).
    library : ``(ffi, lib)`` or None
        The controller's C build to run (:func:`rigctl.simulation.mega_c.open_library`: another build of the sources,
        for a test); None: the installed sources' (:func:`rigctl.simulation.mega_c.load`).

    Attributes
    ----------
    requests : int
        Valid requests addressed to device 1 so far (:meth:`note_request`).
    write_requests : int
        Write requests that reached the register map, accepted or refused (for tests: "nothing was sent").
    writes : deque of (function_code, address, values)
        The last 1000 of them.
    eeprom : EmulatedEeprom
    estop_open : bool
        The e-stop input reads open (:meth:`set_estop`).
    max_step_ms : int
        The longest control period, ms.
    build_id : str or None
        The build id it reports (BUILD_ID_0 .. _2, spec 2.2): the installed sources', as if flashed by rigctl
        (:func:`installed_build_id`). Set another (12 hex digits) for a board flashed from other sources, None for a
        build without one (a plain make, the Arduino IDE); ValueError for anything else.

    Raises
    ------
    rigctl.simulation.mega_c.HostBuildError
        controller.c cannot be built for the host (no C compiler).
    """

    def __init__(self, model: RigModel, *, eeprom_path=None, factory_calibrated: bool = False,
                 library: tuple[Any, Any] | None = None):
        self._ffi, self._lib = library or mega_c.load()
        self._c: Any = self._ffi.new("ctl_t *")
        self._values = self._ffi.new("uint16_t[]", 128)  # a write's values for ctl_write_holding
        self.model, self._now = model, time.monotonic  # the watchdog's clock, s (VirtualMega.use_clock)
        self._lock = threading.RLock()
        self.eeprom = EmulatedEeprom(eeprom_path)
        self.requests = 0
        self.write_requests = 0
        self.writes: collections.deque[tuple[int, int, list[int]]] = collections.deque(maxlen=1000)
        self._loadcell_ok = True  # fault-injection hook: False = the HX711 stops answering
        self._warm_boots: int = 0  # warm resets since the last cold boot (BOOT_COUNT's low byte: RAM, spec 2.7)
        self._warm_away = False  # the warm-boot record's flag (RAM, spec 2.7): the controller's `away` at a reset
        self._home_switch_ok = True  # fault-injection hook: False = the home switch never closes (a broken wire)
        self._hx_sck_broken = False  # fault-injection hook: SCK never clocks, DOUT held low, every read 0
        self._host_heard = True  # the link says the host is not silent (host_link)
        self._last_request = self._now()
        self.estop_open = False
        self.max_step_ms = 10
        self._drive = (model.config.drum.true_steps_per_mm, model.config.mechanics.actuator_max_speed_mm_s)
        self.build_id = installed_build_id()
        # compile the model's kernels now, not in the first control period
        model.advance(1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
        self._power_up(ResetCause.POWER_ON)
        self._boot()
        if factory_calibrated and self.eeprom.data["calibration"] is None:
            # the first start of an erased EEPROM: the record written, valid from now, with the rig's own plate's
            # stiffness (spec 2.12: measured when the scale was verified with a reference mass)
            m = model.config.mechanics
            self._c.hreg[HR.CALIBRATION_STIFFNESS_G_PER_MM] = factory_stiffness(m.contact_stiffness_g_per_mm,
                                                                                m.loadcell_counts_per_g)
            self._save_calibration()

    @property
    def build_id(self) -> str | None:
        return wire.build_id_from_words(self._build_id_words)

    @build_id.setter
    def build_id(self, value: str | None) -> None:
        self._build_id_words = wire.build_id_words(value)

    # ------------------------------------------------------------------ setup() and the resets
    def _power_up(self, cause: ResetCause) -> None:
        """From the reset vector to loop() (``early_init``, ``setup``): the calibration from the EEPROM (``calib_load``;
        none: the defaults, flagged), the boot counter (EEPROM at a cold boot, RAM at a warm reset), ``ctl_init``; the
        step count's zero where the actuator stands, the drivers off, the e-stop input read once."""
        c, lib = self._c, self._lib
        rec = self.eeprom.valid_calibration()
        cold = bool(ResetCause(cause) & wire.COLD_RESETS)
        if cold:
            self.eeprom.count_cold_boot()
        self._warm_boots = 0 if cold else self._warm_boots + 1
        lib.ctl_init(c, int(rec["scale_x100"]) if rec else 0, int(rec["actuator_steps_per_mm"]) if rec else 0)
        zero = rec.get("zero_raw") if rec else None
        c.hreg[HR.CALIBRATION_STIFFNESS_G_PER_MM] = int(rec.get("stiffness_g_per_mm", 0)) if rec else 0  # spec 2.12
        c.calib_defaults = rec is None
        c.zero_raw = int(zero) if zero is not None else 0
        c.zero_valid = zero is not None
        c.reset_cause = int(cause)
        c.boot_count = wire.boot_count_register(self.eeprom.boot_count, self._warm_boots)
        # the reset latch (spec 2.7, issue 76): the warm-boot record (RAM: kept by a warm reset) and the EEPROM's
        # safety record, as mega_drum.cpp's setup() hands them to ctl_boot
        safety = self.eeprom.safety
        lib.ctl_boot(c, not cold, not cold and self._warm_away, int(safety["reset_held"]), int(safety["ratchet_g"]))
        self._warm_away = bool(c.away)
        self._ms = 0  # the controller's tick_ms: 0 at every reset
        self._steps_true_mm = 0.0  # the actuator's step count (in true mm of its lead screw): 0 wherever it stands
        self._pos_steps = 0
        self._hx_seen = self.model.hx711_conversions
        self._hung_ms: int | None = None
        self._motion_inhibit = False  # the e-stop or the watchdog's interrupt stopped the step timers
        self._estop_latched = False
        self._outputs = (0.0, 0.0)  # drum step rate (microsteps/s), actuator velocity (true mm/s)
        self._index = DrumIndex(self.model.config.drum)
        self._echo = 0
        self._logged_faults = 0
        self._last_request_ms = 0
        c.home_switch = self._home_switch()
        c.estop_open = self.estop_open
        if self.estop_open:  # an input already open at boot latches at once (loop()'s first pass: ctl_estop)
            self._estop_isr()
            self._lib.ctl_estop(c)

    def _boot(self) -> None:
        """Run the board's boot at rest until the HX711's rate is timed (the first 6 DOUT-ready edges: 75 ms at
        80 SPS, 600 ms at 10 SPS of simulated time), as the firmware does before a host can reach it."""
        while self._c.hx_edges <= _BOOT_READINGS and self._ms < _BOOT_MAX_MS:
            self.step(self.model.ms_to_next_conversion())

    def reset(self, cause: ResetCause | int = ResetCause.EXTERNAL) -> None:
        """Reset the MCU (``cause``: the MCUSR bits it would see, e.g. EXTERNAL for the reset button, BROWN_OUT,
        WATCHDOG): the physics (the actuator where it stands, a load on the cell) is untouched."""
        with self._lock:
            self._power_up(ResetCause(cause))
        log.warning("virtual Mega reset (%s)", ResetCause(cause))

    # ------------------------------------------------------------------ what the controller says (tests, logs)
    @property
    def state(self) -> DrumState:
        return DrumState(self._c.state)

    @property
    def faults(self) -> Fault:
        return Fault(self._c.faults)

    @property
    def homed(self) -> bool:
        return bool(self._c.homed)

    @property
    def tared(self) -> bool:
        return bool(self._c.tared)

    @property
    def calibration_defaults(self) -> bool:
        return bool(self._c.calib_defaults)

    @property
    def drivers_enabled(self) -> bool:
        """The drivers' EN line as the glue reads it back on its pin (STATUS_FLAGS' DRIVERS_ENABLED): active while the
        glue drives it so, or while it is stuck active (``driver-enable-stuck``), whatever the controller asked."""
        return bool(self._c.drivers_on)

    @property
    def holding(self) -> dict[int, int]:
        """The holding registers now, address -> value."""
        with self._lock:
            return {a: int(self._c.hreg[a]) for a in range(wire.N_HOLDING)}

    def holding_register(self, reg: int) -> int:
        """One holding register now (without the dict :attr:`holding` builds)."""
        return int(self._c.hreg[reg])

    def set_holding_register(self, reg: int, value: int) -> None:
        """Write one holding register as a host's write would (checked by controller.c, not counted as a request);
        ValueError when the controller refuses it."""
        ex = self._apply_write(6, int(reg), [int(value)])
        if ex is not None:
            raise ValueError(f"the controller refuses {HR(reg).name} = {value} (exception {int(ex)})")

    @property
    def scale_x100(self) -> int:
        """The load-cell scale, counts per g x 100 (signed)."""
        return int(self._lib.ctl_scale_x100(self._c))

    @property
    def speed_target_mm_s(self) -> float:
        """The drum's profile target now (SPEED_TARGET), mm/s."""
        return self._c.speed_target_0p1 / 10.0

    def actuator_position_mm(self) -> float:
        """Where the controller believes the actuator is (ACTUATOR_POSITION), mm: its step count over
        ACTUATOR_STEPS_PER_MM; wrong after a miscalibration, a reset away from home, a reversed motor."""
        return self._c.act_pos_steps / self._c.hreg[HR.ACTUATOR_STEPS_PER_MM]

    @property
    def force_g(self) -> float:
        """The force the controller read last, g."""
        return float(self._c.force_gf)

    def snapshot(self) -> dict:
        """State of the controller for tests and logs."""
        with self._lock:
            return {"state": self.state, "faults": self.faults, "force_g": self.force_g, "holding": self.holding,
                    "requests": self.requests, "outputs": self._outputs, "homed": self.homed, "tared": self.tared,
                    "drivers_enabled": self.drivers_enabled}

    # ------------------------------------------------------------------ requests and the watchdog
    def note_request(self) -> None:
        """A valid request to device 1 arrived: count it and feed the host watchdog (``ctl_feed_watchdog``)."""
        with self._lock:
            self.requests += 1
            self._last_request = self._now()
            self._lib.ctl_feed_watchdog(self._c)
            self._last_request_ms = self._ms
            self._host_heard = True

    def host_link(self, heard: bool) -> None:
        """Whether the host counts as heard between its requests (True) or silent since its last one (False: the
        link judged it silent, or is cut); controller.c's watchdog measures the silence from that request."""
        with self._lock:
            self._host_heard = bool(heard)
            if not heard:
                self._c.last_request_ms = self._last_request_ms

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

    def _read(self, func_code: int, address: int, count: int):
        """``modbus_slave.c``'s read: the span checked, then ``ctl_read_holding`` / ``ctl_read_input``."""
        with self._lock:
            c, lib = self._c, self._lib
            if func_code == 6:  # echo of a single-register write (COMMAND itself reads back 0 afterwards)
                return [self._echo]
            if func_code == 3:
                if address < 0 or address + count > wire.N_HOLDING:
                    return ExcCodes.ILLEGAL_ADDRESS
                return [lib.ctl_read_holding(c, a) for a in range(address, address + count)]
            if func_code == 4:
                if address < 0 or address + count > wire.N_INPUT:
                    return ExcCodes.ILLEGAL_ADDRESS
                self._index_to_controller()
                regs = [lib.ctl_read_input(c, a) for a in range(address, address + count)]
                for reg, word in zip(wire.BUILD_ID_REGISTERS, self._build_id_words, strict=True):
                    if address <= reg < address + count:
                        regs[reg - address] = word
                return regs
            return ExcCodes.ILLEGAL_FUNCTION

    def _write(self, func_code: int, address: int, values: list[int]):
        """``modbus_slave.c``'s write: the span checked, then ``ctl_write_holding`` (every value checked against the
        range, limits and the command table before any is applied)."""
        with self._lock:
            self.write_requests += 1
            self.writes.append((func_code, address, list(values)))
            return self._apply_write(func_code, address, values)

    def _apply_write(self, func_code: int, address: int, values: list[int]):
        with self._lock:
            if func_code not in (6, 16):
                return ExcCodes.ILLEGAL_FUNCTION
            n = len(values)
            if address < 0 or n < 1 or address + n > wire.N_HOLDING:
                return ExcCodes.ILLEGAL_ADDRESS
            for i, v in enumerate(values):
                self._values[i] = int(v) & 0xFFFF
            ex = self._lib.ctl_write_holding(self._c, address, n, self._values)
            if ex:
                return ExcCodes(ex)
            self._echo = values[0] if func_code == 6 else 0
            self._after_controller()
            self._apply_outputs()  # loop() applies them within the ms (before the next step the timers make)
            return None

    # ------------------------------------------------------------------ inputs, hooks of the fault injection
    def _home_switch(self) -> bool:
        return self._home_switch_ok and self.model.actuator_mm <= 1e-6

    def _estop_isr(self) -> None:
        """INT4: ``motion_kill`` (drivers off, both step timers stopped) and the latch ``loop()`` hands to ctl_estop."""
        self._motion_inhibit = True
        self._estop_latched = True
        self._outputs = (0.0, 0.0)
        self._c.drivers_on = 0

    def set_estop(self, opened: bool) -> None:
        """The e-stop input: ``True`` = open (contact pressed, or a broken wire): its interrupt stops the motion at once
        and the controller latches ESTOP (``ctl_estop``); ``False`` = closed again (CLEAR_FAULT re-arms it)."""
        with self._lock:
            self.estop_open = bool(opened)
            c = self._c
            c.estop_open = self.estop_open
            if self.estop_open:
                self._estop_isr()
                if not (c.faults & _ESTOP) and not c.estop_release:
                    self._lib.ctl_estop(c)
                    self._after_controller()

    def break_home_switch(self, broken: bool = True) -> None:
        """Fault-injection hook: the home switch never closes (a broken wire); HOME must give up."""
        with self._lock:
            self._home_switch_ok = not broken

    def hang_loop(self) -> None:
        """Test hook: the firmware's ``loop()`` hangs. The outputs keep running as they are (the step ISRs), until
        the AVR watchdog's interrupt stops them after :data:`AVR_WATCHDOG_MS` and its reset follows after as long
        again (:meth:`reset` with WATCHDOG). Requests meanwhile get exception 04 (the firmware would not answer)."""
        with self._lock:
            self._hung_ms = 0

    def break_hx711_sck(self, broken: bool = True) -> None:
        """Fault-injection hook: the HX711's SCK wire is broken (``hx711-sck-broken``): it is never clocked, DOUT
        stays low after its conversion, and every read the firmware makes returns 0, as fast as it polls."""
        with self._lock:
            self._hx_sck_broken = bool(broken)

    def set_loadcell_alive(self, alive: bool) -> None:
        """Fault-injection hook: ``False`` makes the simulated HX711 stop answering (DOUT stays high)."""
        with self._lock:
            self._loadcell_ok = bool(alive)

    def corrupt_eeprom(self) -> None:
        """Fault-injection hook: flip a bit of the stored calibration (its checksum fails at the next boot)."""
        with self._lock:
            self.eeprom.corrupt(int(self._c.hreg[HR.ACTUATOR_STEPS_PER_MM]))

    # ------------------------------------------------------------------ the clock
    def step(self, n_ms: int, *, render: bool = True):
        """Advance the rig by ``n_ms`` ms under the current outputs, the controller running after each control period.

        Returns the model's ``(samples (n, 18) uint16 or None, sync_in (n,) bool)`` for the taxel streamer (samples
        None: not rendered, ``render=False`` of ``RigModel.advance``; ``sync_in``: the index output, from the index
        sensor or the step count, ``DrumIndex.step``). The time is cut into control periods of at most
        :attr:`max_step_ms` ms that end at each HX711 conversion (:meth:`control_period` after each)."""
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
            self.control_period(k)
            samples.append(s)
            sync.append(y)
            left -= k
        if len(samples) == 1:
            return samples[0], sync[0]
        rendered = [s for s in samples if s is not None]
        return np.concatenate(rendered) if len(rendered) == len(samples) else None, np.concatenate(sync)

    def control_period(self, n_ms: int) -> None:
        """``loop()`` after ``n_ms`` ms of physics: the inputs read, that many ticks (``ctl_tick``), the HX711's
        reading if one is ready (``ctl_hx711_ready``, ``ctl_loadcell``), the outputs applied."""
        if n_ms <= 0:
            return
        c, lib, m = self._c, self._lib, self.model
        with self._lock:
            if self._hung_ms is not None:  # loop() hangs: only the ISRs and the watchdog run
                self._hung_ms += n_ms
                if self._hung_ms >= 2 * AVR_WATCHDOG_MS:
                    self._power_up(ResetCause.WATCHDOG)
                    log.warning("virtual Mega: loop() hung, the AVR watchdog reset it")
                elif self._hung_ms >= AVR_WATCHDOG_MS:  # its interrupt: drivers off, step timers stopped
                    self._motion_inhibit = True
                    self._outputs = (0.0, 0.0)
                    c.drivers_on = 0
                return
            c.home_switch = self._home_switch()
            c.estop_open = self.estop_open
            if self._index.take_slip():
                c.drum_slip = 1  # index_to_controller: the speed marks came late or stopped
            if self._estop_latched and not (c.faults & _ESTOP) and not c.estop_release:
                lib.ctl_estop(c)
            first = self._ms + 1
            if self._host_heard:
                c.last_request_ms = self._ms & 0xFFFFFFFF  # (before the first tick: never ahead of now_ms)
            pos0, pos1 = self._pos_steps, int(round(self._steps_true_mm * _TRUE_ACTUATOR_STEPS_PER_MM))
            done = 0
            while done < n_ms:
                ran = lib.mega_host_ticks(c, (first + done) & 0xFFFFFFFF, n_ms - done, pos0, pos1)
                done += ran
                pos0 = c.act_pos_steps
                if c.zero_position:  # home found: the step count zeroed, the actuator's timer stopped
                    self._steps_true_mm = 0.0
                    pos0 = pos1 = 0
                    c.act_pos_steps = 0
                    c.zero_position = 0
                if c.estop_release:  # CLEAR_FAULT with the input closed again: motion allowed again
                    self._estop_latched = False
                    self._motion_inhibit = False
                    c.estop_release = 0
            self._pos_steps = pos1
            self._ms += n_ms
            conversions = m.hx711_conversions
            if self._loadcell_ok and (self._hx_sck_broken or conversions != self._hx_seen):
                if self._hx_sck_broken:  # DOUT held low: "ready" at every pass, every read 0
                    t_us, raw = self._ms * 1000, 0
                else:
                    t_us, raw = int(m.hx711_last_conversion_s * 1e6), m.loadcell_raw
                lib.ctl_hx711_ready(c, t_us & 0xFFFFFFFF)
                lib.ctl_loadcell(c, raw)
            self._hx_seen = conversions
            self._after_controller()
            self._apply_outputs()

    def _after_controller(self) -> None:
        """What ``loop()`` does with the controller's requests: the calibration saved; the faults it latched logged."""
        c = self._c
        if c.save_calibration:
            self._save_calibration()
            c.save_calibration = 0
        self._warm_away = bool(c.away)  # warm_record_away: RAM only
        self.eeprom.save_safety(int(c.ee_reset_held), int(c.ee_ratchet_g))  # safety_save: only when it changed
        new = c.faults & ~self._logged_faults
        if new:
            log.warning("virtual Mega fault: %s", Fault(new).name or f"0x{new:x}")  # named, not a bare number
        self._logged_faults = c.faults

    def _save_calibration(self) -> None:
        """``calib_save``: the record with the tare in force (or the zero stored before, if no tare was taken)."""
        c = self._c
        zero = c.tare_offset if c.tared else (c.zero_raw if c.zero_valid else None)
        self.eeprom.save(self.scale_x100, int(c.hreg[HR.ACTUATOR_STEPS_PER_MM]), zero,
                         int(c.hreg[HR.CALIBRATION_STIFFNESS_G_PER_MM]))
        c.zero_raw = zero if zero is not None else 0
        c.zero_valid = zero is not None
        c.calib_defaults = 0

    def _apply_outputs(self) -> None:
        """``drum_apply`` / ``act_apply`` and the drivers' EN: the step rates the timers make (none while the e-stop or
        the watchdog inhibits them), EN on while the controller asks or a step timer runs."""
        c = self._c
        inhibit = self._motion_inhibit
        rate = float(self._lib.mega_host_drum_apply(c, inhibit))
        # the actuator's step rate at the controller's ACTUATOR_STEPS_PER_MM, in true mm/s of its lead screw
        vel = 0.0 if inhibit else c.act_vel_mm_s * c.hreg[HR.ACTUATOR_STEPS_PER_MM] / _TRUE_ACTUATOR_STEPS_PER_MM
        enabled = not inhibit and bool(c.drivers_on or rate > 0.0 or vel != 0.0)
        # STATUS_FLAGS reports the EN line as read back on its pin (mega_drum.cpp: PINH), not the output latch: a line
        # stuck active reads enabled whatever the glue drives (issue 75)
        c.drivers_on = enabled or bool(self.model.driver_enable_stuck)
        self._outputs = (rate, vel) if enabled else (0.0, 0.0)

    def _index_to_controller(self) -> None:
        """``index_to_controller``: the index and speed-mark counts of the ISRs into the controller's inputs."""
        c, ix = self._c, self._index
        usteps = ix.drum.steps_per_rev * ix.drum.microsteps
        c.index_source = 1 if ix.sensor_live else 0  # RIGCTL_INDEX_SOURCE_SENSOR, _STEPS
        steps = ix.steps - ix.steps_at_sensor if ix.sensor_live else ix.steps
        c.drum_step_in_rev = int(steps % usteps) & 0xFFFF
        c.drum_revolutions = ix.revolutions & 0xFFFF
        c.index_period_ms, c.index_steps = ix.period_ms, ix.steps_per_mark
        c.index_count = ix.edges & 0xFFFF
        c.mark_period_0p1ms, c.mark_steps = ix.mark_period_0p1ms, ix.mark_steps
        c.mark_count = ix.marks & 0xFFFF

