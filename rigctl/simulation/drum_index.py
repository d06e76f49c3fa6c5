"""The drum controller's index counting and speed marks (docs/wire-protocol.md 2.6), for the virtual Mega
(:class:`rigctl.simulation.controller.MegaController`): the step pulses the firmware sends (the stepper's travel
through its acceleration ramp), the index sensor's marks and the speed-mark disc's on the real drum, as the firmware's
step ISR, Timer5 input capture and INT2 interrupt make them (arduino/mega_drum/mega_drum.cpp), and the slip check
that latches DRUM_SLIP.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.core.drum import DRUM_SLIP_TOLERANCE
from rigctl.devices.wire import InputRegister as IR
from rigctl.simulation.model import DrumConfig

__all__ = ["DrumIndex"]


class DrumIndex:
    """Index and speed-mark state of one power-up of the controller.

    Attributes
    ----------
    steps : float
        Microsteps sent since power-up.
    sensor_live : bool
        The index sensor gave an edge within the last 1.5 revolutions of steps (else the step count marks the index).
    edges : int
        Index-sensor edges since power-up (INDEX_COUNT).
    period_ms, steps_per_mark : int
        Time (ms) and microsteps between the last two sensor edges (INDEX_PERIOD_MS, INDEX_STEPS; 0 until two).
    revolutions : int
        Index marks passed, by the sensor or the step count (DRUM_REVOLUTIONS).
    marks, mark_period_0p1ms, mark_steps : int
        Speed marks since power-up (MARK_COUNT), the time (0.1 ms) and microsteps between the last two that came
        while the drum was stepped (MARK_PERIOD_0P1MS, MARK_STEPS; 0 until then).
    slipped : bool
        More than ``1 + DRUM_SLIP_TOLERANCE`` mark intervals of steps passed without a mark while the drum was
        stepped (the controller latches DRUM_SLIP and clears this).
    """

    def __init__(self, drum: DrumConfig):
        self.drum = drum
        self.steps = 0.0
        self.steps_at_sensor = 0.0
        self.sensor_live = False
        self.edges = 0
        self.last_edge_s = 0.0
        self.period_ms = 0
        self.steps_per_mark = 0
        self.revolutions = 0
        self.marks = 0
        self.mark_period_0p1ms = 0
        self.mark_steps = 0
        self.slipped = False
        self._steps_at_mark = 0.0
        self._mark_s = 0.0
        self._mark_fresh = False
        usteps = drum.steps_per_rev * drum.microsteps
        self._slip_steps = usteps / max(1, drum.marks_per_rev) * (1.0 + DRUM_SLIP_TOLERANCE)

    def step(self, sensor: np.ndarray, stepper_mm: np.ndarray, travel0_mm: float, steps_per_mm: float, t0: float,
             marks: np.ndarray | None = None) -> np.ndarray:
        """Count the step pulses of a step of ``sensor.size`` ms from ``t0`` (s) and take the sensors' passes.

        ``sensor``: (n,) bool, the model's real index mark passed in that ms (if a sensor is fitted); the step pulses
        sent since the step's start at the end of each ms are ``(stepper_mm - travel0_mm) * steps_per_mm``
        (``stepper_mm`` (n,) float: the stepper's travel at the end of each ms, mm; ``travel0_mm`` at the step's
        start; ``steps_per_mm`` at the driver's real setting), taken per ms only by a step with an edge, a wrap or a
        speed mark (the common step needs its last: a few ms a step, hundreds of steps a second); ``marks``: (n,)
        bool, a speed mark passed in that ms (None: no disc). Returns the index output per ms, (n,) bool."""
        d = self.drum
        usteps = d.steps_per_rev * d.microsteps  # what the firmware assumes
        n = sensor.size
        before = self.steps
        last_pulses = float((stepper_mm[-1] - travel0_mm) * steps_per_mm) if n else 0.0
        pulses: np.ndarray | None = None  # per ms: made only by a step that needs them, once
        if marks is not None and d.marks_per_rev > 0 and n:
            if np.count_nonzero(marks):  # (most steps of a few ms pass none)
                pulses = (stepper_mm - travel0_mm) * steps_per_mm
            self._speed_marks(marks, before, last_pulses, pulses, t0)
        # the common step: no index edge, and no wrap of the step count that counts (count_nonzero: one C call;
        # ndarray.any() goes through numpy's Python layer)
        if n and not np.count_nonzero(sensor):
            last = before + last_pulses
            if self.sensor_live:
                if last - self.steps_at_sensor <= 1.5 * usteps:  # the sensor stays live: no index output
                    self.steps = last
                    return np.zeros(n, bool)
            elif math.floor(before / usteps) == math.floor(last / usteps):  # no wrap
                self.steps = last
                return np.zeros(n, bool)
        if pulses is None:
            pulses = (stepper_mm - travel0_mm) * steps_per_mm
        steps = before + pulses
        self.steps = float(steps[-1]) if n else before
        out = np.zeros(n, bool)
        if d.index_sensor:
            for j in np.flatnonzero(sensor):
                t = t0 + (j + 1) * 1e-3
                if self.edges:
                    self.period_ms = min(0xFFFF, int(round((t - self.last_edge_s) * 1000.0)))
                    self.steps_per_mark = min(0xFFFF, int(round(steps[j] - self.steps_at_sensor)))
                self.last_edge_s = t
                self.steps_at_sensor = float(steps[j])
                self.edges += 1
                self.sensor_live = True
                self.revolutions += 1
                out[j] = True
        if self.sensor_live and self.steps - self.steps_at_sensor > 1.5 * usteps:
            self.sensor_live = False  # no edge for 1.5 revolutions: back to the step count
        if not self.sensor_live and n:
            wraps = np.diff(np.floor(np.concatenate(([before], steps)) / usteps)) != 0
            out |= wraps
            self.revolutions += int(wraps.sum())
        return out

    def _speed_marks(self, marks: np.ndarray, before: float, last_pulses: float, pulses: np.ndarray | None,
                     t0: float) -> None:
        """The speed marks of one step (the firmware's INT2 interrupt and its slip check in the 1 kHz tick): the
        step count is ``before + pulses`` at the end of each ms (``pulses`` None: no mark passed in the step),
        ``before + last_pulses`` at its end."""
        last = before + last_pulses
        if pulses is not None:
            steps = before + pulses
            for j in np.flatnonzero(marks):
                t = t0 + (j + 1) * 1e-3
                since = float(steps[j]) - self._steps_at_mark
                if since > self._slip_steps:
                    self.slipped = True  # late: the tick saw the limit pass before this mark came
                if self._mark_fresh and since > 0:
                    self.mark_period_0p1ms = min(0xFFFF, int(round((t - self._mark_s) * 10000.0)))
                    self.mark_steps = min(0xFFFF, int(round(since)))
                self._mark_fresh = since > 0
                self._mark_s, self._steps_at_mark = t, float(steps[j])
                self.marks += 1
        if last == before:  # the drum at rest: the check re-arms, the next interval is not reported
            self._steps_at_mark, self._mark_fresh = last, False
        elif last - self._steps_at_mark > self._slip_steps:
            self.slipped = True  # a stall, or a slip: no mark within the interval's steps and the tolerance
        if self.slipped:  # re-armed (the firmware's too): the deceleration that follows does not latch it again
            self._steps_at_mark, self._mark_fresh = last, False

    def take_slip(self) -> bool:
        """Whether the drum slipped or stalled since the last call (the controller latches DRUM_SLIP)."""
        slipped, self.slipped = self.slipped, False
        return slipped

    def input_registers(self, regs: list[int]) -> None:
        """Fill the drum angle, revolution, index and speed-mark input registers of ``regs`` (spec 2.2, 2.6)."""
        regs[IR.DRUM_ANGLE_0P01DEG] = int(self.angle_deg() * 100) % 36000
        regs[IR.DRUM_REVOLUTIONS] = self.revolutions & 0xFFFF
        regs[IR.INDEX_SOURCE] = 1 if self.sensor_live else 0
        regs[IR.INDEX_PERIOD_MS], regs[IR.INDEX_STEPS] = self.period_ms, self.steps_per_mark
        regs[IR.INDEX_COUNT] = self.edges & 0xFFFF
        regs[IR.MARK_PERIOD_0P1MS], regs[IR.MARK_STEPS] = self.mark_period_0p1ms, self.mark_steps
        regs[IR.MARK_COUNT] = self.marks & 0xFFFF

    def angle_deg(self) -> float:
        """DRUM_ANGLE, degrees: the steps since the last index-sensor edge while the sensor is live, else the step
        count."""
        d = self.drum
        usteps = d.steps_per_rev * d.microsteps
        steps = self.steps - self.steps_at_sensor if self.sensor_live else self.steps
        return float((steps % usteps) / usteps * 360.0)
