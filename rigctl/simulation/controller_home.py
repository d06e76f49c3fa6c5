"""HOME and the direction checks of the virtual drum controller (the firmware's home_step and the direction watch in
ctl_loadcell, docs/wire-protocol.md 2.5 and 2.11): :class:`HomeAndDirection`, a part of
:class:`rigctl.simulation.controller.MegaController`.

HOME backs to the switch, leaves it (it must open within HOME_PROOF_MM: the direction is right) and returns; from an
unknown position (not homed) its seek creeps at HOME_CREEP_UM per HX711 period until the load on the cell, |raw -
zero| from the tare (or the zero stored with the calibration), has fallen by HOME_PROOF_FALL_G. Moving home or backing
off only takes force off the cell: that load grown above its lowest since the move began (HOME_RISE_G from an unknown
position, DIRECTION_RISE_G otherwise), or past FORCE_LIMIT_G + 2 x FORCE_TOLERANCE_G while homing from an unknown
position, is ACTUATOR_DIRECTION, sign-free: a reversed motor and a reversed cell alike. While the force loop drives,
the press's direction watch (:meth:`HomeAndDirection._watch_press_direction`) holds the step count against the load
read, and says whether a back-off may take the way this press proved (:attr:`HomeAndDirection._press_dir_proven`).
"""

from __future__ import annotations

import collections
from collections.abc import Mapping

from rigctl.devices import wire
from rigctl.devices.wire import DrumState, Fault, HoldingRegister as HR
from rigctl.simulation.force_loop import ContactProbe
from rigctl.simulation.model import RigModel

__all__ = ["HOME_SPEED_MM_S", "HomeAndDirection"]

#: actuator speed while seeking home, commanded mm/s (firmware: ACT_HOME_SPEED_MM_S; equal by tests/test_wire_spec.py)
HOME_SPEED_MM_S = 3.0


