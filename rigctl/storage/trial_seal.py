"""The seal over everything the analysis reads (issue 77 item 6), schema 4 and 5.

The trial facts (:mod:`rigctl.storage.trial_facts`) hold a SHA-256 of each trial's taxels; the rest of what the
commands read was not covered: a force trace multiplied by 100, a swapped texture label, NaN host times or a moved
force time stamp passed ``info``, ``encode`` and ``export``. So the writer also stores, in the same commit:

- ``/recording/seal``, one row per trial (:data:`SEAL_DTYPE`): the rows it is about (as its ``/recording/index``
  row), the SHA-256 of its taxels (as the facts', kept when a writer drops the facts of a file edited since its
  last commit) and of its other recording arrays' stored bytes (:data:`SEALED_ARRAYS`: ``seq``, ``flags``,
  ``host_time_s``, the force and speed traces and their times), the SHA-256 of its ``/plan`` row's labels
  (:func:`plan_digest`: texture, speed, force, duration, profile, ramp, repeat) and its repeated samples;
- the root attribute :data:`ROOT_ATTR`: per result-changing root attribute (:data:`SEALED_ROOT_ATTRS`) and the
  ``/calibration`` group, the SHA-256 of its value as h5py reads it, recomputed at the end of every commit.

The validator (:mod:`rigctl.storage.validate`) compares them with what it reads, whether or not the file's
modification time still holds the facts' seal (a plain edit moves it; the checksums still say what changed): a trial
whose arrays or labels differ from its seal row is excluded by itself (the others stay usable), a root attribute
that differs from its checksum excludes every trial, naming it. What it cannot see: an author who rewrites the
checksums too (a forgery, not an accident or a slip), and trial group attributes (rigctl reads the plan and the
recording arrays). Data stored in another file (an external link, a virtual dataset) is never the session's own:
:func:`foreign_problem`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from typing import Any

import h5py
import numpy as np

from rigctl.core.trial import TrialData, repeated_samples
from rigctl.storage import session_recording
from rigctl.storage.session_recording import GROUP, INDEX_CHUNK_ROWS

__all__ = ["ROOT_ATTR", "SEAL", "SEALED_ARRAYS", "SEALED_ROOT_ATTRS", "SEAL_DTYPE", "append", "arrays_digest",
           "foreign_problem", "plan_digest", "read_seal", "root_problem", "store_root"]

#: the seal's dataset in ``/recording``
SEAL = "seal"
#: root attribute: JSON {name: SHA-256 hex} of :data:`SEALED_ROOT_ATTRS` present and the calibration group
ROOT_ATTR = "sealed_attrs_sha256"
#: the root attributes whose change changes results (the sensor, the textures, what the import did)
SEALED_ROOT_ATTRS = ("schema_version", "kind", "sensor_layout", "texture_set", "texture_labels", "import_steps",
                     "import_flags")
#: the recording arrays a trial's ``arrays_sha256`` covers, in order (the taxels have the facts' own SHA-256)
SEALED_ARRAYS = ("seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s", "speed_time_s")
#: the plan fields a trial's ``plan_sha256`` covers (its status changes as it is recorded; these do not)
SEALED_PLAN_FIELDS = ("trial_id", "texture", "speed_mm_s", "force_g", "duration_s", "profile", "ramp_start_mm_s",
                      "ramp_end_mm_s", "repeat")
SEAL_DTYPE = np.dtype([
    ("trial_id", "<u4"),
    ("sample_start", "<i8"), ("n_samples", "<i8"),
    ("force_start", "<i8"), ("n_force", "<i8"),
    ("speed_start", "<i8"), ("n_speed", "<i8"),
    ("taxels_sha256", "u1", (32,)), ("arrays_sha256", "u1", (32,)), ("plan_sha256", "u1", (32,)),
    ("repeated_samples", "<i8"),
])
_EXTENTS = ("sample_start", "n_samples", "force_start", "n_force", "speed_start", "n_speed")


def arrays_digest(arrays: Sequence[np.ndarray]) -> bytes:
    """SHA-256 of one trial's :data:`SEALED_ARRAYS`, each in its stored type, in that order."""
    h = hashlib.sha256()
    for a in arrays:
        if a.size:  # (an empty array adds nothing; the extents say how long each is)
            h.update(np.ascontiguousarray(a).data.cast("B"))
    return h.digest()


def _plain(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace").rstrip("\x00")
    if isinstance(v, (np.floating, float)):
        f = float(np.float32(v))
        return "nan" if f != f else f
    if isinstance(v, (np.integer, int)):
        return int(v)
    return str(v)


def plan_digest(row: Any) -> bytes:
    """SHA-256 of a ``/plan`` row's labels (:data:`SEALED_PLAN_FIELDS`, the fields it has), as canonical JSON: the
    same for the row the writer holds and the row :attr:`Session.plan` reads back."""
    names = row.dtype.names or ()
    doc = [[k, _plain(row[k])] for k in SEALED_PLAN_FIELDS if k in names]
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).digest()


def _trial_arrays(data: TrialData, n_channels: int) -> list[np.ndarray]:
    return [session_recording.stored(name, getattr(data, name), n_channels) for name in SEALED_ARRAYS]


