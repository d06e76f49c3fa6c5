"""Reading other labs' recording files: CSV, NPY/NPZ, MATLAB .mat, NWB, XDF (:mod:`rigctl.storage.xdf`) ->
``(n_samples, n_channels)`` blocks.

The first step of ``rigctl import`` (:mod:`rigctl.storage.importers`, whose module docstring describes every format
rule): :func:`read_recording_file` reads one file into float64 blocks (one per stacked trial), the rate the file
states (NWB) and format details; NaN samples are handled by :func:`fill_nan` (``--nan refuse|hold|interpolate``).

Errors are :class:`RecordingImportError` (a ValueError) with one line naming the file and what to change.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["RecordingImportError", "FORMATS", "NAN_POLICIES", "read_recording_file", "fill_nan"]

#: extension -> format name
FORMATS = {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".npy": "npy", ".npz": "npz", ".mat": "mat",
           ".nwb": "nwb", ".xdf": "xdf"}


class RecordingImportError(ValueError):
    """A recording that cannot be imported as asked (unreadable file, wrong shape, values out of range, ...)."""


# ----------------------------------------------------------------------------------------------------- reading
def _orient(arr: np.ndarray, channels: int | None, where: str) -> np.ndarray:
    """``(n_samples, n_channels)`` from a 1-D or 2-D array (transposed when needed)."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in "biuf":
        raise RecordingImportError(f"{where}: expected a numeric array, got dtype {arr.dtype}")
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise RecordingImportError(f"{where}: expected a (n_samples, n_channels) array, got shape {arr.shape}")
    if channels is not None:
        if arr.shape[1] == channels:
            return arr
        if arr.shape[0] == channels:
            return arr.T
        raise RecordingImportError(f"{where}: shape {arr.shape} has no axis of {channels} channels (--channels)")
    return arr.T if arr.shape[0] < arr.shape[1] else arr


def _as_blocks(arr: np.ndarray, channels: int | None, where: str) -> list[np.ndarray]:
    arr = np.asarray(arr)
    if arr.ndim == 3:  # stacked trials (n_trials, n_samples, n_channels)
        return [_orient(a, channels, f"{where}[{i}]") for i, a in enumerate(arr)]
    return [_orient(arr, channels, where)]


_TIME_NAME = re.compile(r"^(time|timestamp|timestamps|t|time_s|time_ms|seconds)$", re.I)