class HomeAndDirection:
    """HOME's phases and the direction checks; the state they use is :class:`MegaController`'s (set at its power-up)."""

    holding: dict[int, int]
    homed: bool
    tared: bool
    state: DrumState
    _tare_raw: int
    _zero_raw: int | None
    _last_raw: int
    _hx_period_s: float
    _homing: bool
    _retracting: bool
    _home_creep: bool
    _home_d_start: float | None
    _move_d_min: float | None
    _move_ref_raw: int | None
    _move_skip: int
    _home_ms: int
    _home_phase: int
    _home_phase_mm: float
    _home_leave_mm: float
    _home_travel_mm: float
    _steps_true_mm: float
    _force_g: float
    _press_dir_hist: collections.deque[tuple[float, float]]
    _press_dir_age: int | None
    _press_dir_held: bool
    _press_dir_leave: bool
    _probe: ContactProbe
    model: RigModel

    @property
    def scale_x100(self) -> int:  # (MegaController's)
        raise NotImplementedError

    def _fault(self, bits: Fault) -> None:  # (MegaController's)
        raise NotImplementedError

    def _actuator_steps(self) -> float:  # (MegaController's)
        raise NotImplementedError

    def _home_switch(self) -> bool:  # (MegaController's)
        raise NotImplementedError

    def _direction_zero(self) -> int | None:
        """The raw zero the direction checks measure the load from (spec 2.11): the tare, else the stored one."""
        return self._tare_raw if self.tared else self._zero_raw

    def _load_g(self, raw: int, zero: int) -> float:
        """|raw - zero| in g: the load on the cell whatever the sign of the scale or of the cell's wiring."""
        return abs((raw - zero) * 100 / self.scale_x100)

    @staticmethod
    def _home_load_cap_g(holding: Mapping[int, int]) -> float:
        """HOME from an unknown position never finds nor makes a load (|raw - zero|) above this, g (spec 2.11)."""
        return holding[HR.FORCE_LIMIT_G] + 2.0 * holding[HR.FORCE_TOLERANCE_G]

    def _home_overloaded(self, holding: Mapping[int, int]) -> bool:
        zero = self._direction_zero()
        return not self.homed and zero is not None and \
            self._load_g(self._last_raw, zero) > self._home_load_cap_g(holding)

    def _move_watch_start(self, skip: int) -> None:
        """A move that only takes force off the cell begins (the firmware's move_watch_start)."""
        raw, zero = self._last_raw, self._direction_zero()
        self._move_ref_raw, self._move_skip = raw, skip
        self._move_d_min = None if zero is None or raw is None else self._load_g(raw, zero)
        self._home_d_start = self._move_d_min

    def _stop_unproven(self, bits: Fault) -> None:
        """A fault after which the actuator may not go where its steps say (the firmware's stop_unproven): a reversed
        motor (ACTUATOR_DIRECTION), or the two channels disagreeing (POSITION_LIMIT, CONTACT_LOST: the reading lies,
        and the position bounds the force where it stands, or the motor runs backwards, and a back-off would press).
        Not homed, stopped where it stands: the start's HOME creeps and proves the way (spec 2.11)."""
        self.homed = False
        self._fault(bits)
        self._retracting = False

    def _direction_fault(self) -> None:
        """The actuator moved the wrong way (the firmware's direction_fault): :meth:`_stop_unproven`."""
        self._stop_unproven(Fault.ACTUATOR_DIRECTION)

    def _watch_direction(self, raw: int) -> None:
        """A new reading while moving home or backing off (firmware: ctl_loadcell): a load (|raw - zero|, sign-free:
        a reversed motor and a reversed cell alike) grown above the lowest since the move began is a move towards
        the sensor (spec 2.11; HOME_RISE_G while homing, DIRECTION_RISE_G backing off); without a known zero, an
        untared rise in the scale's sign (spec 2.5). A creeping HOME whose load fell by HOME_PROOF_FALL_G goes on
        at its speed. HOME from a known position (homed) uses DIRECTION_RISE_G: the readings still carry the press's
        last rise."""
        if not (self._homing or self._retracting):
            return
        thr = wire.HOME_RISE_G if self._homing and not self.homed else wire.DIRECTION_RISE_G  # (the firmware's)
        self._move_skip = max(0, self._move_skip - 1) if self._move_skip else 0
        skipping = self._move_skip > 0
        zero = self._direction_zero()
        if zero is not None:
            d = self._load_g(raw, zero)
            if self._home_d_start is None:
                self._home_d_start = d
            if self._move_d_min is None or d < self._move_d_min or skipping:
                self._move_d_min = d
            elif d - self._move_d_min > thr:
                self._direction_fault()
                return
            if self._homing and not self.homed and d > self._home_load_cap_g(self.holding):
                self._direction_fault()
                return
            if self._home_creep and self._homing and d <= self._home_d_start - wire.HOME_PROOF_FALL_G:
                self._home_creep = False  # the load fell: the direction is right
                self._home_ms = 0  # the timeout runs from the end of the creep
            return
        rise = (raw - self._move_ref_raw) * 100 / self.scale_x100 if self._move_ref_raw is not None else 0.0
        if self._move_ref_raw is None or rise < 0 or skipping:
            self._move_ref_raw = raw
        elif rise > thr:
            self._direction_fault()

    def _home_velocity(self, n_ms: int, cal: float) -> float:
        """HOME's actuator velocity this step (the firmware's home_step): back to the switch, leave it (it must open
        within HOME_PROOF_MM: the direction is right), back again; zero there. Travel is the step count (commanded
        mm, moving or not)."""
        m, dt = self.model, n_ms / 1000.0
        self._home_ms += n_ms
        late = self._home_ms >= wire.HOME_TIMEOUT_MS
        if self._home_phase == 0:  # seek
            period = self._hx_period_s or 1.0 / self.holding[HR.HX711_RATE_SPS]
            creep_mm_s = wire.HOME_CREEP_UM * 1e-3 / period  # spec 2.11: a speed bounded by the HX711's period
            creep_late = self._home_ms >= wire.HOME_TIMEOUT_MS + 1000.0 * wire.HOME_MAX_TRAVEL_MM / creep_mm_s
            if self._home_switch():
                self._home_creep = False
                self._home_phase, self._home_phase_mm = 1, 0.0
            elif self._home_travel_mm >= wire.HOME_MAX_TRAVEL_MM or (late and not self._home_creep) or creep_late:
                return self._home_not_found()
            else:
                speed = creep_mm_s if self._home_creep else HOME_SPEED_MM_S
                self._home_travel_mm += speed * dt
                return -speed * cal
        if self._home_phase == 1:  # leave
            if not self._home_switch():
                self._home_phase, self._home_leave_mm, self._home_phase_mm = 2, self._home_phase_mm, 0.0
            elif self._home_phase_mm >= wire.HOME_PROOF_MM:
                self._direction_fault()
                return 0.0
            else:
                self._home_phase_mm += HOME_SPEED_MM_S * dt
                return HOME_SPEED_MM_S * cal
        if self._home_switch():  # return: home, the direction proven
            m.home_actuator()
            self._steps_true_mm = 0.0
            self._homing = False
            self._tare_pending = True  # HOMING ends when the tare at the switch is taken
            return 0.0
        if self._home_phase_mm >= self._home_leave_mm + wire.HOME_PROOF_MM or late:
            return self._home_not_found()
        self._home_phase_mm += HOME_SPEED_MM_S * dt
        return -HOME_SPEED_MM_S * cal

    def _home_not_found(self) -> float:
        self.homed = False
        self._fault(Fault.HOME_NOT_FOUND)
        return 0.0

    def _watch_press_direction(self) -> None:
        """A new reading while the force loop drives (the firmware's press_dir_watch, spec 2.11): the step count
        commanded over PRESS_DIR_READINGS readings (monotone) against the load read (|force|, sign-free: a reversed
        cell presses as a load too) over as many readings PRESS_DIR_LAG_READINGS later. At least PRESS_DIR_STEPS with
        the load against it by PRESS_DIR_G: ACTUATOR_DIRECTION, stopped where it stands; with it by
        PRESS_DIR_G: the way proven, for PRESS_DIR_PROOF_READINGS readings while the probe runs, and from then on
        once it is done (the loop holds: a reversed motor would drive the force off and be seen); half of both
        against it: the proof is void."""
        hist = self._press_dir_hist
        hist.append((self._actuator_steps(), abs(self._force_g)))  # the load, sign-free: the motor's way, not the cell's
        if self._press_dir_age is not None:
            self._press_dir_age += 1
        if self._probe.active:
            self._press_dir_held = False
        if abs(self._force_g) >= min(float(wire.PROBE_CONTACT_G), 0.5 * self.holding[HR.FORCE_SETPOINT_G]):
            self._press_dir_leave = False  # the contact: the force proves the way from here
        if len(hist) <= wire.PRESS_DIR_READINGS + wire.PRESS_DIR_LAG_READINGS:
            return
        n = wire.PRESS_DIR_READINGS
        steps = [s for s, _ in hist][: n + 1]
        moves = [b - a for a, b in zip(steps, steps[1:])]
        ds = steps[-1] - steps[0]
        if 2 * abs(ds) < wire.PRESS_DIR_STEPS or not (all(d >= 0 for d in moves) or all(d <= 0 for d in moves)):
            return
        df = (hist[-1][1] - hist[-1 - n][1]) * (1.0 if ds > 0 else -1.0)  # + : the force follows the count
        if 2 * df <= -wire.PRESS_DIR_G:
            self._press_dir_age, self._press_dir_held = None, False
            if abs(ds) >= wire.PRESS_DIR_STEPS and df <= -wire.PRESS_DIR_G:
                self._direction_fault()
        elif abs(ds) >= wire.PRESS_DIR_STEPS and df >= wire.PRESS_DIR_G:
            self._press_dir_age = 0
            self._press_dir_held = not self._probe.active

    @property
    def _press_dir_proven(self) -> bool:
        """The way a back-off takes is proven by this press's own motion (spec 2.11): the count and the force
        moved together in a window that ended at most PRESS_DIR_PROOF_READINGS readings ago, or the probe's measuring
        step(s) raised the settled load by PRESS_DIR_G (or the loop's motion did since the probe was done), and
        nothing moved them apart since. Before the contact HOME's switch proof stands: the press left the closed
        switch, and the switch reading closed more than HOME_PROOF_MM out voids it."""
        return self._press_dir_held or self._press_dir_leave or (
            self._press_dir_age is not None and self._press_dir_age <= wire.PRESS_DIR_PROOF_READINGS)
