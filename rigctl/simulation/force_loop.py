"""The drum controller's force loop for the virtual Mega: its PI update, over-force prediction and contact probe.

The same rules as the firmware's ``force_pi.c`` (:func:`force_pi_update`) and ``controller.c`` (``probe_reading``,
``ctl_stiffness_max``, the trip in ``ctl_loadcell``; docs/wire-protocol.md 2.9, 2.10): the first press after a reset
approaches at PROBE_TRAVEL_UM per FORCE_LEAD_PERIODS HX711 periods until the reading passes PROBE_CONTACT_G (or half
the setpoint), stops until the reading has averaged only the new position (the 5th reading: the HX711's sinc^4 spans
4 periods), steps PROBE_STEP_UM further, settles again, and takes the contact stiffness as the force's change over the
step's travel. A stiffness above LOOP_PHASE_RAD / (Kp x HX711_DELAY_PERIODS x period) is more than the force loop
holds: CONTACT_STIFFNESS, and PRESS and RUN are refused while it stays above that limit (slower gains raise it).
While the loop drives, the force-limit trip extrapolates the last period's rise over FORCE_LEAD_PERIODS.

Firmware 1.2 (spec 2.11): every press from rest probes (the contact is forgotten at each release, HOME and reset);
a first step that pressed less than half of PROBE_REFINE_G is followed by a second sized from it to press
PROBE_REFINE_G more (at most 0.5 mm), and the stiffness is taken over both; the contact's zero-force point is the
first settle's position less its force over the stiffness (:attr:`ContactProbe.x0_mm`). Where the contact is stays
known across a release until HOME, a fault or a reset (:attr:`ContactProbe.located_x0_steps`): the next press
approaches it at the loop's clamp speed up to PROBE_LOCATED_MARGIN_UM before it, then probes from there (the
stiffness and the zero-force point measured again at every press).
"""

from __future__ import annotations

from collections.abc import Mapping

from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR

__all__ = ["ContactProbe", "force_pi_update", "stiffness_max_g_per_mm"]

_NONE, _APPROACH, _SETTLE1, _STEP, _SETTLE2, _STEP2, _SETTLE3 = range(7)


def force_pi_update(integ: float, kp: float, ki: float, out_max: float, band_g: float, setpoint_g: float,
                    force_g: float, dt_s: float) -> tuple[float, float]:
    """One PI update per HX711 reading (the firmware's force_pi_update): the integral grows only while abs(error)
    is below ``band_g`` and not while the output is clamped in the error's direction. Gains in (mm/s)/g and
    (mm/s)/(g s); returns (actuator velocity, mm/s, clamped to +-``out_max``; the new integral)."""
    e = setpoint_g - force_g
    grown = integ + ki * e * dt_s if abs(e) < band_g else integ
    out = kp * e + grown
    if out > out_max:
        out, integ = out_max, grown if e < 0 else integ
    elif out < -out_max:
        out, integ = -out_max, grown if e > 0 else integ
    else:
        integ = grown
    return out, min(out_max, max(-out_max, integ))


def stiffness_max_g_per_mm(holding: Mapping[int, int], period_s: float) -> int:
    """The stiffest contact the force loop holds with the gains of HX711_RATE_SPS in ``holding``, g/mm (65535 with
    Kp = 0, and at most that); ``period_s``: the HX711's measured period (0: 1 / HX711_RATE_SPS)."""
    slow = holding[HR.HX711_RATE_SPS] < 40
    kp = holding[HR.FORCE_KP_10SPS_NMS_G if slow else HR.FORCE_KP_80SPS_NMS_G] * 1e-6
    period = period_s if period_s > 0 else 1.0 / holding[HR.HX711_RATE_SPS]
    if kp <= 0:
        return 0xFFFF
    return int(min(0xFFFF, wire.LOOP_PHASE_RAD / (kp * period * wire.HX711_DELAY_PERIODS)))


