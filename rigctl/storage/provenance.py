"""Reading a file's provenance (:mod:`rigctl.core.provenance`): sessions and encoded files keep it as the
``provenance`` root attribute (JSON), an NWB export in ``/scratch/rigctl_provenance`` (NWB's place for data outside
its schema), each with the provenance of the files it was made from nested (``source_session``, ``encoded``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from rigctl.core.provenance import PROVENANCE_ATTR, RESUMED_ATTR

__all__ = ["NWB_PROVENANCE", "ProvenanceError", "read_provenance"]

#: where an NWB export keeps rigctl's provenance (a scratch dataset of JSON text)
NWB_PROVENANCE = "scratch/rigctl_provenance"


class ProvenanceError(ValueError):
    """The file is not one rigctl wrote, or holds no provenance (written before it was recorded)."""


def _text(v: Any) -> str:
    if isinstance(v, bytes):
        return v.decode()
    if hasattr(v, "shape") and getattr(v, "shape", None) == ():
        v = v[()]
        return v.decode() if isinstance(v, bytes) else str(v)
    return str(v)


def read_provenance(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The provenance of the rigctl file ``path`` (session, encoded or NWB) as a dict, with ``session_id`` (a
    session's UUID, when the file has one) added when the provenance itself lacks it, and ``resumed`` (the list of
    :data:`rigctl.core.provenance.RESUMED_ATTR`: each resuming run's time, trials complete before it, provenance)
    for a resumed session.

    Raises
    ------
    FileNotFoundError; ProvenanceError (not HDF5, or no provenance: a file written before rigctl recorded it).
    """
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ProvenanceError(f"{path} is not an HDF5 file rigctl wrote ({exc})") from None
    with f:
        text: Any = f.attrs.get(PROVENANCE_ATTR)
        if text is None and NWB_PROVENANCE in f:
            text = f[NWB_PROVENANCE][()]
        if text is None:
            raise ProvenanceError(f"{path} holds no provenance (written before rigctl recorded it, or not by rigctl)")
        try:
            out: dict[str, Any] = json.loads(_text(text))
        except ValueError as exc:
            raise ProvenanceError(f"{path}: its provenance is not valid JSON ({exc})") from None
        sid = f.attrs.get("session_id")
        if sid is not None:
            out.setdefault("session_id", _text(sid))
        resumed = f.attrs.get(RESUMED_ATTR)
        if resumed is not None:  # a resumed session: each resuming run's provenance, oldest first
            try:
                out["resumed"] = json.loads(_text(resumed))
            except ValueError as exc:
                raise ProvenanceError(f"{path}: its {RESUMED_ATTR} is not valid JSON ({exc})") from None
    return out