def _sniff_delimiter(line: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in line:
            return d
    return None


def _read_csv(path: Path, channels: int | None, columns: Sequence[Any] | None, time_column: Any) -> np.ndarray:
    with open(path, encoding="utf-8-sig") as fh:
        first = fh.readline()
    delim = _sniff_delimiter(first)
    cells = [c.strip().strip('"') for c in (first.split(delim) if delim else first.split())]
    try:
        [float(c) for c in cells]
        header = None
    except ValueError:
        header = cells
    try:
        data = np.loadtxt(path, delimiter=delim, skiprows=1 if header else 0, ndmin=2, dtype=np.float64,
                          encoding="utf-8-sig")
    except ValueError as exc:
        raise RecordingImportError(f"{path}: not a numeric CSV ({exc})") from None

    def index(col: Any) -> int:
        if isinstance(col, int) or (isinstance(col, str) and col.isdigit() and (header is None or col not in header)):
            i = int(col)
            if not 0 <= i < data.shape[1]:
                raise RecordingImportError(f"{path}: column {i} out of range (0..{data.shape[1] - 1})")
            return i
        if header is None or col not in header:
            raise RecordingImportError(f"{path}: no column {col!r} (header: {header})")
        return header.index(col)

    if columns:
        keep = [index(c) for c in columns]
    else:
        skip = {index(time_column)} if time_column is not None else set()
        if time_column is None and header is not None:  # a time column named as such is not a taxel
            skip |= {i for i, name in enumerate(header) if _TIME_NAME.match(name)}
        keep = [i for i in range(data.shape[1]) if i not in skip]
    out = data[:, keep]
    if channels is not None and out.shape[1] != channels:
        raise RecordingImportError(f"{path}: {out.shape[1]} channel columns, but --channels {channels} (one column "
                                   "per channel; pick columns with 'columns' / 'time_column' in the mapping)")
    return out


def _pick(arrays: Mapping[str, Any], variable: str | None, where: str) -> np.ndarray:
    numeric = {k: v for k, v in arrays.items() if not k.startswith("__") and isinstance(v, np.ndarray)
               and v.dtype.kind in "biuf" and v.size > 1}
    if variable is not None:
        if variable not in arrays:
            raise RecordingImportError(f"{where}: no variable {variable!r} (has: {', '.join(sorted(numeric))})")
        return np.asarray(arrays[variable])
    if not numeric:
        raise RecordingImportError(f"{where}: no numeric array in the file")
    if len(numeric) > 1:
        for name in ("taxels", "data", "signals", "readings"):
            if name in numeric:
                return numeric[name]
    return max(numeric.values(), key=lambda a: a.size)


def _read_mat(path: Path, variable: str | None) -> np.ndarray:
    import scipy.io

    try:
        return _pick(scipy.io.loadmat(path), variable, str(path))
    except NotImplementedError:  # MATLAB v7.3: an HDF5 file
        import h5py

        with h5py.File(path, "r") as f:
            found: dict[str, Any] = {}
            f.visititems(lambda name, obj: found.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None)
            arrays = {k: v[()] for k, v in found.items() if not k.startswith("#")}
        arr = _pick(arrays, variable, str(path))
        return np.asarray(arr).T  # MATLAB stores column-major: h5py sees the transpose
    except ValueError as exc:
        if isinstance(exc, RecordingImportError):
            raise
        raise RecordingImportError(f"{path}: not a MATLAB file ({exc})") from None


def _read_nwb(path: Path, variable: str | None) -> tuple[np.ndarray, float | None, dict[str, Any]]:
    try:
        from pynwb import NWBHDF5IO, TimeSeries
    except ImportError as exc:  # pragma: no cover - pynwb is a dependency
        raise RecordingImportError(f"{path}: reading NWB needs pynwb ({exc})") from None
    with NWBHDF5IO(str(path), "r") as io:
        nwb = io.read()
        series = {}
        for container in (nwb.acquisition, nwb.processing):
            for name, obj in container.items():
                if isinstance(obj, TimeSeries):
                    series[name] = obj
        if variable is not None:
            if variable not in series:
                raise RecordingImportError(f"{path}: no TimeSeries {variable!r} (has: {', '.join(sorted(series))})")
            ts = series[variable]
        elif "taxels" in series:  # a file rigctl exported (rigctl.storage.nwb)
            ts = series["taxels"]
        elif series:
            ts = series[sorted(series)[0]]
        else:
            raise RecordingImportError(f"{path}: no TimeSeries in the NWB file's acquisition")
        data = np.asarray(ts.data[()], dtype=np.float64)
        rate = ts.rate
        if rate is None and ts.timestamps is not None and len(ts.timestamps) > 1:
            rate = 1.0 / float(np.median(np.diff(np.asarray(ts.timestamps[()]))))
        meta = {"timeseries": ts.name, "unit": ts.unit, "conversion": float(ts.conversion)}
        if rate and nwb.trials is not None and ts.name == "taxels":
            meta["trials"] = _nwb_trials(nwb.trials.to_dataframe(), float(ts.starting_time or 0.0), float(rate),
                                         data.shape[0])
        device = nwb.devices.get("taxel_sensor") if nwb.devices else None
        if device is not None and ts.name == "taxels":
            try:
                meta["sensor"] = json.loads(device.description)
            except (TypeError, ValueError):
                pass
    return data, (float(rate) if rate else None), meta


def _nwb_trials(table: Any, start_s: float, rate: float, n: int) -> list[dict[str, Any]] | None:
    """The trials of an NWB trials table as sample ranges of the TimeSeries with their labels, or None when the rows
    do not fall inside the series."""
    out = []
    for _, row in table.iterrows():
        a = int(round((float(row["start_time"]) - start_s) * rate))
        b = int(round((float(row["stop_time"]) - start_s) * rate))
        if not 0 <= a < b <= n:
            return None
        labels = {k: row[k] for k in ("texture", "speed_mm_s", "force_g") if k in row.index}
        out.append({"start": a, "stop": b, "labels": labels})
    return out or None


def read_recording_file(path: str | os.PathLike[str], *, channels: int | None = None, variable: str | None = None,
                        columns: Sequence[Any] | None = None, time_column: Any = None, nan: str = "refuse"
                        ) -> tuple[list[np.ndarray], float | None, dict[str, Any]]:
    """Read one recording file.

    Returns
    -------
    blocks : list of (n_samples, n_channels) float64 arrays (one per stacked trial; usually one)
    rate_hz : float or None, the rate the file itself states (NWB), else None
    meta : dict, format details for the session's attributes (``nan``: the policy and the values it filled)

    ``nan`` is the NaN policy (:func:`fill_nan`: refuse, hold, interpolate).

    Raises
    ------
    RecordingImportError for an unknown extension, an unreadable file, an array that is not 1-3-D numeric,
    infinite values, or NaN values under ``nan="refuse"`` (the count and first sample indices named).
    """
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise RecordingImportError(f"{path}: unknown format {path.suffix!r} (known: {', '.join(sorted(FORMATS))})")
    if not path.is_file():
        raise RecordingImportError(f"{path}: {'a folder, not a recording file' if path.is_dir() else 'no such file'}")
    rate = None
    meta: dict[str, Any] = {"format": fmt}
    if fmt == "csv":
        arr = _read_csv(path, channels, columns, time_column)
    elif fmt == "npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise RecordingImportError(f"{path}: not a plain NPY array ({exc})") from None
    elif fmt == "npz":
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arr = _pick(arrays, variable, str(path))
        if "rate_hz" in arrays and np.asarray(arrays["rate_hz"]).size == 1:
            rate = float(arrays["rate_hz"])
    elif fmt == "mat":
        arr = _read_mat(path, variable)
    elif fmt == "xdf":
        from rigctl.storage.xdf import read_xdf

        arr, rate, xdf_meta = read_xdf(path, variable, RecordingImportError)
        xdf_meta.pop("frame_seq", None)
        meta.update(xdf_meta)
    else:
        arr, rate, nwb_meta = _read_nwb(path, variable)
        meta.update(nwb_meta)
    blocks = _as_blocks(np.asarray(arr, dtype=np.float64), channels, str(path))
    nwb_trials = meta.pop("trials", None)
    if nwb_trials and len(blocks) == 1:  # an NWB trials table or rigctl's XDF markers: one block per trial, labelled
        blocks = [blocks[0][t["start"]:t["stop"]] for t in nwb_trials]
        meta["block_labels"] = [t["labels"] for t in nwb_trials]
    for b in blocks:
        if b.shape[0] < 1:
            raise RecordingImportError(f"{path}: no samples")
        if np.isinf(b).any():
            raise RecordingImportError(f"{path}: holds infinite values (at samples "
                                       f"{_first_rows(np.isinf(b))}); fix the file")
    filled = [fill_nan(b, nan, str(path)) for b in blocks]
    meta["nan"] = {"policy": nan, "samples": sum(n for _, n in filled)}
    return [b for b, _ in filled], rate, meta


#: what ``--nan`` may say: refuse (default), hold the last good sample, interpolate linearly between good samples
NAN_POLICIES = ("refuse", "hold", "interpolate")


def _first_rows(bad: np.ndarray, k: int = 5) -> str:
    """The first ``k`` sample indices (0-based rows) where ``bad`` (n, c) holds, as text."""
    rows = np.flatnonzero(bad.any(axis=1))
    return ", ".join(str(int(r)) for r in rows[:k]) + (", ..." if rows.size > k else "")


def fill_nan(x: np.ndarray, policy: str, where: str = "") -> tuple[np.ndarray, int]:
    """NaN samples of ``(n, c)`` readings handled by ``policy`` (:data:`NAN_POLICIES`).

    ``refuse``: RecordingImportError naming ``where``, the NaN count and the first sample indices. ``hold``: each
    NaN takes the channel's last good value (leading NaNs the first good one). ``interpolate``: linear between the
    channel's good neighbours (``numpy.interp``; the ends hold). Returns ``(readings, n_nan_values)``; a channel with
    no good value is refused under every policy.
    """
    if policy not in NAN_POLICIES:
        raise RecordingImportError(f"--nan {policy!r}: use {' | '.join(NAN_POLICIES)}")
    bad = np.isnan(x)
    n_bad = int(bad.sum())
    if not n_bad:
        return x, 0
    if policy == "refuse":
        raise RecordingImportError(f"{where}: {n_bad} NaN values in {int(bad.any(axis=1).sum())} samples (first at "
                                   f"samples {_first_rows(bad)}); give --nan hold or --nan interpolate")
    empty = np.flatnonzero(bad.all(axis=0))
    if empty.size:
        raise RecordingImportError(f"{where}: channel {int(empty[0])} holds only NaN; nothing to fill it from")
    out = np.array(x, dtype=np.float64, copy=True)
    idx = np.arange(x.shape[0])
    for c in np.flatnonzero(bad.any(axis=0)):
        good = ~bad[:, c]
        if policy == "interpolate":
            out[:, c] = np.interp(idx, idx[good], x[good, c])
        else:
            last = np.maximum.accumulate(np.where(good, idx, -1))
            last[last < 0] = int(np.flatnonzero(good)[0])
            out[:, c] = x[last, c]
    return out, n_bad
