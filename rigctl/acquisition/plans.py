"""Python protocols as plans: the narrow API a plan is written against (:class:`PlanContext`), and its type.

A Python protocol is a ``.py`` file defining ``plan(ctx)``, a generator function (bluesky's plans are the model):
it *yields* the trials it wants, one at a time (``ctx.trial(...)``), and receives each one's recording back as the
value of the ``yield``: a :class:`rigctl.core.trial.TrialData`, or None when the trial failed after its retries. The
run engine (:func:`rigctl.acquisition.runner.run_protocol`, the same one a TOML protocol runs in) does everything
else between two yields: mounting the plate, pressing, recording, the retries and the dropped-frame policy, pause,
STOP and abort, the safety latch, progress events, and writing each trial to the session file in one crash-safe
commit. So a plan gets all of that for free and touches no device::

    NAME = "force_sweep"
    MAX_TRIALS = 6                      # optional: for the progress bar

    def plan(ctx):
        for force in (200.0, 400.0, 600.0):
            data = yield ctx.trial("L", speed_mm_s=100.0, force_g=force, duration_s=1.2)
            if data is not None:
                ctx.note(f"{force:g} g: mean {data.taxels.mean():.1f} counts")

Resume (``rigctl acquire --resume``) runs the plan again from its start: the trials the session file already holds
are sent back from the file instead of being recorded, so a plan must be deterministic given its recordings (the
same yields for the same data). A yield that differs from the file's trial at that position is refused
(:class:`rigctl.storage.session.SessionError`). docs/protocols.md ("Python protocols") has the details.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass

from rigctl.core.drum import PROTOCOL_LIMITS
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import PlannedTrial, TrialData

__all__ = ["Plan", "PlanContext", "PlanFunction"]

#: what ``plan(ctx)`` returns: a generator yielding trials and receiving each one's recording (None: failed)
Plan = Generator[PlannedTrial, "TrialData | None", None]
#: a Python protocol's ``plan``
PlanFunction = Callable[["PlanContext"], Plan]


@dataclass(frozen=True)
class PlanContext:
    """What a plan sees of the rig: the texture set plates are mounted from, the sensor, and a way to report.

    Attributes
    ----------
    textures : the rig's :class:`rigctl.core.textures.TextureSet` (a trial's texture must be one of its labels).
    layout : the taxel source's :class:`rigctl.core.sensor.SensorLayout` (a recording's ``taxels`` is
        ``(n_samples, layout.n_channels)`` uint16 ADC counts).
    note : ``note(message)`` shows a line on the run's progress (the CLI's bar, the GUI's log).
    """

    textures: TextureSet
    layout: SensorLayout
    note: Callable[[str], None]

    def trial(self, texture: str, *, speed_mm_s: float, force_g: float, duration_s: float | None = None,
              travel_mm: float | None = None, ramp_start_mm_s: float = math.nan,
              ramp_end_mm_s: float = math.nan, profile: str | None = None) -> PlannedTrial:
        """A trial to yield: ``texture`` (a label of :attr:`textures`), ``speed_mm_s`` (mm/s; for a ramp its mean,
        with ``ramp_start_mm_s`` / ``ramp_end_mm_s``), ``force_g`` (g), and its length as ``duration_s`` (s) or
        ``travel_mm`` (mm of drum surface). The engine gives it its trial id.

        Raises ValueError (``rigctl.core.textures.TextureSetError``) for a label outside the set,
        ``rigctl.core.drum.SetpointRangeError`` for a speed or force outside the rig's protocol range, ValueError for
        a missing or non-positive length."""
        label = self.textures.resolve(str(texture))
        limits = PROTOCOL_LIMITS
        ramp = not (math.isnan(ramp_start_mm_s) and math.isnan(ramp_end_mm_s))
        for v in ((ramp_start_mm_s, ramp_end_mm_s) if ramp else (speed_mm_s,)):
            limits.speed_range().check(float(v))
        limits.force_range().check(float(force_g))
        if (duration_s is None) == (travel_mm is None):
            raise ValueError("give the trial's length as duration_s or travel_mm (one of them)")
        length = float(duration_s) if duration_s is not None else float(travel_mm or 0.0) / float(speed_mm_s)
        if not (math.isfinite(length) and length > 0):
            raise ValueError(f"a trial lasts more than 0 s, got {length:g} s")
        return PlannedTrial(trial_id=-1, texture=label, speed_mm_s=float(speed_mm_s), force_g=float(force_g),
                            duration_s=length, profile=profile or ("ramp" if ramp else "constant"),
                            ramp_start_mm_s=float(ramp_start_mm_s), ramp_end_mm_s=float(ramp_end_mm_s))
