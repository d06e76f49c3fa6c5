"""A session's trials as the encoder labels them: the plan's labels (trial id, texture, speed, force, profile), an
imported session's source recording per trial, and whether the trials' lengths are the operator's (a handheld scan).
Read from an open session (:class:`rigctl.storage.session_reader.SessionReader`: ``plan``, ``attrs``,
``trial_attrs``); used by :mod:`rigctl.encoding.pipeline`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from rigctl.storage.session_reader import SessionReader

__all__ = ["trial_labels", "plan_labels", "operator_paced", "recordings"]


def trial_labels(session: SessionReader, ids: Sequence[int]) -> dict[str, np.ndarray]:
    """:func:`plan_labels` and :func:`recordings` of ``ids`` in one mapping (each array of ``len(ids)``)."""
    return {**plan_labels(session, ids), **recordings(session, ids)}


def plan_labels(session: SessionReader, ids: Sequence[int]) -> dict[str, np.ndarray]:
    """The plan's labels of ``ids``: ``trial_id`` (uint32), ``texture`` and ``profile`` (str), ``speed_mm_s`` and
    ``force_g`` (float64, NaN where the plan has no such column), each of ``len(ids)``; a trial id not in the plan
    raises KeyError."""
    plan = session.plan
    row_of = {int(t): i for i, t in enumerate(plan["trial_id"])}
    rows = plan[[row_of[t] for t in ids]]
    names = plan.dtype.names or ()

    def col(name: str, default: Any) -> Any:
        return rows[name] if name in names else np.full(len(ids), default)

    def text(values: Any) -> np.ndarray:
        return np.array([v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in np.asarray(values)],
                        dtype=str)

    return {
        "trial_id": np.asarray(ids, dtype=np.uint32),
        "texture": text(col("texture", "")),
        "speed_mm_s": np.asarray(col("speed_mm_s", np.nan), dtype=np.float64),
        "force_g": np.asarray(col("force_g", np.nan), dtype=np.float64),
        "profile": text(col("profile", "constant")),
    }


def operator_paced(session: SessionReader, ids: Sequence[int]) -> bool:
    """Whether the trials' lengths are the operator's: a handheld scan's boundaries are positions on the plate
    (``boundary = "position"``, rigctl.acquisition.handheld), so its length is the operator's speed."""
    return bool(ids) and session.trial_attrs(int(ids[0])).get("boundary") == "position"


def recordings(session: SessionReader, ids: Sequence[int]) -> dict[str, np.ndarray]:
    """An imported session's source recording per trial (``recording``: file, ``[block]`` of a stacked file; str) and
    where in it the trial starts (``recording_start_s``, float64 s), from the trial attributes ``rigctl import``
    writes; {} for a session recorded here (the session is the recording)."""
    if str(session.attrs.get("kind", "")) != "imported":
        return {}
    rec, start = [], []
    for tid in ids:
        a = session.trial_attrs(int(tid))
        name = str(a.get("source_file", ""))
        block = a.get("source_block")
        rec.append(name if block is None else f"{name}[{int(block)}]")
        start.append(float(a.get("segment_start_s", 0.0)))
    return {"recording": np.array(rec, dtype=str), "recording_start_s": np.asarray(start, dtype=np.float64)}
