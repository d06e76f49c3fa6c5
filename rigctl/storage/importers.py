"""Any recording in: read taxel recordings from other labs and write them as a session file.

``rigctl import FILES... --rate HZ [--channels N] [--layout RxCxL] [--label-pattern P] [--resample HZ]
[--segment ...] [--mapping MAP.toml] [--volts-ref V] --out SESSION.h5`` is :func:`import_recordings`.

Steps, each explicit and recorded in the session's root attributes (``import_steps``, JSON):

1. **Read** (format from the extension): ``.csv`` (one column per channel; a header row is detected and skipped;
   ``columns`` / ``time_column`` in the mapping pick columns by name or 0-based index; a header column named
   ``time``/``timestamp``/``t`` is not a channel), ``.npy`` / ``.npz``
   (a ``(n_samples, n_channels)`` array, or ``(n_trials, n_samples, n_channels)`` for stacked trials; in an NPZ the
   array named by ``variable`` or the only / largest one; a scalar ``rate_hz`` in it gives the rate), MATLAB ``.mat``
   (``scipy.io.loadmat``; v7.3 files through h5py, transposed back from MATLAB's column-major order), NWB
   (``.nwb``, a ``TimeSeries`` read with pynwb; its ``rate`` is used when no rate is given). Arrays are turned to
   ``(n_samples, n_channels)`` (a ``(channels, n)`` array is transposed when the channel count says so, or when it
   has more columns than rows). NaN samples (``--nan``): refused by default with the count and the first sample
   indices, or held (last good value) or linearly interpolated per channel (:func:`fill_nan`); the count is recorded.
2. **Resample** (optional, ``--resample HZ``): ``scipy.signal.resample_poly`` (polyphase FIR, Kaiser window,
   ``padtype="line"``) by the rational factor ``up/down`` closest to ``resample_hz / rate_hz``.
3. **Scale** to ADC counts at the layout's bits: counts as given (``x * scale + offset``, rounded; mapping keys
   ``scale``/``offset``), or volts with a reference ``V``: one count is ``V / 2**bits`` volts (the AVR ADC's
   ``ADC = Vin * 1024 / VREF``, ATmega328P datasheet, "ADC Conversion Result": 0x3FF is VREF minus one LSB), so
   ``counts = rint(x / (V / 2**bits))``; ``V`` itself is one step past the top count and stored as ``2**bits - 1``. Values outside
   ``0 .. 2**bits - 1`` are refused with one clear error for raw counts; after resampling or volts scaling they
   are clipped and the clipped count recorded.
4. **Segment** (optional, ``--segment``): a continuous recording cut into trials: ``fixed:SECONDS[:HOP_S]``,
   ``threshold:LEVEL[:MIN_S[:SMOOTH_S]]`` (activity = max over channels of ``|counts - channel median|``,
   moving-averaged over SMOOTH_S (0.05 s); runs above LEVEL counts lasting at least MIN_S (0.2 s) are trials),
   ``cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]]`` (the period from the autocorrelation peak of the channel-mean
   signal: the shortest lag whose peak reaches 90 % of the highest; trials of N periods, default 1).
5. **Label**: ``texture``, ``speed_mm_s``, ``force_g``, ``repeat`` from the file name by ``--label-pattern``
   (``{texture}__V{speed_mm_s}__{rep}.csv``; aliases ``label``, ``speed``, ``force``, ``rep``; other fields become
   trial attributes), from the mapping's ``[files."NAME"]`` tables, ``[defaults]`` or ``--texture``. Missing speed
   or force = NaN. Without a repeat, trials of the same condition are numbered 0, 1, ... in input order.
6. **Write** through :class:`rigctl.storage.session.SessionWriter` with the sensor layout (rate = the output rate)
   and the texture set (the mapping's ``[texture_set]``, else the sorted distinct labels).

The TOML mapping may give every command-line value (command-line values win)::

    rate_hz = 100.0
    channels = 9              # or layout = "3x3x1", or a full [sensor] table (SensorLayout.to_dict())
    adc_bits = 10
    volts_ref = 3.3           # the inputs are volts; omit for counts
    scale = 1.0               # counts = x * scale + offset (counts only)
    offset = 0.0
    label_pattern = "{texture}__V{speed_mm_s}__{rep}.csv"
    resample_hz = 1000.0
    segment = "fixed:2.0"
    nan = "interpolate"       # NaN samples: refuse (default) | hold | interpolate
    variable = "taxels"       # array / TimeSeries name in NPZ, MAT, NWB
    columns = ["t1", "t2"]    # CSV channel columns, in channel order (names or 0-based indices)
    time_column = "time"      # a CSV column that is not a channel
    [defaults]
    texture = "felt"
    [files."run3.csv"]
    texture = "silk"
    speed_mm_s = 20
    [texture_set]
    textures = ["felt", "silk"]
    groups = { natural = ["felt", "silk"] }

Errors are :class:`RecordingImportError` (a ValueError) with one line naming the file and what to change.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.sensor import LayoutError, SensorLayout, parse_layout
from rigctl.core.textures import TextureSet, texture_set_from_labels
from rigctl.core.trial import TrialData

__all__ = [
    "RecordingImportError", "ImportedTrial", "FORMATS", "read_recording_file", "parse_label_pattern",
    "labels_from_name", "resample", "to_counts", "volts_step", "fill_nan", "NAN_POLICIES", "segment",
    "parse_segment", "load_mapping", "import_recordings", "write_imported_session", "write_session",
]

#: extension -> format name
FORMATS = {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".npy": "npy", ".npz": "npz", ".mat": "mat",
           ".nwb": "nwb"}

#: pattern field aliases -> plan column
_FIELD_ALIASES = {"texture": "texture", "label": "texture", "speed_mm_s": "speed_mm_s", "speed": "speed_mm_s",
                  "force_g": "force_g", "force": "force_g", "repeat": "repeat", "rep": "repeat"}
_NUMERIC = {"speed_mm_s", "force_g", "repeat"}


class RecordingImportError(ValueError):
    """A recording that cannot be imported as asked (unreadable file, wrong shape, values out of range, ...)."""


@dataclass
class ImportedTrial:
    """One trial ready to write: ``counts`` (n_samples, n_channels) uint16 ADC counts at the session's rate, plan
    ``labels`` (texture, speed_mm_s, force_g, repeat; repeat may be None) and trial ``attrs``."""

    counts: np.ndarray
    labels: dict[str, Any]
    attrs: dict[str, Any] = field(default_factory=dict)


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
    else:
        arr, rate, nwb_meta = _read_nwb(path, variable)
        meta.update(nwb_meta)
    blocks = _as_blocks(np.asarray(arr, dtype=np.float64), channels, str(path))
    nwb_trials = meta.pop("trials", None)
    if nwb_trials and len(blocks) == 1:  # an NWB trials table: one block per trial, labelled
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


# ----------------------------------------------------------------------------------------------------- labels
def parse_label_pattern(pattern: str) -> re.Pattern[str]:
    """Compile ``{texture}__V{speed_mm_s}__{rep}.csv`` into a regular expression with named groups.

    Numeric fields (speed, force, repeat) match signed decimals; other fields match the shortest text. Literal
    text matches itself. Raises RecordingImportError for a pattern with no field or a repeated field.
    """
    parts = re.split(r"\{(\w+)\}", pattern)
    out, seen = [], set()
    for i, part in enumerate(parts):
        if i % 2 == 0:
            out.append(re.escape(part))
            continue
        if part in seen:
            raise RecordingImportError(f"label pattern {pattern!r} names {{{part}}} twice")
        seen.add(part)
        if _FIELD_ALIASES.get(part) in _NUMERIC:
            out.append(rf"(?P<{part}>[-+]?\d+(?:\.\d+)?)")
        else:
            out.append(rf"(?P<{part}>.+?)")
    if not seen:
        raise RecordingImportError(f"label pattern {pattern!r} names no field (e.g. {{texture}})")
    return re.compile("^" + "".join(out) + "$")


def labels_from_name(name: str, pattern: str | re.Pattern[str]) -> dict[str, Any]:
    """Labels of a file name (the base name, or the stem if the pattern has no extension).

    Returns ``{"texture": str, "speed_mm_s": float, "force_g": float, "repeat": int, <other fields>: str}`` with
    only the fields the pattern names. Raises RecordingImportError when the name does not match.
    """
    rx = parse_label_pattern(pattern) if isinstance(pattern, str) else pattern
    base = Path(name).name
    m = rx.match(base) or rx.match(Path(base).stem)
    if not m:
        shown = pattern if isinstance(pattern, str) else pattern.pattern
        raise RecordingImportError(f"file name {base!r} does not match the label pattern {shown!r}")
    out: dict[str, Any] = {}
    for key, value in m.groupdict().items():
        col = _FIELD_ALIASES.get(key, key)
        if col == "repeat":
            out[col] = int(float(value))
        elif col in _NUMERIC:
            out[col] = float(value)
        else:
            out[col] = value
    return out


# ----------------------------------------------------------------------------------------------------- processing
def resample(x: np.ndarray, rate_hz: float, resample_hz: float) -> tuple[np.ndarray, dict[str, Any]]:
    """Resample ``(n, c)`` readings from ``rate_hz`` to ``resample_hz`` with ``scipy.signal.resample_poly``.

    Returns the resampled float64 array (``ceil(n * up / down)`` rows) and the step's record
    ``{"method", "from_hz", "to_hz", "up", "down"}``. The factor is the fraction closest to the rate ratio with a
    denominator <= 1000; the stored rate is ``rate_hz * up / down``.
    """
    from scipy.signal import resample_poly

    ratio = Fraction(float(resample_hz) / float(rate_hz)).limit_denominator(1000)
    up, down = ratio.numerator, ratio.denominator
    step = {"method": "scipy.signal.resample_poly (Kaiser FIR, padtype=line)", "from_hz": float(rate_hz),
            "to_hz": float(rate_hz) * up / down, "up": up, "down": down}
    if up == down:
        return np.asarray(x, np.float64), step
    y = resample_poly(np.asarray(x, np.float64), up, down, axis=0, padtype="line")
    return y, step


def to_counts(x: np.ndarray, adc_bits: int, *, volts_ref: float | None = None, scale: float = 1.0,
              offset: float = 0.0, clip: bool = False, where: str = "") -> tuple[np.ndarray, int]:
    """Readings -> ADC counts ``0 .. 2**adc_bits - 1`` (uint16).

    Volts (``volts_ref`` given): one count is ``volts_ref / 2**adc_bits`` V (the AVR ADC's ``ADC = Vin * 1024 /
    VREF``, ATmega328P datasheet, "ADC Conversion Result"), ``rint(x / step)``, clipped. Counts:
    ``rint(x * scale + offset)``;
    values outside the range raise RecordingImportError unless ``clip`` (after resampling). Returns
    ``(counts, n_clipped)``.
    """
    adc_max = (1 << int(adc_bits)) - 1
    if volts_ref is not None:
        if not volts_ref > 0:
            raise RecordingImportError(f"--volts-ref must be > 0, got {volts_ref}")
        y = np.rint(np.asarray(x, np.float64) / volts_step(float(volts_ref), adc_bits))
        clip = True
    else:
        y = np.rint(np.asarray(x, np.float64) * float(scale) + float(offset))
    bad = (y < 0) | (y > adc_max)
    n_bad = int(bad.sum())
    if n_bad and not clip:
        raise RecordingImportError(
            f"{where}: values {y.min():g}..{y.max():g} are outside the {adc_bits}-bit ADC range 0..{adc_max}: give "
            "the right --bits, --volts-ref for volts, or scale/offset in the mapping")
    return np.clip(y, 0, adc_max).astype(np.uint16), n_bad


def volts_step(volts_ref: float, adc_bits: int) -> float:
    """Volts per ADC count: ``volts_ref / 2**adc_bits`` (5 V, 10 bits: 4.883 mV; 0x3FF is VREF minus one LSB:
    ATmega328P datasheet, "ADC Conversion Result")."""
    return float(volts_ref) / float(1 << int(adc_bits))


def parse_segment(spec: str | None) -> dict[str, Any] | None:
    """``fixed:S[:HOP]`` | ``threshold:LEVEL[:MIN_S[:SMOOTH_S]]`` | ``cycles[:N[:MIN_P[:MAX_P]]]`` -> dict.
    Raises RecordingImportError on anything else."""
    if not spec:
        return None
    kind, *args = str(spec).strip().split(":")
    try:
        vals = [float(a) for a in args if a != ""]
    except ValueError:
        raise RecordingImportError(f"--segment {spec!r}: the values after the method must be numbers") from None
    if kind == "fixed" and 1 <= len(vals) <= 2 and all(v > 0 for v in vals):
        return {"method": "fixed", "length_s": vals[0], "hop_s": vals[1] if len(vals) > 1 else vals[0]}
    if kind == "threshold" and 1 <= len(vals) <= 3 and all(v >= 0 for v in vals):
        return {"method": "threshold", "level_counts": vals[0], "min_s": vals[1] if len(vals) > 1 else 0.2,
                "smooth_s": vals[2] if len(vals) > 2 else 0.05}
    if kind == "cycles" and len(vals) <= 3 and all(v > 0 for v in vals):
        return {"method": "cycles", "n_cycles": int(vals[0]) if vals else 1,
                "min_period_s": vals[1] if len(vals) > 1 else None, "max_period_s": vals[2] if len(vals) > 2 else None}
    raise RecordingImportError(f"--segment {spec!r}: use fixed:SECONDS[:HOP_S], threshold:LEVEL[:MIN_S[:SMOOTH_S]] "
                               "or cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]]")


def _cycle_period(x: np.ndarray, rate_hz: float, min_p: float | None, max_p: float | None) -> int:
    sig = x.astype(np.float64).mean(axis=1)
    sig = sig - sig.mean()
    n = sig.size
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    spec = np.fft.rfft(sig, nfft)
    ac = np.fft.irfft(spec * np.conj(spec), nfft)[:n]
    if ac[0] <= 0:
        raise RecordingImportError("cycles: the recording is constant, no cycle to detect")
    ac = ac / ac[0]
    ac = ac * n / (n - np.arange(n))  # unbiased: long lags are not penalised
    lo = max(1, int(round((min_p or 0.0) * rate_hz)))
    hi = min(n // 2, int(round(max_p * rate_hz)) if max_p else n // 2)
    if min_p is None:  # start after the first zero crossing (the central lobe is not a period)
        neg = np.flatnonzero(ac[1:hi] < 0)
        if not neg.size:
            raise RecordingImportError("cycles: no periodic structure found (give MIN_PERIOD_S:MAX_PERIOD_S)")
        lo = int(neg[0]) + 1
    if hi <= lo + 1:
        raise RecordingImportError("cycles: the recording is too short for the period range")
    seg = ac[lo:hi]
    # the shortest lag whose local peak reaches 90 % of the highest: multiples of the period peak as high
    peaks = np.flatnonzero((seg[1:-1] >= seg[:-2]) & (seg[1:-1] >= seg[2:])) + 1
    best = float(seg.max())
    good = peaks[seg[peaks] >= 0.9 * best] if peaks.size else np.array([int(np.argmax(seg))])
    return lo + int(good[0] if good.size else np.argmax(seg))


def segment(counts: np.ndarray, rate_hz: float, spec: dict[str, Any] | None
            ) -> tuple[list[tuple[int, int]], dict[str, Any]]:
    """Cut a continuous ``(n, c)`` recording into trials; returns ``[(start, stop), ...]`` sample ranges and the
    step's record (``period_s`` for cycles). ``spec`` None: the whole recording is one trial."""
    n = counts.shape[0]
    if spec is None:
        return [(0, n)], {}
    rec = dict(spec)
    if spec["method"] == "fixed":
        length = int(round(spec["length_s"] * rate_hz))
        hop = int(round(spec["hop_s"] * rate_hz))
        if length < 1 or hop < 1:
            raise RecordingImportError(f"segment length {spec['length_s']} s is under one sample at {rate_hz:g} Hz")
        return [(s, s + length) for s in range(0, n - length + 1, hop)], rec
    if spec["method"] == "threshold":
        x = counts.astype(np.float64)
        act = np.abs(x - np.median(x, axis=0)).max(axis=1)
        w = max(1, int(round(spec["smooth_s"] * rate_hz)))
        act = np.convolve(act, np.ones(w) / w, mode="same")
        on = np.concatenate(([False], act > spec["level_counts"], [False]))
        edges = np.flatnonzero(np.diff(on.astype(np.int8)))
        runs = list(zip(edges[::2].tolist(), edges[1::2].tolist()))
        min_n = max(1, int(round(spec["min_s"] * rate_hz)))
        return [(a, b) for a, b in runs if b - a >= min_n], rec
    period = _cycle_period(counts, rate_hz, spec.get("min_period_s"), spec.get("max_period_s"))
    length = period * int(spec["n_cycles"])
    rec["period_s"] = period / rate_hz
    return [(s, s + length) for s in range(0, n - length + 1, length)], rec


