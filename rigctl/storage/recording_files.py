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

from rigctl.storage.time_column import (
    TIME_UNITS,
    TimeColumnError,
    explicit_unit,
    rising_counter,
    stamp_gaps,
    unit_of_name,
)

__all__ = ["RecordingImportError", "FORMATS", "NAN_POLICIES", "read_recording_file", "fill_nan", "check_whole_counts"]

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


#: a number written with a decimal comma (``1,73``): the CSV dialect of ``;``-separated files in much of Europe
_DECIMAL_COMMA = re.compile(r"^[-+]?\d+,\d+(?:[eE][-+]?\d+)?$")


def _sniff_dialect(line: str) -> tuple[str | None, str]:
    """(delimiter, decimal mark) of a CSV from its first line: tab, ``;`` (with a decimal comma when its cells are
    written ``1,5``), ``,``, or None for whitespace."""
    if "\t" in line:
        return "\t", "."
    if ";" in line:
        cells = [c.strip().strip('"') for c in line.split(";")]
        return ";", "," if any(_DECIMAL_COMMA.match(c) for c in cells) else "."
    if "," in line:
        return ",", "."
    return None, "."


def _csv_rows(path: Path) -> tuple[list[str], str | None, str, dict[str, Any]]:
    """The CSV's non-empty lines, its delimiter, decimal mark and dialect record (named in the import steps)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise RecordingImportError(f"{path}: not a text CSV (not UTF-8)") from None
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise RecordingImportError(f"{path}: an empty CSV")
    delim, decimal = _sniff_dialect(lines[0] if len(lines) == 1 else lines[1])
    dialect: dict[str, Any] = {"delimiter": {None: "whitespace", "\t": "tab"}.get(delim, delim), "decimal": decimal}
    if delim is not None:
        trailing = [ln.rstrip().endswith(delim) for ln in lines]
        if all(trailing[1:]) and trailing[1:]:  # every data row ends in the delimiter: an empty last column
            lines = [ln.rstrip()[:-1] if ln.rstrip().endswith(delim) else ln.rstrip() for ln in lines]
            dialect["trailing_delimiter"] = "dropped (every row ended in it: an empty last column)"
        elif any(trailing[1:]):
            n = sum(trailing[1:])
            raise RecordingImportError(f"{path}: {n} of {len(lines) - 1} rows end in the delimiter "
                                       f"{dialect['delimiter']!r}, the others do not: ragged rows; fix the file")
    return lines, delim, decimal, dialect


def _cells(line: str, delim: str | None) -> list[str]:
    return [c.strip().strip('"') for c in (line.split(delim) if delim else line.split())]


def _read_csv(path: Path, channels: int | None, columns: Sequence[Any] | None, time_column: Any,
              time_unit: str | None = None) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """(channels (n, c), the time column in seconds or None, the format record: dialect, columns, time column and
    its unit). The time column: ``time_column``, else the first whose name rigctl knows as one
    (:func:`rigctl.storage.time_column.unit_of_name`); its unit ``time_unit`` or the name's (never guessed)."""
    lines, delim, decimal, dialect = _csv_rows(path)
    first = _cells(lines[0], delim)

    def number(c: str) -> float:
        return float(c.replace(",", ".") if decimal == "," else c)

    try:
        [number(c) for c in first]
        header = None
    except ValueError:
        header = first
    rows = lines[1:] if header else lines
    if not rows:
        raise RecordingImportError(f"{path}: a header and no rows")
    widths = {len(_cells(ln, delim)) for ln in (rows[0], rows[-1], rows[len(rows) // 2])}
    if header is not None:
        widths.add(len(header))
    if len(widths) > 1:
        raise RecordingImportError(f"{path}: rows of {', '.join(map(str, sorted(widths)))} cells (delimiter "
                                   f"{dialect['delimiter']!r}): ragged rows; fix the file")
    if decimal == ",":
        rows = [ln.replace(",", ".") for ln in rows]
    try:
        data = np.loadtxt(rows, delimiter=delim, ndmin=2, dtype=np.float64, quotechar='"')
    except ValueError as exc:
        raise RecordingImportError(f"{path}: not a numeric CSV ({exc}; delimiter {dialect['delimiter']!r}, decimal "
                                   f"{decimal!r})") from None

    def index(col: Any) -> int:
        if isinstance(col, int) or (isinstance(col, str) and col.isdigit() and (header is None or col not in header)):
            i = int(col)
            if not 0 <= i < data.shape[1]:
                raise RecordingImportError(f"{path}: column {i} out of range (0..{data.shape[1] - 1})")
            return i
        if header is None or col not in header:
            raise RecordingImportError(f"{path}: no column {col!r} (header: {header})")
        return header.index(col)

    time_i = index(time_column) if time_column is not None else None
    if time_i is None and header is not None:  # a time column named as such is not a taxel, and gives the times
        named = [i for i, name in enumerate(header) if unit_of_name(name) is not None]
        time_i = named[0] if named else None
    if columns:
        keep = [index(c) for c in columns]
        if time_i is not None and time_i in keep:
            raise RecordingImportError(f"{path}: column {columns[keep.index(time_i)]!r} is both a channel "
                                       "(--columns) and the time column")
    else:
        keep = [i for i in range(data.shape[1]) if i != time_i]
        counters = [i for i in keep if rising_counter(data[:, i])]
        if counters:  # a clock or a frame counter is never a taxel unless --columns names it
            name = header[counters[0]] if header else str(counters[0])
            raise TimeColumnError(f"{path}: column {name!r} rises at every row ({data[0, counters[0]]:g} to "
                                  f"{data[-1, counters[0]]:g}): a clock or a counter, not a taxel; give it as "
                                  f"--time-column {name} --time-unit s|ms|us|ns, or list the channels with --columns")
    out = data[:, keep]
    if channels is not None and out.shape[1] != channels:
        raise RecordingImportError(f"{path}: {out.shape[1]} channel columns, but --channels {channels} (one column "
                                   "per channel; pick them with --columns and --time-column)")
    times = None
    meta: dict[str, Any] = {"csv": dialect, "columns": [header[i] if header else i for i in keep]}
    if time_i is not None:
        name = header[time_i] if header else str(time_i)
        named_unit = unit_of_name(name) if header else None
        spelled = explicit_unit(name) if header else None
        if time_unit is not None and spelled is not None and time_unit != spelled:
            raise TimeColumnError(f"{path}: the time column {name!r} says {spelled} by its name, --time-unit says "
                                  f"{time_unit}: give the unit it holds")
        unit = time_unit or named_unit
        if unit is None:
            raise TimeColumnError(f"{path}: the time column {name!r}: give its unit with --time-unit s|ms|us|ns "
                                  "(rigctl never guesses it from the numbers)")
        times = data[:, time_i] * TIME_UNITS[unit]
        meta["time_column"] = {"column": name, "unit": unit,
                               "unit_from": "--time-unit" if time_unit else "its name"}
    return out, times, meta


def _pick(arrays: Mapping[str, Any], variable: str | None, where: str) -> tuple[np.ndarray, str, list[str]]:
    """(the array, its name, the names of every numeric array): ``variable``'s, else the only one, else one named
    taxels/data/signals/readings, else the largest (named in the import's notes with the others)."""
    numeric = {k: v for k, v in arrays.items() if not k.startswith("__") and isinstance(v, np.ndarray)
               and v.dtype.kind in "biuf" and v.size > 1}
    names = sorted(numeric)
    if variable is not None:
        if variable not in arrays:
            raise RecordingImportError(f"{where}: no variable {variable!r} (has: {', '.join(names)})")
        return np.asarray(arrays[variable]), variable, names
    if not numeric:
        raise RecordingImportError(f"{where}: no numeric array in the file")
    if len(numeric) > 1:
        for name in ("taxels", "data", "signals", "readings"):
            if name in numeric:
                return numeric[name], name, names
    name = max(numeric, key=lambda k: numeric[k].size)
    return numeric[name], name, names


def _read_mat(path: Path, variable: str | None) -> tuple[np.ndarray, str, list[str]]:
    import scipy.io

    try:
        return _pick(scipy.io.loadmat(path), variable, str(path))
    except NotImplementedError:  # MATLAB v7.3: an HDF5 file
        import h5py

        with h5py.File(path, "r") as f:
            found: dict[str, Any] = {}
            f.visititems(lambda name, obj: found.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None)
            arrays = {k: v[()] for k, v in found.items() if not k.startswith("#")}
        arr, name, names = _pick(arrays, variable, str(path))
        return np.asarray(arr).T, name, names  # MATLAB stores column-major: h5py sees the transpose
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
        elif len(series) == 1:
            ts = next(iter(series.values()))
        elif series:
            shown = ", ".join(f"{k} {tuple(v.data.shape)}" for k, v in sorted(series.items()))
            raise RecordingImportError(f"{path}: {len(series)} TimeSeries ({shown}) and none named taxels: choose "
                                       "the taxels' with --variable NAME")
        else:
            raise RecordingImportError(f"{path}: no TimeSeries in the NWB file's acquisition")
        data = np.asarray(ts.data[()], dtype=np.float64)
        rate = ts.rate
        if rate is None and ts.timestamps is not None and len(ts.timestamps) > 1:
            rate = 1.0 / float(np.median(np.diff(np.asarray(ts.timestamps[()]))))
        meta = {"timeseries": ts.name, "variable": ts.name, "candidates": sorted(series), "unit": ts.unit,
                "conversion": float(ts.conversion)}
        if ts.timestamps is not None and len(ts.timestamps) > 2:  # stamped samples: a hole in them is named
            meta["gaps"] = stamp_gaps(np.asarray(ts.timestamps[()], np.float64), rate)
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
                        columns: Sequence[Any] | None = None, time_column: Any = None, nan: str = "refuse",
                        whole_counts: bool = False, time_unit: str | None = None
                        ) -> tuple[list[np.ndarray], float | None, dict[str, Any]]:
    """Read one recording file.

    Returns
    -------
    blocks : list of (n_samples, n_channels) float64 arrays (one per stacked trial; usually one)
    rate_hz : float or None, the rate the file itself states (NWB), else None
    meta : dict, format details for the session's attributes (``nan``: the policy and the values it filled)

    ``nan`` is the NaN policy (:func:`fill_nan`: refuse, hold, interpolate). ``time_unit``: a CSV time column's
    unit (:data:`rigctl.storage.time_column.TIME_UNITS`; else its name's, :class:`TimeColumnError` when neither).
    ``whole_counts``: readings that are
    not whole numbers are refused (:func:`check_whole_counts`, before NaN samples are filled).

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
        arr, times, csv_meta = _read_csv(path, channels, columns, time_column, time_unit)
        meta.update(csv_meta)
        if times is not None:
            meta["time_s"] = times
    elif fmt == "npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise RecordingImportError(f"{path}: not a plain NPY array ({exc})") from None
    elif fmt == "npz":
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arr, meta["variable"], meta["candidates"] = _pick(arrays, variable, str(path))
        if "rate_hz" in arrays and np.asarray(arrays["rate_hz"]).size == 1:
            rate = float(arrays["rate_hz"])
        if "press_period_s" in arrays and np.asarray(arrays["press_period_s"]).size == 1:  # the rig's, s
            meta["press_period_s"] = float(arrays["press_period_s"])
    elif fmt == "mat":
        arr, meta["variable"], meta["candidates"] = _read_mat(path, variable)
    elif fmt == "xdf":
        from rigctl.storage.xdf import read_xdf

        arr, rate, xdf_meta = read_xdf(path, variable, RecordingImportError)
        seq = xdf_meta.pop("frame_seq", None)
        if seq is not None and len(seq) > 1:  # rigctl's own stream: frames lost on the way, by their numbers
            skips = np.clip(np.diff(np.asarray(seq, np.int64)) - 1, 0, None)
            xdf_meta["lost_at"] = [(int(i) + 1, int(skips[i])) for i in np.flatnonzero(skips)]
        meta.update(xdf_meta)
    else:
        arr, rate, nwb_meta = _read_nwb(path, variable)
        meta.update(nwb_meta)
    blocks = _as_blocks(np.asarray(arr, dtype=np.float64), channels, str(path))
    nwb_trials = meta.pop("trials", None)
    lost_at = meta.pop("lost_at", None)
    if nwb_trials and len(blocks) == 1:  # an NWB trials table or rigctl's XDF markers: one block per trial, labelled
        blocks = [blocks[0][t["start"]:t["stop"]] for t in nwb_trials]
        meta["block_labels"] = [t["labels"] for t in nwb_trials]
        _gaps_inside(meta, [(int(t["start"]), int(t["stop"])) for t in nwb_trials], lost_at)
    elif "gaps" in meta or lost_at is not None:
        _gaps_inside(meta, [(0, blocks[0].shape[0] if blocks else 0)], lost_at)
    for b in blocks:
        if b.shape[0] < 1:
            raise RecordingImportError(f"{path}: no samples")
        if np.isinf(b).any():
            raise RecordingImportError(f"{path}: holds infinite values (at samples "
                                       f"{_first_rows(np.isinf(b))}); fix the file")
    if whole_counts:
        for b in blocks:
            check_whole_counts(b, str(path))
    filled = [fill_nan(b, nan, str(path)) for b in blocks]
    meta["nan"] = {"policy": nan, "samples": sum(n for _, n in filled)}
    return [b for b, _ in filled], rate, meta


def _gaps_inside(meta: dict[str, Any], spans: list[tuple[int, int]], lost_at: list[tuple[int, int]] | None) -> None:
    """Keep in ``meta["gaps"]`` the stamp gaps that fall inside the samples read as trials (``spans``: sample ranges;
    a gap between two trials of a trials table or rigctl's markers joins nothing), and count in
    ``meta["lost_frames"]`` the frames lost inside them (``lost_at``: (sample after the skip, frames skipped))."""
    def inside(at: int) -> bool:
        return any(a < at < b for a, b in spans)

    if "gaps" in meta:
        meta["gaps"] = [g for g in meta["gaps"] if inside(int(g.get("at_sample", 1)))]
    if lost_at is not None:
        meta["lost_frames"] = sum(n for at, n in lost_at if inside(at))


def check_whole_counts(x: np.ndarray, where: str) -> None:
    """Refuse readings that are not whole ADC counts (volts, values normalised to 0..1) unless the user said how to
    map them: rounding them to counts would change the data without a word (1.73 V -> 2)."""
    finite = x[np.isfinite(x)]
    frac = finite != np.rint(finite)
    if frac.any():
        v = float(finite[frac][0])
        raise RecordingImportError(
            f"{where}: values are not whole ADC counts ({v:g}; range {finite.min():g}..{finite.max():g}): rigctl "
            "stores counts and will not round them silently; give --volts-ref V if they are volts, or --scale S "
            "--offset O to map them to counts (counts = x * S + O, then rounded)")


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
