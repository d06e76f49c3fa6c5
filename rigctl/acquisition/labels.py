"""The condition a trial was recorded under, where it is not the planned one: a trial of the replay rig carries the
source trial's samples, so its labels are the source's (issue 23: a replayed session stored the protocol's speed and
force for every trial, and the encoder scaled the speed-scaled variants by the protocol's speed, not the recording's).

:func:`recorded_labels` reads them from the trial's ``source_*`` attributes (:meth:`rigctl.acquisition.rig.Rig.
record_trial` on the replay rig); the runner passes them to :meth:`rigctl.storage.session.SessionWriter.write_trial`,
which stores them in the trial's ``/plan`` row and keeps the planned ones as ``planned_*`` trial attributes
(docs/session-format.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

__all__ = ["recorded_labels"]

#: plan field <- the trial attribute that holds the source's value (FabricSlide's force is a setpoint level, not
#: grams: it has no source_force_g, and the plan's force stays)
_SOURCE_OF = {"texture": "source_texture", "speed_mm_s": "source_speed_mm_s", "force_g": "source_force_g"}


def recorded_labels(planned: Any, attrs: Mapping[str, Any]) -> dict[str, Any]:
    """The labels of a trial recorded from one source trial (``attrs`` hold ``source_*`` and no ``source_pieces``)
    that differ from ``planned`` (a :class:`rigctl.acquisition.protocol.PlannedTrial`): ``texture`` (str),
    ``speed_mm_s`` (mm/s), ``force_g`` (g); {} for any other trial, for a trial whose samples cross source trials
    (no one condition), and for source values that are missing or not finite positive numbers."""
    if "source_pieces" in attrs or not any(k in attrs for k in _SOURCE_OF.values()):
        return {}
    out: dict[str, Any] = {}
    texture = attrs.get("source_texture")
    if isinstance(texture, str) and texture and texture != planned.texture:
        out["texture"] = texture
    for field in ("speed_mm_s", "force_g"):
        raw = attrs.get(_SOURCE_OF[field])
        try:
            value = float(raw)  # type: ignore[arg-type]  # anything an attribute holds; refused below if not a number
        except (TypeError, ValueError):
            continue
        if math.isfinite(value) and value > 0 and not math.isclose(value, float(getattr(planned, field)),
                                                                   rel_tol=1e-6):
            out[field] = value
    return out
