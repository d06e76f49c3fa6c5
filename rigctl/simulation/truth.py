"""The simulated rigs' ground truth as CSV (``--truth-log FILE``, issue 39): what the physical model did, to compare
with what the firmware or the controller believed.

Columns: ``wall_time_s`` (Unix time, s, at which the row was written: the moment the physics reached ``time_s``, up
to one physics step later; what another process's actions are compared with), ``time_s`` (s from the run's start:
the moment the rig was open, the clock ``--inject`` times its faults on: the physics clock of the simulated rig, the
Mega's simulated time under simavr), ``true_force_g`` (the contact
force on the load cell, g, not the HX711's delayed reading), ``actuator_mm`` (the actuator's real position from home,
mm, + towards the sensor), ``drum_speed_mm_s`` (the drum's real surface speed, mm/s), ``motor_mm`` (the actuator
motor's position as the screw travel it turns, mm from home, + towards the sensor: ``actuator_mm`` plus a slipping
coupling's wind-up; it moves only by the steps the motor really takes, so a wound coupling's catch-up moves
``actuator_mm`` and not it: what the controller's own steps moved). One row per physics step of
the simulated rig (<= 10 ms) or per report of the HIL harness (every 10 ms of simulated time, and at each change of
the controller's state): >= 100 Hz; under simavr a row's force is the largest and its actuator and motor positions the
furthest towards the sensor since the previous row (the harness watches them every 0.1 ms), so no peak between rows is lost. The file is
flushed after every row: another process may read it while it grows (``rigctl sim --truth-log``), whole lines only.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

__all__ = ["TruthLog", "TRUTH_COLUMNS"]

TRUTH_COLUMNS = ("wall_time_s", "time_s", "true_force_g", "actuator_mm", "drum_speed_mm_s", "motor_mm")


class TruthLog:
    """A CSV file of ground-truth rows, written from the moment :meth:`start` gives the run's start.

    Parameters
    ----------
    path : the file to create. FileExistsError if it exists (a user's file is never overwritten).
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        self._file = open(self.path, "x", encoding="ascii", newline="")  # noqa: SIM115 - closed by close()
        self._file.write(",".join(TRUTH_COLUMNS) + "\n")
        self._file.flush()
        self._lock = threading.Lock()
        self._t0: float | None = None
        self.rows = 0

    @property
    def t0_s(self) -> float | None:
        """The physics clock's time of the run's start (None before :meth:`start`)."""
        return self._t0

    def start(self, t0_s: float) -> None:
        """The run starts at the physics clock's ``t0_s`` (the first call wins); rows before it are not written."""
        with self._lock:
            if self._t0 is None:
                self._t0 = float(t0_s)

    def row(self, t_s: float, true_force_g: float, actuator_mm: float, drum_speed_mm_s: float, motor_mm: float
            ) -> None:
        """One row at the physics clock's ``t_s`` (nothing before :meth:`start`, or after :meth:`close`)."""
        with self._lock:
            if self._t0 is None or self._file.closed or t_s < self._t0:
                return
            self._file.write(f"{time.time():.4f},{t_s - self._t0:.4f},{true_force_g:.2f},{actuator_mm:.4f},"
                             f"{drum_speed_mm_s:.3f},{motor_mm:.4f}\n")
            self._file.flush()  # whole rows for a reader in another process (one write each)
            self.rows += 1

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._file.close()
