"""The setpoint policy an operator meets: which manual speed / force setpoints are accepted, and why one is not.

The ranges are :class:`rigctl.core.drum.DrumLimits`' (the lower of the rig's protocol range and the controller's
hard limits: the one home of the limits); this module words a refusal for the operator, short (under a box) and in
full (a message line, the event log), so that the CLI and the GUI say the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass

from rigctl.core.drum import DrumLimits, SetpointRange

__all__ = ["SetpointRefusal", "setpoint_refusals", "refusal"]


@dataclass(frozen=True)
class SetpointRefusal:
    """Why a setpoint cannot be sent.

    Attributes
    ----------
    name : "speed" | "force"
    value : the refused value, in ``unit``
    unit : "mm/s" | "g"
    short : a short line, e.g. ``"speed 200 mm/s refused: max 150 mm/s"``
    full : the full sentence, e.g. ``"speed 200 mm/s refused: above the rig's protocol range of 150 mm/s"``
    """

    name: str
    value: float
    unit: str
    short: str
    full: str


def refusal(rng: SetpointRange, value: float) -> SetpointRefusal | None:
    """Why ``value`` cannot be sent within ``rng`` (None when it can)."""
    if rng.contains(value):
        return None
    v = float(value)
    head = f"{rng.name} {v:g} {rng.unit} refused"
    if not v > rng.low:
        return SetpointRefusal(rng.name, v, rng.unit, f"{head}: must be > {rng.low:g}",
                               f"{head}: it must be above {rng.low:g} {rng.unit} (Stop drum / STOP to stop)")
    return SetpointRefusal(rng.name, v, rng.unit, f"{head}: max {rng.high:g} {rng.unit}",
                           f"{head}: above the {rng.source} of {rng.high:g} {rng.unit}")


def setpoint_refusals(limits: DrumLimits, *, speed_mm_s: float | None = None,
                      force_g: float | None = None) -> list[SetpointRefusal]:
    """The refusals of the given manual setpoints under ``limits`` (empty when every one can be sent)."""
    out = []
    for rng, value in ((limits.speed_range(), speed_mm_s), (limits.force_range(), force_g)):
        if value is not None and (r := refusal(rng, value)) is not None:
            out.append(r)
    return out
