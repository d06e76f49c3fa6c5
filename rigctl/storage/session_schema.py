"""Decoding a session file's header, every schema: the checks of the file as a whole, the plan, and the sensor and
texture set of schema 3 (``sensor_layout``, ``texture_set`` attributes) and of schema 1/2 files (the paper's sensor,
or the present channels of a FabricSlide import; the texture set of the plan's labels: ``docs/session-format.md``,
"Older files")."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, texture_set_from_labels
from rigctl.core.trial import TrialData  # noqa: F401 (re-exported: the trial record lives in rigctl.core)
from rigctl.storage.session_format import (
    _READ_ERRORS,
    SCHEMA_VERSION,
    STATUS_ENUM,
    SessionError,
    TrialStatus,
    _read_attrs,
    _read_text,
    _reading,
    _text,
)

log = logging.getLogger("rigctl.storage.session")


def _group_status(group: Any) -> str:
    """The ``status`` attribute of a trial group as str ("" when absent or unreadable)."""
    try:
        v = group.attrs.get("status", "")
    except _READ_ERRORS:
        return ""
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _check_file(f: h5py.File, path: Path) -> None:
    with _reading(path, "the file's top level"):
        missing = [k for k in ("plan", "trials", "protocol") if k not in f]
        has_version = "schema_version" in f.attrs
    _check_top(f, path, missing, has_version)


def _check_top(f: h5py.File, path: Path, missing: list[Any], has_version: bool) -> None:
    if missing or not has_version:
        raise SessionError(f"{path} is not a rigctl session file (missing {missing or ['schema_version']})")
    with _reading(path, "the schema_version attribute"):
        version = int(np.asarray(f.attrs["schema_version"]).reshape(-1)[0])
    if version > SCHEMA_VERSION:
        raise SessionError(f"{path} has schema_version {version}, newer than this rigctl ({SCHEMA_VERSION})")
    for name, kind in (("plan", h5py.Dataset), ("trials", h5py.Group), ("protocol", h5py.Group)):
        with _reading(path, f"/{name}"):
            ok = isinstance(f.get(name), kind)
        if not ok:
            raise SessionError(f"{path}: /{name} is not an HDF5 {kind.__name__.lower()}; not a rigctl session file")


#: ``/plan`` fields every reader relies on (schema 1-3)
_PLAN_REQUIRED = ("trial_id", "texture", "speed_mm_s", "force_g", "duration_s", "status")


def _check_plan(plan: np.ndarray, path: Path) -> None:
    """Refuse a ``/plan`` that cannot be read unambiguously: not a table of one row per trial, a required field
    missing, a trial id listed twice, a status outside ``status_enum``. Raises SessionError naming the problem."""
    names = plan.dtype.names or ()
    missing = [k for k in _PLAN_REQUIRED if k not in names]
    if plan.ndim != 1 or missing:
        raise SessionError(f"{path}: /plan is not a plan table ({'missing ' + ', '.join(missing) if missing else f'{plan.ndim}-d'})")
    for k in ("trial_id", "status"):
        if plan.dtype[k].kind not in "iu":
            raise SessionError(f"{path}: /plan field {k!r} is {plan.dtype[k]}, not an integer")
    ids = plan["trial_id"].astype(np.int64)
    if ids.size and ids.min() < 0:
        raise SessionError(f"{path}: /plan holds a negative trial id ({int(ids.min())})")
    uniq, counts = np.unique(ids, return_counts=True)
    if uniq.size != ids.size:
        dup = uniq[counts > 1]
        raise SessionError(f"{path}: /plan lists trial {int(dup[0])} {int(counts[counts > 1][0])} times"
                           f"{f' (and {dup.size - 1} more ids twice or more)' if dup.size > 1 else ''}; a trial id "
                           "must be unique (the file is damaged or was edited): refusing to read it")
    bad = ~np.isin(plan["status"], [int(st) for st in TrialStatus])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SessionError(f"{path}: /plan gives trial {int(ids[i])} the unknown status {int(plan['status'][i])} "
                           f"(known: {STATUS_ENUM})")


@dataclass
class _Header:
    """What :func:`_read_session_header` reads: everything but the trials."""

    attrs: dict[str, Any]
    protocol_source: str
    raw_plan: np.ndarray
    layout: SensorLayout
    present: np.ndarray | None
    textures: TextureSet
    #: plan row index -> warning, for rows marked complete whose ``/trials/<id>`` group does not exist
    unrecorded: dict[int, str]


def _read_session_header(f: h5py.File, path: Path) -> _Header:
    """Read and check a session's root attributes, ``/protocol/source`` and ``/plan`` (for the reader and the
    writer alike), and find the plan rows marked complete that have no recording.

    Raises SessionError for anything malformed (:func:`_check_file`, :func:`_check_plan`, unreadable attributes,
    a malformed ``sensor_layout`` / ``texture_set``).
    """
    _check_file(f, path)
    with _reading(path, "/plan"):
        raw_plan = f["plan"][()]
    _check_plan(raw_plan, path)
    with _reading(path, "the root attributes"):
        attrs = _read_attrs(f)
    with _reading(path, "/protocol/source"):
        source = _read_text(f["protocol/source"])
    with _reading(path, "the sensor layout / texture set"):
        layout, present, textures = _file_sensor(attrs, raw_plan, path)
    with _reading(path, "the /trials group"):
        recorded = set(f["trials"].keys())
    unrecorded = {}
    for i in np.flatnonzero(raw_plan["status"] == TrialStatus.COMPLETE):
        tid = int(raw_plan["trial_id"][i])
        if f"{tid:06d}" not in recorded:
            unrecorded[int(i)] = (f"{path}: trial {tid} is marked complete in /plan but has no recording "
                                  f"(/trials/{tid:06d} is missing); it is treated as pending (a --resume records it)")
    return _Header(attrs, source, raw_plan, layout, present, textures, unrecorded)


def _legacy_layout(attrs: Mapping[str, Any], present: np.ndarray) -> SensorLayout:
    """The sensor of a schema-1/2 file whose ``channel_present`` marks only some of its 18 columns as real (the
    FabricSlide import: 16 of 18): one row of the present channels, named ``channel<k+1>`` after their column
    (FabricSlide's ``channel1`` ... ``channel16``), 1 kHz, 10-bit (those files were always resampled to that)."""
    idx = np.flatnonzero(present)
    fabricslide = str(attrs.get("kind", "")) == "fabricslide"
    return SensorLayout.grid(
        1, len(idx), 1, sample_rate_hz=PAPER_SENSOR.sample_rate_hz, adc_bits=PAPER_SENSOR.adc_bits,
        layer_names=("taxels",), receptors=("",), channel_names=[f"channel{int(k) + 1}" for k in idx],
        name=(f"FabricSlide CPM-Finger ({len(idx)} taxels)" if fabricslide
              else f"{len(idx)} present channels of {len(present)}"))


def _file_layout(attrs: Mapping[str, Any]) -> tuple[SensorLayout, np.ndarray | None]:
    """``(layout, present)``: the file's sensor and, for a schema-1/2 file with absent channels, the indices of the
    stored columns that are real (else None).

    Schema 3: the ``sensor_layout`` attribute. Schema 1/2: the paper's sensor (all those files hold 18 columns at
    1 kHz, 10-bit), unless a ``channel_present`` root attribute marks some of the 18 columns absent (FabricSlide
    imports): then :func:`_legacy_layout` of the present ones, and readers drop the absent columns.
    """
    text = attrs.get("sensor_layout")
    if text:
        layout = SensorLayout.from_json(text)
        return (PAPER_SENSOR if layout == PAPER_SENSOR else layout), None
    present = attrs.get("channel_present")
    if present is not None:
        present = np.asarray(present).astype(bool).reshape(-1)
        if present.size == PAPER_SENSOR.n_channels and present.any() and not present.all():
            return _legacy_layout(attrs, present), np.flatnonzero(present)
    return PAPER_SENSOR, None


def _file_textures(attrs: Mapping[str, Any], plan: np.ndarray) -> TextureSet:
    """Schema 3: the ``texture_set`` attribute; schema 1/2: ``texture_set_from_labels`` of the plan's labels (the
    paper's A-P set when all are A-P or the plan is empty). The paper's set is returned as :data:`PAPER_TEXTURES`
    itself (as the paper's sensor as :data:`PAPER_SENSOR`), so identity checks downstream hold."""
    text = attrs.get("texture_set")
    if text:
        textures = TextureSet.from_json(text)
        return PAPER_TEXTURES if textures == PAPER_TEXTURES else textures
    labels = [t for t in (_text(v) for v in plan["texture"].tolist()) if t.strip()]
    return texture_set_from_labels(labels) if labels else PAPER_TEXTURES


def _file_sensor(attrs: Mapping[str, Any], plan: np.ndarray, path: Path
                 ) -> tuple[SensorLayout, np.ndarray | None, TextureSet]:
    """``(layout, present, textures)`` of a session file (:func:`_file_layout`, :func:`_file_textures`), for the
    reader and the writer alike. Raises SessionError for a malformed ``sensor_layout`` / ``texture_set``."""
    try:
        layout, present = _file_layout(attrs)
        return layout, present, _file_textures(attrs, plan)
    except ValueError as exc:  # LayoutError, TextureSetError
        raise SessionError(f"{path}: {exc}") from exc