# ----------------------------------------------------------------------------------------------------- mapping
def load_mapping(path: str | os.PathLike[str] | None) -> dict[str, Any]:
    """Read a TOML mapping (see the module docstring). Raises RecordingImportError on a missing or bad file."""
    if path is None:
        return {}
    import tomllib

    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise RecordingImportError(f"mapping {path}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise RecordingImportError(f"mapping {path}: not valid TOML ({exc})") from None
    unknown = sorted(set(doc) - set(MAPPING_KEYS))
    if unknown:
        raise RecordingImportError(f"mapping {path}: unknown key(s) {', '.join(unknown)}; the keys are "
                                   f"{', '.join(MAPPING_KEYS)}")
    return doc


#: keys a TOML mapping may hold (module docstring)
MAPPING_KEYS = ("rate_hz", "channels", "layout", "sensor", "adc_bits", "volts_ref", "scale", "offset",
                "label_pattern", "resample_hz", "segment", "nan", "variable", "columns", "time_column", "defaults", "files",
                "texture_set")


def _resolve_layout(n_channels: int, rate_hz: float, *, channels: int | None, layout: str | None,
                    sensor: Mapping[str, Any] | None, adc_bits: int) -> SensorLayout:
    try:
        if sensor:
            out = SensorLayout.from_dict({**dict(sensor), "sample_rate_hz": rate_hz,
                                          "adc_bits": sensor.get("adc_bits", adc_bits)})
        elif layout:
            out = parse_layout(layout, sample_rate_hz=rate_hz, adc_bits=adc_bits)
        else:
            out = SensorLayout.for_channels(channels or n_channels, sample_rate_hz=rate_hz, adc_bits=adc_bits)
    except LayoutError as exc:
        raise RecordingImportError(str(exc)) from None
    if channels is not None and out.n_channels != channels:
        raise RecordingImportError(f"layout {out.shape_text} has {out.n_channels} channels, --channels says {channels}")
    if out.n_channels != n_channels:
        raise RecordingImportError(f"the recordings have {n_channels} channels but the layout {out.shape_text} has "
                                   f"{out.n_channels}")
    return out


# ----------------------------------------------------------------------------------------------------- writing
def _check_paths(inputs: Iterable[Path], out: Path, overwrite: bool) -> None:
    out_r = out.resolve()
    for p in inputs:
        if Path(p).resolve() == out_r:
            raise RecordingImportError(f"--out {out} is one of the input files; choose another output")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; choose another --out or pass --overwrite")


def write_imported_session(out: str | os.PathLike[str], trials: Sequence[ImportedTrial], *, layout: SensorLayout,
                           textures: TextureSet | None = None, kind: str = "recorded", attrs: Mapping[str, Any] | None = None,
                           rig_config: Mapping[str, Any] | None = None, protocol_name: str = "import",
                           overwrite: bool = False, progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Write ``trials`` as a session file (plan in input order) through ``SessionWriter.create(..., layout=,
    textures=)``. Repeats missing from the labels are numbered per (texture, speed, force) condition.

    ``progress`` receives :class:`rigctl.core.progress.ProgressEvent` s (stage ``"writing trials"``).

    Returns ``{"path", "n_trials", "samples", "rate_hz", "n_channels", "textures"}``.
    Raises FileExistsError (``out`` exists, no ``overwrite``), RecordingImportError (no trials).
    """
    if not trials:
        raise RecordingImportError("nothing to import: no trials (check the files and --segment)")
    counters: dict[tuple[Any, ...], int] = {}
    plan = []
    for i, t in enumerate(trials):
        lab = t.labels
        speed, force = float(lab.get("speed_mm_s", math.nan)), float(lab.get("force_g", math.nan))
        key = (lab["texture"], speed, force)
        rep = lab.get("repeat")
        if rep is None:
            rep = counters.get(key, 0)
            counters[key] = rep + 1
        plan.append({"trial_id": i, "texture": str(lab["texture"]), "speed_mm_s": speed, "force_g": force,
                     "duration_s": t.counts.shape[0] / layout.sample_rate_hz, "profile": "constant",
                     "repeat": int(rep)})
    if textures is None:
        textures = texture_set_from_labels(p["texture"] for p in plan)
    samples = 0
    bar = Stage(progress, "writing trials", len(trials))

    def items() -> Iterator[Any]:
        nonlocal samples
        for i, t in enumerate(trials):
            samples += t.counts.shape[0]
            yield i, TrialData(taxels=t.counts, layout=layout, attrs=dict(t.attrs))
            bar.advance(1)

    write_session(out, plan, items(), layout=layout, textures=textures, kind=kind, attrs=attrs,
                  rig_config=rig_config, protocol_name=protocol_name, overwrite=overwrite)
    return {"path": str(out), "n_trials": len(trials), "samples": samples, "rate_hz": layout.sample_rate_hz,
            "n_channels": layout.n_channels, "textures": list(textures.labels)}


def write_session(out: str | os.PathLike[str], plan: Sequence[Mapping[str, Any]], items: Iterable[tuple[int, TrialData]], *,
                  layout: SensorLayout, textures: TextureSet, kind: str = "recorded", attrs: Mapping[str, Any] | None = None,
                  rig_config: Mapping[str, Any] | None = None, protocol_name: str = "import", overwrite: bool = False) -> None:
    """Create the session (``SessionWriter.create(out, plan=, layout=, textures=, ...)``) and write ``items``
    (``(trial_id, TrialData)`` pairs, produced lazily: a large import never holds every trial in memory) in one
    opening of the file. Raises FileExistsError when ``out`` exists without ``overwrite``."""
    from rigctl.storage.session import SessionWriter

    writer = SessionWriter.create(out, plan=plan, layout=layout, textures=textures, protocol_name=protocol_name,
                                  protocol_format="none", rig_config=dict(rig_config or {}), kind=kind,
                                  overwrite=overwrite, attrs=dict(attrs or {}))
    writer.write_trials(items)


def import_recordings(files: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], *,
                      rate_hz: float | None = None,
                      channels: int | None = None, layout: str | None = None, label_pattern: str | None = None,
                      texture: str | None = None, resample_hz: float | None = None, segment_spec: str | None = None,
                      mapping: str | os.PathLike[str] | Mapping[str, Any] | None = None, volts_ref: float | None = None,
                      adc_bits: int | None = None, nan: str | None = None, overwrite: bool = False,
                      progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Import recordings (CSV, NPY/NPZ, MAT, NWB) into a session file; the steps are in the module docstring.

    Parameters
    ----------
    files : recording files (format from the extension).
    out : session file (``.h5``) to write; refused if it exists (without ``overwrite``) or is one of ``files``.
    rate_hz : the recordings' sample rate, Hz (or the mapping's ``rate_hz``, or the NWB file's rate).
    channels, layout : channel count and/or ``ROWSxCOLSxLAYERS``; default the files' column count
        (:meth:`SensorLayout.for_channels`).
    label_pattern : file-name pattern naming ``texture``, ``speed_mm_s``, ``force_g``, ``repeat`` (and others).
    texture : the texture label of every file the pattern / mapping does not label.
    resample_hz : resample to this rate (scipy.signal.resample_poly); None keeps ``rate_hz``.
    segment_spec : ``fixed:...``, ``threshold:...``, ``cycles...`` (see :func:`parse_segment`); None: a file (or a
        stacked trial) is one trial.
    mapping : TOML mapping path (or an already-loaded dict).
    volts_ref : the inputs are volts with this reference (V) -> counts at ``adc_bits``.
    adc_bits : ADC resolution of the stored counts (default 10).
    nan : NaN samples: ``refuse`` (default; the error names the file, the count and the first samples), ``hold``,
        ``interpolate`` (:func:`fill_nan`); the mapping's ``nan`` otherwise.
    progress : callback receiving :class:`rigctl.core.progress.ProgressEvent` s: stage ``"reading recordings"``
        (done/total = files), then ``"writing trials"`` (done/total = trials).

    Returns
    -------
    dict: ``path``, ``n_trials``, ``samples``, ``rate_hz``, ``n_channels``, ``textures``, ``steps``.

    Raises
    ------
    RecordingImportError (a ValueError) with one line for the user; FileExistsError for an existing ``out``.
    """
    m = dict(mapping) if isinstance(mapping, Mapping) else load_mapping(mapping)
    paths = [Path(f) for f in files]
    if not paths:
        raise RecordingImportError("no input files")
    out = Path(out)
    _check_paths(paths, out, overwrite)
    rate_hz = rate_hz if rate_hz is not None else m.get("rate_hz")
    channels = channels if channels is not None else m.get("channels")
    layout = layout or m.get("layout")
    label_pattern = label_pattern or m.get("label_pattern")
    resample_hz = resample_hz if resample_hz is not None else m.get("resample_hz")
    segment_spec = segment_spec or m.get("segment")
    volts_ref = volts_ref if volts_ref is not None else m.get("volts_ref")
    nan = nan or m.get("nan") or "refuse"
    adc_bits = int(adc_bits if adc_bits is not None else m.get("adc_bits", 10))
    scale, offset = float(m.get("scale", 1.0)), float(m.get("offset", 0.0))
    if layout and channels is None:
        try:
            channels = parse_layout(layout).n_channels
        except LayoutError as exc:
            raise RecordingImportError(str(exc)) from None
    seg = parse_segment(segment_spec)
    rx = parse_label_pattern(label_pattern) if label_pattern else None
    per_file = m.get("files", {}) or {}
    defaults = dict(m.get("defaults", {}) or {})
    if texture:
        defaults["texture"] = texture

    trials: list[ImportedTrial] = []
    steps: dict[str, Any] = {"read": [], "resampling": None, "value_scale": None, "segmentation": None}
    out_rate = None
    n_ch = None
    n_clipped = 0
    sensor_from_file = None  # an NWB file's own sensor description (rigctl exports it)
    bar = Stage(progress, "reading recordings", len(paths), unit="file")
    for path in paths:
        blocks, file_rate, meta = read_recording_file(path, channels=channels, variable=m.get("variable"),
                                                      columns=m.get("columns"), time_column=m.get("time_column"),
                                                      nan=nan)
        src_rate = float(rate_hz) if rate_hz is not None else file_rate
        if src_rate is None or not src_rate > 0:
            raise RecordingImportError(f"{path}: no sample rate: give --rate HZ (or rate_hz in the mapping)")
        labels = {k: v for k, v in defaults.items() if _FIELD_ALIASES.get(k, k) in ("texture", *_NUMERIC)}
        extra = {}
        if rx is not None:
            got = labels_from_name(path.name, rx)
            labels.update({k: v for k, v in got.items() if k in ("texture", *_NUMERIC)})
            extra.update({k: v for k, v in got.items() if k not in ("texture", *_NUMERIC)})
        for key in (path.name, path.stem, str(path)):
            if key in per_file:
                labels.update({_FIELD_ALIASES.get(k, k): v for k, v in per_file[key].items()})
        labels = {_FIELD_ALIASES.get(k, k): v for k, v in labels.items()}
        block_labels = meta.pop("block_labels", None)
        file_sensor = meta.pop("sensor", None)
        if file_sensor is not None and sensor_from_file is None:
            sensor_from_file = file_sensor
        if block_labels and not labels.get("texture"):
            labels["texture"] = "?"  # each block has its own (below)
        if not labels.get("texture"):
            raise RecordingImportError(f"{path}: no texture label: give --label-pattern, --texture or a mapping")
        labels["texture"] = str(labels["texture"])
        steps["read"].append({"file": str(path), **meta, "rate_hz": src_rate, "blocks": len(blocks)})
        for bi, block in enumerate(blocks):
            if n_ch is None:
                n_ch = block.shape[1]
            elif block.shape[1] != n_ch:
                raise RecordingImportError(f"{path}: {block.shape[1]} channels, earlier files have {n_ch}")
            x, rate = block, src_rate
            if resample_hz:
                x, rs = resample(x, src_rate, float(resample_hz))
                rate = rs["to_hz"]
                steps["resampling"] = {k: v for k, v in rs.items()}
            if out_rate is None:
                out_rate = rate
            elif not math.isclose(out_rate, rate, rel_tol=1e-9):
                raise RecordingImportError(f"{path}: {rate:g} Hz, earlier files are {out_rate:g} Hz: give --resample")
            counts, clipped = to_counts(x, adc_bits, volts_ref=volts_ref, scale=scale, offset=offset,
                                        clip=bool(resample_hz), where=str(path))
            n_clipped += clipped
            bounds, seg_rec = segment(counts, rate, seg)
            if seg is not None:
                steps["segmentation"] = {k: v for k, v in seg_rec.items() if k != "period_s"}
                steps.setdefault("segments", []).append({"file": str(path), "block": bi, "n": len(bounds),
                                                         **({"period_s": seg_rec["period_s"]}
                                                            if "period_s" in seg_rec else {})})
            for si, (a, b) in enumerate(bounds):
                lab = dict(labels)
                if block_labels:
                    lab.update({k: (str(v) if k == "texture" else float(v)) for k, v in block_labels[bi].items()})
                if len(bounds) > 1 or len(blocks) > 1:
                    lab.pop("repeat", None)  # numbered per condition
                attrs = {"source_file": path.name, "source_format": meta["format"], "source_rate_hz": src_rate,
                         **{k: str(v) for k, v in extra.items()}}
                if len(blocks) > 1:
                    attrs["source_block"] = bi
                if seg is not None:
                    attrs.update({"segment_index": si, "segment_start_s": a / rate, "segment_stop_s": b / rate})
                trials.append(ImportedTrial(np.ascontiguousarray(counts[a:b]), lab, attrs))
        bar.advance(1)
    assert out_rate is not None and n_ch is not None
    file_layout = None
    if sensor_from_file is not None and m.get("sensor") is None and layout is None and channels in (None, n_ch):
        try:
            file_layout = SensorLayout.from_dict(sensor_from_file).with_rate(out_rate)
        except (TypeError, ValueError, KeyError):
            file_layout = None
    sl = file_layout if file_layout is not None and file_layout.n_channels == n_ch else _resolve_layout(
        n_ch, out_rate, channels=channels, layout=layout, sensor=m.get("sensor"), adc_bits=adc_bits)
    steps["value_scale"] = ({"unit": "volts", "volts_ref": float(volts_ref), "formula": "rint(v / (volts_ref / 2**adc_bits))"}
                            if volts_ref is not None else
                            {"unit": "counts", "scale": scale, "offset": offset, "formula": "rint(x * scale + offset)"})
    steps["value_scale"].update({"adc_bits": adc_bits, "clipped_values": n_clipped})
    textures = None
    if m.get("texture_set"):
        textures = TextureSet.from_dict(m["texture_set"])
    attrs = {"import_steps": json.dumps(steps, default=str),
             "resampling": json.dumps(steps["resampling"] or {"method": "none"}),
             "segmentation": json.dumps(steps["segmentation"] or {"method": "none"}),
             "label_pattern": label_pattern or ""}
    summary = write_imported_session(out, trials, layout=sl, textures=textures, kind="imported", attrs=attrs,
                                     rig_config={"source": "rigctl import", "sensor": sl.to_dict()},
                                     protocol_name="import", overwrite=overwrite, progress=progress)
    summary["steps"] = steps
    return summary