class ContactProbe:
    """The probe's state and the measured stiffness (lost at a reset: make a new one)."""

    def __init__(self) -> None:
        self.stiffness_g_per_mm = 0  #: measured by the first press since the reset, g/mm (0 = not yet)
        self._phase = _NONE
        self._readings = 0
        self._f1_g = 0.0
        self._x1_mm = 0.0
        self._target_mm = 0.0
        self._prev_g: float | None = None
        #: the contact this press probed (spec 2.11): valid until the actuator is released
        self.contact_valid = False
        self.k_g_per_step = 0.0  #: its stiffness, g per actuator step (the firmware's: a calibration change keeps it)
        self.x0_steps = 0.0  #: its zero-force point, actuator steps
        #: where the last probe found the contact's zero-force point, actuator steps, kept across a release until HOME,
        #: a fault or a reset (:meth:`forget`): the next press approaches fast up to PROBE_LOCATED_MARGIN_UM before it
        self.located_x0_steps: float | None = None
        #: the settled load's rise over the last completed probe's measuring step(s), g (forward steps: it proves the
        #: actuator's way for the rest of the press when at least PRESS_DIR_G, spec 2.11)
        self.step_rise_g = 0.0

    @property
    def active(self) -> bool:
        """The probe drives the actuator (the force loop waits)."""
        return self._phase != _NONE

    def ok(self, holding: Mapping[int, int], period_s: float) -> bool:
        """PRESS and RUN may run: no stiffness measured yet, or one the loop holds."""
        return not self.stiffness_g_per_mm or self.stiffness_g_per_mm <= stiffness_max_g_per_mm(holding, period_s)

    def engage(self) -> None:
        """The force loop engages: probe the contact unless this press has probed it (every press from rest)."""
        self._phase = _NONE if self.contact_valid else _APPROACH
        self._prev_g = None

    def release(self) -> None:
        """The actuator is released (STOP, a fault's back-off, HOME): the next press probes again."""
        self.contact_valid = False

    def forget(self) -> None:
        """HOME or a fault: the next press locates the contact from scratch (its whole approach at the probe's speed)."""
        self.located_x0_steps = None

    def _fast(self, pos_mm: float, holding: Mapping[int, int]) -> bool:
        spmm = holding[HR.ACTUATOR_STEPS_PER_MM]
        return self.located_x0_steps is not None and \
            pos_mm * spmm < self.located_x0_steps - wire.PROBE_LOCATED_MARGIN_UM * 1e-3 * spmm

    def approach_cut(self, pos_mm: float, holding: Mapping[int, int]) -> bool:
        """The 1 kHz tick: a fast approach has reached PROBE_LOCATED_MARGIN_UM before the located contact (the
        actuator goes on at the probe's speed)."""
        return self._phase == _APPROACH and self.located_x0_steps is not None and not self._fast(pos_mm, holding)

    def position_limit_steps(self, force_limit_g: float) -> float | None:
        """The step count past which POSITION_LIMIT latches (spec 2.11), or None (no contact probed)."""
        if not self.contact_valid or self.active:
            return None
        return self.x0_steps + (force_limit_g + wire.POSITION_MARGIN_G) / self.k_g_per_step

    def contact_lost(self, force_g: float, pos_steps: float, tolerance_g: float) -> bool:
        """The reading holds a force the position (the step count) says the contact does not carry (CONTACT_LOST,
        spec 2.11)."""
        return (self.contact_valid and not self.active and force_g > 2.0 * tolerance_g
                and (pos_steps - self.x0_steps) * self.k_g_per_step < 0.5 * force_g)

    def forget_reading(self) -> None:
        """A tare: the next reading is not comparable with the last."""
        self._prev_g = None

    def predicted_g(self, force_g: float, driving: bool) -> float:
        """The force the trip compares with FORCE_LIMIT_G after a new reading: while the loop drives the actuator
        (``driving``), the reading plus its rise since the last one times FORCE_LEAD_PERIODS."""
        rise = force_g - self._prev_g if driving and self._prev_g is not None and force_g > self._prev_g else 0.0
        self._prev_g = force_g
        return force_g + rise * wire.FORCE_LEAD_PERIODS

    def speed_mm_s(self, period_s: float, max_mm_s: float) -> float:
        """The probe's approach speed, commanded mm/s."""
        return min(max_mm_s, wire.PROBE_TRAVEL_UM * 1e-3 / (wire.FORCE_LEAD_PERIODS * period_s))

    def reading(self, force_g: float, pos_mm: float, holding: Mapping[int, int], period_s: float,
                max_mm_s: float) -> tuple[float, bool]:
        """A new reading while the probe runs: (the actuator velocity, mm/s; True when the stiffness it has just
        measured is more than the loop holds: the caller latches CONTACT_STIFFNESS)."""
        v = self.speed_mm_s(period_s, max_mm_s)
        contact = min(float(wire.PROBE_CONTACT_G), 0.5 * holding[HR.FORCE_SETPOINT_G])
        if self._phase == _APPROACH:
            if force_g < contact:
                return (max_mm_s if self._fast(pos_mm, holding) else v), False
            self._phase, self._readings = _SETTLE1, 0
            return 0.0, False
        if self._phase in (_STEP, _STEP2):
            return v, False
        self._readings += 1
        if self._readings <= wire.HX711_RATE_PERIODS:
            return 0.0, False
        if self._phase == _SETTLE1:
            self._f1_g, self._x1_mm = force_g, pos_mm
            self._target_mm = pos_mm + wire.PROBE_STEP_UM * 1e-3
            self._phase = _STEP
            return v, False
        dx = pos_mm - self._x1_mm
        k = (force_g - self._f1_g) / dx if dx > 0 else 0.0
        refine = min(float(wire.PROBE_REFINE_G), 0.5 * holding[HR.FORCE_SETPOINT_G])
        self.stiffness_g_per_mm = int(min(0xFFFF, max(1.0, k)))
        if not self.ok(holding, period_s):
            self._phase = _NONE
            return 0.0, True
        if self._phase == _SETTLE2 and force_g - self._f1_g < 0.5 * refine:  # a soft contact: a second step
            dx2 = min(0.5, (refine - (force_g - self._f1_g)) / max(k, 200.0))
            self._target_mm = pos_mm + dx2
            self._phase = _STEP2
            return v, False
        self._phase = _NONE
        spmm = holding[HR.ACTUATOR_STEPS_PER_MM]
        self.k_g_per_step = max(k, 1.0) / spmm
        self.x0_steps = self._x1_mm * spmm - self._f1_g / self.k_g_per_step
        self.contact_valid = True
        self.located_x0_steps = self.x0_steps
        self.step_rise_g = force_g - self._f1_g
        return 0.0, False

    def step_done(self, pos_mm: float) -> bool:
        """The 1 kHz tick: the measuring step has reached its travel (the actuator stops; settle)."""
        if self._phase in (_STEP, _STEP2) and pos_mm >= self._target_mm - 1e-9:
            self._phase, self._readings = (_SETTLE2 if self._phase == _STEP else _SETTLE3), 0
            return True
        return False
