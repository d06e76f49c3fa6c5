"""A new session file: its image built by HDF5 in memory (:func:`new_file_image`), written to a ``<name>.creating``
sidecar and renamed into place (:func:`write_new_file`, :mod:`rigctl.storage.sidecars`), under the writer lock
(:func:`writer_lock`). Used by :meth:`rigctl.storage.session_writer.SessionWriter.create`."""

from __future__ import annotations

import contextlib
import io
import json
import os
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.provenance import PROVENANCE_ATTR, provenance_json, software_provenance
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.version import __version__
from rigctl.storage import journal, journal_replay, session_recording, sidecars
from rigctl.storage.session_format import (
    DEFAULT_SCHEMA_VERSION,
    PLAN_CHUNK_ROWS,
    STATUS_ENUM,
    SessionLocked,
    SessionWriteError,
    _attr_value,
    _os_error_text,
    _utc_now,
    taxels_description,
)


def _writer_lock(path: Path) -> journal.WriterLock:
    """The writer lock of ``path`` (:class:`rigctl.storage.journal.WriterLock`). Raises SessionLocked if another
    writer holds it, SessionWriteError if the lock file cannot be made."""
    try:
        return journal.WriterLock(path)
    except journal.WriterLockHeld as exc:
        raise SessionLocked(str(exc), exc.pid) from None
    except OSError as exc:
        raise SessionWriteError(f"cannot write {path}: {_os_error_text(exc)} (making its lock file "
                                f"{journal.lock_path(path).name}); choose a writable place", exc.errno) from None


def _new_file_image(plan_arr: np.ndarray, *, layout: SensorLayout, textures: TextureSet, protocol_source: str,
                    protocol_name: str, protocol_format: str, rig_config: Mapping[str, Any] | None, kind: str,
                    calibration: Mapping[str, Any] | None, attrs: Mapping[str, Any] | None,
                    schema_version: int = DEFAULT_SCHEMA_VERSION, compression: str | None = "gzip") -> bytes:
    """The bytes of a new session file (root attributes, ``/protocol``, ``/plan``, ``/trials``, ``/calibration``,
    and for schema 4 and 5 the empty ``/recording`` arrays), built by HDF5 in memory: HDF5 never writes to a disk that
    may be full (at a few KiB free it can crash there)."""
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs["schema_version"] = schema_version
        f.attrs["session_id"] = str(uuid.uuid4())
        f.attrs["created_utc"] = _utc_now()
        f.attrs["rigctl_version"] = __version__
        f.attrs["kind"] = kind
        f.attrs["rig_config"] = json.dumps(dict(rig_config or {}), default=str)
        f.attrs["sensor_layout"] = layout.to_json()
        f.attrs["texture_set"] = textures.to_json()
        for k, v in (attrs or {}).items():
            f.attrs[k] = _attr_value(v)
        if PROVENANCE_ATTR not in f.attrs:  # every session says what made it (the runner adds the rig's part)
            f.attrs[PROVENANCE_ATTR] = provenance_json(software_provenance(kind=kind))
        g = f.create_group("protocol")
        g.create_dataset("source", data=protocol_source, dtype=h5py.string_dtype("utf-8"))
        g.attrs["name"] = protocol_name
        g.attrs["format"] = protocol_format
        d = f.create_dataset("plan", data=plan_arr, maxshape=(None,), chunks=(PLAN_CHUNK_ROWS,))
        d.attrs["status_enum"] = json.dumps(STATUS_ENUM)
        trials = f.create_group("trials")
        trials.attrs.update(taxels_description(layout))
        if calibration:
            _write_calibration(f, calibration, layout.n_channels)
        if schema_version >= 4:
            session_recording.create(f, layout.n_channels, compression=compression)
    return buf.getvalue()


def _write_new_file(path: Path, image: bytes, *, keep_aside: bool = False) -> sidecars.Sidecar:
    """Write ``image`` to ``<name>.creating`` (a sidecar: created new, never a file or link already there), fsync
    it and rename it to ``path`` (which appears complete or not at all); with ``keep_aside`` (an ``--overwrite``:
    the old session stays until the new one's first commit, :meth:`SessionWriter._commit`) it stays aside. Returns
    the sidecar (its file closed, its folder's descriptor open; its name is ``path``'s once renamed).

    Raises SidecarExists (a usage error: something at ``<name>.creating``, left as it is), SessionWriteError
    (nothing left behind) if the disk refuses the bytes (no space, read-only).
    """
    side = sidecars.Sidecar(path.with_name(path.name + ".creating"), what="session being created")
    try:
        assert side.fd is not None
        journal_replay.pwrite(side.fd, image, 0)
        os.fsync(side.fd)
        os.fchmod(side.fd, 0o644)
        if not keep_aside:
            side.commit_to(path.name)
    except BaseException as exc:
        side.remove(committed_too=True)  # (a Ctrl-C or SIGTERM too: nothing left of a file being created)
        side.close()
        if not isinstance(exc, OSError):
            raise
        free = ""
        with contextlib.suppress(OSError):
            st = os.statvfs(path.parent)
            free = f", {st.f_bavail * st.f_frsize / 1024:.0f} KiB free"
        raise SessionWriteError(f"{_os_error_text(exc)} creating {path} ({len(image) / 1024:.0f} KiB needed{free}): "
                                "nothing was written; free space or choose another --out", exc.errno) from None
    side.close_file()  # the folder's descriptor stays: SessionWriter renames or removes the file through it
    return side


def _check_no_journal(path: Path) -> None:
    """Before a session is created at ``path``: an old session's committed journal is applied (it must never be
    replayed onto the new file); anything else at ``<name>.journal`` is refused, left as it is."""
    if path.exists():
        journal.recover(path)
    jpath = journal.journal_path(path)
    if os.path.lexists(jpath):
        raise sidecars.SidecarExists(f"{jpath} exists and is no journal of {path.name} (left as it is): move it "
                                     "away or choose another --out")


def _calibration_arrays(calibration: Mapping[str, Any], n_channels: int) -> dict[str, Any]:
    """``taxel_min``/``taxel_max`` of ``calibration`` as float64 arrays. Raises ValueError unless ``(n_channels,)``."""
    out = {}
    for k in ("taxel_min", "taxel_max"):
        if k in calibration:
            arr = np.asarray(calibration[k], dtype=np.float64)
            if arr.shape != (n_channels,):
                raise ValueError(f"calibration {k} must have shape ({n_channels},) (one value per channel of the "
                                 f"session's sensor), got {arr.shape}")
            out[k] = arr
    return out


def _write_calibration(f: h5py.File, calibration: Mapping[str, Any], n_channels: int) -> None:
    arrays = _calibration_arrays(calibration, n_channels)
    if "calibration" in f:
        del f["calibration"]
    g = f.create_group("calibration")
    for k, v in calibration.items():
        if k in arrays:
            g.create_dataset(k, data=arrays[k]).attrs["unit"] = "ADC counts"
        else:
            g.attrs[k] = _attr_value(v)


