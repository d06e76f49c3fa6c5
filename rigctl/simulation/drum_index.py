"""The drum controller's index counting (docs/wire-protocol.md 2.6), for the virtual Mega
(:class:`rigctl.simulation.controller.MegaController`): the step count the firmware keeps and the index sensor's
marks on the real drum, as the firmware's step ISR and Timer5 input capture make them (arduino/mega_drum/mega_drum.cpp).
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.simulation.model import DrumConfig

__all__ = ["DrumIndex"]


class DrumIndex:
    """Index state of one power-up of the controller.

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

    def step(self, sensor: np.ndarray, rate: float, t0: float) -> np.ndarray:
        """Count the step pulses of a step of ``sensor.size`` ms at ``rate`` microsteps/s from ``t0`` (s) and take
        the index sensor's passes (``sensor``: (n,) bool, the model's real index mark, if a sensor is fitted);
        returns the index output per ms, (n,) bool."""
        d = self.drum
        usteps = d.steps_per_rev * d.microsteps  # what the firmware assumes
        n = sensor.size
        before = self.steps
        if n and not self.sensor_live and not sensor.any():  # the common ms: no index edge, maybe no wrap
            last = before + rate * n / 1000.0
            if math.floor(before / usteps) == math.floor(last / usteps):  # steps are linear in time: no wrap
                self.steps = float(last)
                return np.zeros(n, bool)
        steps = before + rate * np.arange(1, n + 1) / 1000.0
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

    def angle_deg(self) -> float:
        """DRUM_ANGLE, degrees: the steps since the last index-sensor edge while the sensor is live, else the step
        count."""
        d = self.drum
        usteps = d.steps_per_rev * d.microsteps
        steps = self.steps - self.steps_at_sensor if self.sensor_live else self.steps
        return float((steps % usteps) / usteps * 360.0)