def append(f: h5py.File, rows: np.ndarray, data: Sequence[TrialData], plan_rows: Sequence[Any]) -> None:
    """Append the seal rows of trials just appended to ``/recording`` (``rows`` their index rows, ``plan_rows``
    their ``/plan`` rows as written), making ``/recording/seal`` in a file that has none (its earlier trials stay
    without: read as before)."""
    rec = f[GROUP]
    n_ch = int(rec["taxels"].shape[1])
    new = np.zeros(len(data), dtype=SEAL_DTYPE)
    for i, (d, p) in enumerate(zip(data, plan_rows)):
        tax = session_recording.stored("taxels", d.taxels, n_ch)
        new["taxels_sha256"][i] = np.frombuffer(arrays_digest([tax]), np.uint8)
        new["arrays_sha256"][i] = np.frombuffer(arrays_digest(_trial_arrays(d, n_ch)), np.uint8)
        new["plan_sha256"][i] = np.frombuffer(plan_digest(p), np.uint8)
        new["repeated_samples"][i] = repeated_samples(tax)
    for name in ("trial_id", *_EXTENTS):
        new[name] = rows[name]
    ds = rec.get(SEAL)
    if ds is None:
        ds = rec.create_dataset(SEAL, shape=(0,), maxshape=(None,), chunks=(INDEX_CHUNK_ROWS,), dtype=SEAL_DTYPE)
    start = int(ds.shape[0])
    ds.resize((start + len(new),))
    ds[start:] = new


def read_seal(f: h5py.File) -> dict[int, np.void]:
    """Trial id -> its seal row; ``{}`` without a documented ``/recording/seal``. A trial listed more than once gets
    none (which row is its is ambiguous)."""
    return session_recording.rows_by_trial(f, SEAL, SEAL_DTYPE)


def describes(row: np.void, index_row: np.void) -> bool:
    """True when seal ``row`` is about the rows ``index_row`` (its ``/recording/index`` row) gives the trial."""
    return all(int(row[k]) == int(index_row[k]) for k in _EXTENTS)


def _value_digest(v: Any) -> str:
    a = np.asarray(v)
    if a.dtype.kind == "O":
        raw = json.dumps([_plain(x) for x in a.reshape(-1)]).encode()
    elif a.dtype.kind in "SU":
        raw = str(a.reshape(-1).tolist()).encode()
    else:
        raw = a.dtype.str.encode() + repr(a.shape).encode() + np.ascontiguousarray(a).data.cast("B").tobytes()
    return hashlib.sha256(raw).hexdigest()


def _root_digests(f: h5py.File) -> dict[str, str]:
    out = {name: _value_digest(f.attrs[name]) for name in SEALED_ROOT_ATTRS if name in f.attrs}
    cal = f.get("calibration")
    if isinstance(cal, h5py.Group):
        h = hashlib.sha256()
        for k in sorted(cal.attrs):
            h.update(k.encode() + _value_digest(cal.attrs[k]).encode())
        for k in sorted(cal):
            obj = cal.get(k)
            h.update(k.encode() + (_value_digest(obj[()]).encode() if isinstance(obj, h5py.Dataset) else b"?"))
        out["calibration"] = h.hexdigest()
    return out


def store_root(f: h5py.File) -> None:
    """At the end of a commit to a schema-4/5 file: the checksums of its result-changing root attributes."""
    if session_recording.is_flat(f):
        f.attrs[ROOT_ATTR] = json.dumps(_root_digests(f), sort_keys=True)


def root_problem(f: h5py.File) -> str | None:
    """What of the sealed root attributes differs from its checksum (one line), or None (no seal: read as
    before)."""
    raw = f.attrs.get(ROOT_ATTR)
    if raw is None:
        return None
    try:
        sealed = json.loads(raw if isinstance(raw, str) else bytes(raw).decode("utf-8"))
        if not isinstance(sealed, Mapping):
            raise ValueError
    except (TypeError, ValueError):
        return f"its /{ROOT_ATTR} attribute is not the checksums rigctl writes"
    now = _root_digests(f)
    changed = sorted(k for k in set(sealed) | set(now) if sealed.get(k) != now.get(k))
    if changed:
        return (f"the session's {', '.join(changed)} differ{'s' if len(changed) == 1 else ''} from the checksum "
                "sealed at its last commit (changed since)")
    return None


def foreign_problem(parent: h5py.Group, name: str, where: str, *, views: bool = False) -> str | None:
    """``parent[name]`` not stored as this file's own data, or None: an external link, a soft link, or a virtual
    dataset (h5py's ``get_link``, ``is_virtual``, ``virtual_sources``); with ``views`` (schema 4's trial views) a
    virtual dataset is refused only when a source lies in another file. ``where``: its path for the message. A
    missing object is not this check's."""
    try:
        link = parent.get(name, getlink=True)
    except (OSError, KeyError, ValueError, RuntimeError):
        return f"{where} cannot be read"
    if link is None:
        return None
    if isinstance(link, h5py.ExternalLink):
        return f"{where} is a link into another file ({link.filename}), not the session's own data"
    if isinstance(link, h5py.SoftLink):
        return f"{where} is a soft link ({link.path}), not the session's own data"
    try:
        obj = parent.get(name)
        if isinstance(obj, h5py.Dataset) and obj.is_virtual:
            files = sorted({m.file_name for m in obj.virtual_sources()} - {"."})
            if not views:
                return (f"{where} is a virtual dataset ({', '.join(files) or 'of this file'}), not the session's own "
                        "stored data")
            if files:
                return f"{where} is a virtual dataset of another file ({', '.join(files)}), not the session's own data"
    except (OSError, KeyError, ValueError, RuntimeError):
        return f"{where} cannot be read"
    return None
