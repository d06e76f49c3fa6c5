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
4. **Segment** (optional, ``--segment``, ``--align``, ``--pre-ms``; :mod:`rigctl.storage.segmentation` gives the
   rules): a continuous recording cut into trials, per file at that file's own level: ``fixed:SECONDS[:HOP_S]``,
   ``threshold[:LEVEL[%][:MIN_S[:SMOOTH_S]]]`` (activity runs; LEVEL a percentage of the file's own swing, default
   50 %, or counts), ``cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]]`` (press-and-slide cycles: the period checked
   against its harmonics and sub-harmonics, trials cut at each press onset minus ``--pre-ms``). Every trial records
   where it came from (``source_file``, ``source_first_sample``, ``source_last_sample``, ``cycle_index``); the
   per-file table (period, trials, rejected partial cycles) is returned and stored (``import_steps.segments``),
   files whose period or trial count is an outlier are named in ``warnings``, and a file that yields no trial is
   an error naming it.
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
    segment = "cycles"        # fixed:S | threshold[:LEVEL[%]] | cycles[:N]
    align = "onset"           # cycles: cut at each press onset (or "none": from sample 0)
    pre_ms = 100.0            # margin before each onset, ms
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
from rigctl.core.trial import REPEATED_SAMPLES_FLAG, TrialData, repeated_samples
from rigctl.storage.ledger import FLAGS_ATTR
from rigctl.storage.recording_files import (
    FORMATS,
    NAN_POLICIES,
    RecordingImportError,
    fill_nan,
    read_recording_file,
)
from rigctl.storage.segmentation import (
    Segmentation,
    SegmentSpec,
    declared_press_period,
    outlier_warnings,
    parse_segment,
    segment,
)
from rigctl.storage.time_column import gaps_text, grid_text, onto_grid

__all__ = [
    "RecordingImportError", "ImportedTrial", "ImportOptions", "FORMATS", "read_recording_file",
    "parse_label_pattern", "labels_from_name", "resample", "to_counts", "volts_step", "fill_nan", "NAN_POLICIES",
    "onto_grid", "label_ranges", "UNIT_FIELDS",
    "segment", "parse_segment", "SegmentSpec", "Segmentation", "load_mapping", "import_recordings",
    "write_imported_session", "write_session",
]

#: pattern field aliases -> plan column
_FIELD_ALIASES = {"texture": "texture", "label": "texture", "speed_mm_s": "speed_mm_s", "speed": "speed_mm_s",
                  "force_g": "force_g", "force": "force_g", "repeat": "repeat", "rep": "repeat"}
_NUMERIC = {"speed_mm_s", "force_g", "repeat"}
#: label fields that carry a unit other than the plan's: field -> (plan column, factor to the plan's unit, unit text).
#: A pattern or a mapping's per-file table may name any of them; the value is converted on import and the value as
#: given is kept as a trial attribute (``speed_as_labelled``, ``force_as_labelled``)
UNIT_FIELDS = {"speed_mm_min": ("speed_mm_s", 1 / 60, "mm/min"), "speed_m_s": ("speed_mm_s", 1000.0, "m/s"),
               "speed_cm_s": ("speed_mm_s", 10.0, "cm/s"), "speed_m_min": ("speed_mm_s", 1000 / 60, "m/min"),
               "force_N": ("force_g", 1000 / 9.80665, "N"), "force_mN": ("force_g", 1 / 9.80665, "mN"),
               "force_kg": ("force_g", 1000.0, "kg")}
_FIELD_ALIASES.update({k: v[0] for k, v in UNIT_FIELDS.items()})

#: a file imported whole (no ``--segment``) this long or longer, s, is named with the hint to segment it: a trial of
#: the rigs rigctl knows lasts seconds (FabricSlide's longest, 10 mm/s over ~475 mm: 47.5 s)
LONG_TRIAL_S = 60.0


@dataclass
class ImportedTrial:
    """One trial ready to write: ``counts`` (n_samples, n_channels) uint16 ADC counts at the session's rate, plan
    ``labels`` (texture, speed_mm_s, force_g, repeat; repeat may be None) and trial ``attrs``."""

    counts: np.ndarray
    labels: dict[str, Any]
    attrs: dict[str, Any] = field(default_factory=dict)


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
    m = rx.match(Path(base).stem) or rx.match(base)  # a pattern without an extension never takes it as a field
    if not m:
        shown = pattern if isinstance(pattern, str) else pattern.pattern
        raise RecordingImportError(f"file name {base!r} does not match the label pattern {shown!r}")
    out: dict[str, Any] = {}
    for key, value in m.groupdict().items():
        out.update(_label_value(key, value))
    return out


def _label_value(key: str, value: Any) -> dict[str, Any]:
    """One label field as plan columns: aliases resolved, units converted (:data:`UNIT_FIELDS`; the value as given
    kept as ``<speed|force>_as_labelled``)."""
    col = _FIELD_ALIASES.get(key, key)
    if key in UNIT_FIELDS:
        _, factor, unit = UNIT_FIELDS[key]
        return {col: float(value) * factor, col.split("_")[0] + "_as_labelled": f"{float(value):g} {unit}"}
    if col == "repeat":
        return {col: int(float(value))}
    if col in _NUMERIC:
        return {col: float(value)}
    return {col: value}


def label_ranges(plan_labels: Iterable[Mapping[str, Any]]) -> dict[str, list[float] | None]:
    """``{"speed_mm_s": [min, max] | None, "force_g": [min, max] | None}`` of the finite labels (in the plan's
    units, after :data:`UNIT_FIELDS`' conversions)."""
    rows = list(plan_labels)
    out: dict[str, list[float] | None] = {}
    for col in ("speed_mm_s", "force_g"):
        v = np.array([float(lab.get(col, math.nan)) for lab in rows], np.float64)
        v = v[np.isfinite(v)]
        out[col] = [float(v.min()), float(v.max())] if v.size else None
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
    VREF``, ATmega328P datasheet, "ADC Conversion Result"), ``rint(x / step)``. Counts: ``rint(x * scale +
    offset)``. Values outside the range (volts at or above the reference, a resampling's overshoot, another ADC's
    counts) raise RecordingImportError naming how many, unless ``clip`` (``--clip``: pinned to the range and
    counted; clipping loses information, so it is only done when asked for by name). Returns ``(counts, n_clipped)``.
    """
    adc_max = (1 << int(adc_bits)) - 1
    if volts_ref is not None:
        if not volts_ref > 0:
            raise RecordingImportError(f"--volts-ref must be > 0, got {volts_ref}")
        y = np.rint(np.asarray(x, np.float64) / volts_step(float(volts_ref), adc_bits))
    else:
        y = np.rint(np.asarray(x, np.float64) * float(scale) + float(offset))
    bad = (y < 0) | (y > adc_max)
    n_bad = int(bad.sum())
    if n_bad and not clip:
        what = f"volts {np.asarray(x).min():g}..{np.asarray(x).max():g} (--volts-ref {volts_ref:g} V)" \
            if volts_ref is not None else f"values {y.min():g}..{y.max():g}"
        raise RecordingImportError(
            f"{where}: {what}: {n_bad} of {y.size} values are outside the {adc_bits}-bit ADC range 0..{adc_max}: "
            "give the right --bits, --volts-ref for volts, or scale/offset in the mapping; or --clip to pin them "
            "to the range (counted)")
    return np.clip(y, 0, adc_max).astype(np.uint16), n_bad


def volts_step(volts_ref: float, adc_bits: int) -> float:
    """Volts per ADC count: ``volts_ref / 2**adc_bits`` (5 V, 10 bits: 4.883 mV; 0x3FF is VREF minus one LSB:
    ATmega328P datasheet, "ADC Conversion Result")."""
    return float(volts_ref) / float(1 << int(adc_bits))


# ----------------------------------------------------------------------------------------------------- mapping
def load_mapping(path: str | os.PathLike[str] | None) -> dict[str, Any]:
    """Read a TOML mapping (see the module docstring). Raises RecordingImportError on a missing or bad file."""
    if path is None:
        return {}
    import stat
    import tomllib

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise RecordingImportError(f"mapping {path}: not a regular file (a device, a FIFO or a folder): give the "
                                       "mapping's TOML file")
        with open(path, "rb") as fh:
            raw = fh.read(MAX_MAPPING_BYTES + 1)  # bounded: --mapping /dev/zero (or a wrong big file) is refused
        if len(raw) > MAX_MAPPING_BYTES:
            raise RecordingImportError(f"mapping {path}: larger than {MAX_MAPPING_BYTES >> 20} MB: not a mapping "
                                       "(a TOML file of a few KiB)")
        doc = tomllib.loads(raw.decode("utf-8"))
    except FileNotFoundError:
        raise RecordingImportError(f"mapping {path}: no such file") from None
    except UnicodeDecodeError:
        raise RecordingImportError(f"mapping {path}: not UTF-8 text (not a TOML mapping)") from None
    except tomllib.TOMLDecodeError as exc:
        raise RecordingImportError(f"mapping {path}: not valid TOML ({exc})") from None
    unknown = sorted(set(doc) - set(MAPPING_KEYS))
    if unknown:
        raise RecordingImportError(f"mapping {path}: unknown key(s) {', '.join(unknown)}; the keys are "
                                   f"{', '.join(MAPPING_KEYS)}")
    return doc


#: the largest mapping read, bytes (per-file labels of thousands of files fit easily)
MAX_MAPPING_BYTES = 16 << 20

#: keys a TOML mapping may hold (module docstring)
MAPPING_KEYS = ("rate_hz", "channels", "layout", "sensor", "adc_bits", "volts_ref", "scale", "offset",
                "label_pattern", "resample_hz", "segment", "align", "pre_ms", "min_swing", "press_period_s", "nan", "variable", "columns",
                "time_column", "time_unit", "repeated_stamps", "clip", "close_gaps", "defaults", "files", "texture_set")


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
        profile = str(lab.get("profile", "") or "constant")  # a label pattern's {profile} (a profile export's names)
        key = (lab["texture"], speed, force, profile)
        rep = lab.get("repeat")
        if rep is None:
            rep = counters.get(key, 0)
            counters[key] = rep + 1
        plan.append({"trial_id": i, "texture": str(lab["texture"]), "speed_mm_s": speed, "force_g": force,
                     "duration_s": t.counts.shape[0] / layout.sample_rate_hz, "profile": profile,
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
    opening of the file. Raises FileExistsError when ``out`` exists without ``overwrite``; SessionWriteError when
    the disk refuses (one line; an import has no ``--resume``: it says to run the import again)."""
    from rigctl.storage.session import SessionWriteError, SessionWriter

    done, writer = False, None
    try:
        writer = SessionWriter.create(out, plan=plan, layout=layout, textures=textures, protocol_name=protocol_name,
                                      protocol_format="none", rig_config=dict(rig_config or {}), kind=kind,
                                      overwrite=overwrite, attrs=dict(attrs or {}))
        writer.write_trials(items)
        done = True
    except SessionWriteError as exc:  # the writer's hint is acquisition's (--resume), which an import has not
        text = str(exc).split("; ", 1)[0]
        raise SessionWriteError(f"{text}; the partial output was removed (an import is written whole or not at "
                                "all): free space and run the import again", exc.errno, []) from None
    finally:
        if writer is None:
            pass
        elif done:
            writer.close()
        else:  # a full disk, Ctrl-C, a file refused mid-way: the file this import made is removed (only it: an
            writer.discard()  # --overwrite's old session stays, rigctl.storage.sidecars)


@dataclass(frozen=True)
class ImportOptions:
    """Every setting of an import (the module docstring's steps), the command line's over the mapping's.

    Built by :meth:`resolve`; the field names are the mapping's keys (``segment`` parsed into a
    :class:`rigctl.storage.segmentation.SegmentSpec`, ``files`` as ``per_file``).
    """

    rate_hz: float | None = None
    channels: int | None = None
    layout: str | None = None
    sensor: Mapping[str, Any] | None = None
    label_pattern: str | None = None
    resample_hz: float | None = None
    segment: SegmentSpec | None = None
    volts_ref: float | None = None
    adc_bits: int = 10
    nan: str = "refuse"
    scale: float = 1.0
    offset: float = 0.0
    #: the user said how readings map to counts (``scale``/``offset`` given, or ``volts_ref``): fractional readings
    #: are then rounded after the mapping; otherwise they are refused (rounding volts to counts loses them)
    mapped: bool = False
    variable: str | None = None
    columns: Sequence[Any] | None = None
    time_column: Any = None
    #: the time column's unit (``s``, ``ms``, ``us``, ``ns``; None: its name's, rigctl.storage.time_column)
    time_unit: str | None = None
    #: repeated time stamps: "refuse" or "keep-first" (the rows dropped counted in the import steps)
    repeated_stamps: str = "refuse"
    #: values outside the ADC range are pinned to it (counted, said) instead of refused
    clip: bool = False
    #: gaps inside a trial's time stamps (a CSV time column, an NWB series', an XDF stream's, frames lost) are
    #: closed (interpolated across or joined back to back: declared in the ledger) instead of refused
    close_gaps: bool = False
    #: the rig's press period, s (--press-period-s): cycles' presses are counted against it (else against rigctl's
    #: press finder); a file's own (the mapping's ``[files."NAME"]`` or an NPZ's ``press_period_s``) goes first
    press_period_s: float | None = None
    per_file: Mapping[str, Any] = field(default_factory=dict)
    defaults: Mapping[str, Any] = field(default_factory=dict)
    texture_set: Mapping[str, Any] | None = None

    @classmethod
    def resolve(cls, mapping: str | os.PathLike[str] | Mapping[str, Any] | None = None, *,
                texture: str | None = None, segment_spec: str | None = None, align: str | None = None,
                pre_ms: float | None = None, min_swing: float | None = None, **given: Any) -> "ImportOptions":
        """Options from a TOML mapping (path or loaded dict) and command-line values (``given``: the field names;
        None = not given). Raises RecordingImportError for a bad mapping, layout or segmentation."""
        m = dict(mapping) if isinstance(mapping, Mapping) else load_mapping(mapping)

        def pick(key: str, default: Any = None) -> Any:
            value = given.get(key)
            return value if value is not None else m.get(key, default)

        defaults = dict(m.get("defaults", {}) or {})
        if texture:
            defaults["texture"] = texture
        channels, layout = pick("channels"), pick("layout")
        if layout and channels is None:
            try:
                channels = parse_layout(layout).n_channels
            except LayoutError as exc:
                raise RecordingImportError(str(exc)) from None
        segment = parse_segment(segment_spec or m.get("segment"), align=align or m.get("align"),
                                pre_ms=pre_ms if pre_ms is not None else m.get("pre_ms"),
                                min_swing=min_swing if min_swing is not None else m.get("min_swing"))
        scale, offset = pick("scale"), pick("offset")
        return cls(rate_hz=pick("rate_hz"), channels=channels, layout=layout, sensor=m.get("sensor"),
                   label_pattern=pick("label_pattern"), resample_hz=pick("resample_hz"), segment=segment,
                   volts_ref=pick("volts_ref"), adc_bits=int(pick("adc_bits", 10)), nan=pick("nan", "refuse"),
                   scale=float(1.0 if scale is None else scale), offset=float(0.0 if offset is None else offset),
                   mapped=scale is not None or offset is not None or pick("volts_ref") is not None,
                   variable=pick("variable"), columns=pick("columns"), time_column=pick("time_column"),
                   time_unit=pick("time_unit"), repeated_stamps=pick("repeated_stamps", "refuse"),
                   clip=bool(pick("clip", False)), close_gaps=bool(pick("close_gaps", False)),
                   press_period_s=declared_press_period(pick("press_period_s"), "--press-period-s", segment),
                   per_file=m.get("files", {}) or {}, defaults=defaults, texture_set=m.get("texture_set"))

    def value_scale(self, n_clipped: int) -> dict[str, Any]:
        """The scale step's record."""
        rec: dict[str, Any] = (
            {"unit": "volts", "volts_ref": float(self.volts_ref), "formula": "rint(v / (volts_ref / 2**adc_bits))"}
            if self.volts_ref is not None else
            {"unit": "counts", "scale": self.scale, "offset": self.offset, "formula": "rint(x * scale + offset)"})
        return {**rec, "adc_bits": self.adc_bits, "clipped_values": n_clipped}


def _file_labels(path: Path, opts: ImportOptions, rx: re.Pattern[str] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The labels step for one file: plan labels (texture, speed_mm_s, force_g, repeat, profile) from the defaults, the
    pattern and the mapping's ``[files."NAME"]`` table, and the pattern's other fields."""
    plan_fields = ("texture", "profile", *_NUMERIC)  # profile: a profile export's names (rigctl export trials)
    labels = {k: v for k, v in opts.defaults.items() if _FIELD_ALIASES.get(k, k) in plan_fields}
    extra: dict[str, Any] = {}
    if rx is not None:
        got = labels_from_name(path.name, rx)
        labels.update({k: v for k, v in got.items() if k in plan_fields})
        extra.update({k: v for k, v in got.items() if k not in plan_fields})
    for key in (path.name, path.stem, str(path)):
        if key in opts.per_file:
            for k, v in opts.per_file[key].items():
                if k == "press_period_s":  # the rig's, not a label (_Import.rig_period)
                    continue
                labels.update(_label_value(k, v) if k in UNIT_FIELDS or k in _FIELD_ALIASES else {k: v})
    moved = {k: v for k, v in labels.items() if k.endswith("_as_labelled")}
    extra.update(moved)
    return {_FIELD_ALIASES.get(k, k): v for k, v in labels.items() if k not in moved}, extra


@dataclass
class _Import:
    """The state of one import across its files: the trials so far, the steps' records, the per-file table."""

    opts: ImportOptions
    #: --skip-bad: a file whose trials do not follow its presses one by one is refused (left out, named)
    skip_bad: bool = False
    trials: list[ImportedTrial] = field(default_factory=list)
    steps: dict[str, Any] = field(default_factory=lambda: {"read": [], "resampling": None, "value_scale": None,
                                                           "segmentation": None})
    rows: list[dict[str, Any]] = field(default_factory=list)
    #: lines for the user beyond the outlier table's: refused files (skip_bad), long unsegmented files
    notes: list[str] = field(default_factory=list)
    out_rate: float | None = None
    n_ch: int | None = None
    n_clipped: int = 0
    sensor_from_file: Mapping[str, Any] | None = None  # an NWB file's own sensor description (rigctl exports it)
    regridded: bool = False  # a time column put a file onto the rate grid (linear interpolation: no overshoot)

    def add_file(self, path: Path, rx: re.Pattern[str] | None) -> None:
        """Read, label, resample, scale and segment one file; its trials join :attr:`trials`."""
        o = self.opts
        blocks, file_rate, meta = read_recording_file(path, channels=o.channels, variable=o.variable,
                                                      columns=o.columns, time_column=o.time_column, nan=o.nan,
                                                      whole_counts=o.volts_ref is None and not o.mapped,
                                                      time_unit=o.time_unit)
        src_rate = float(o.rate_hz) if o.rate_hz is not None else file_rate
        if src_rate is None and "time_s" in meta:
            src_rate = 0.0  # from the time column (onto_grid)
        elif src_rate is None or not src_rate > 0:
            raise RecordingImportError(f"{path}: no sample rate: give --rate HZ (or rate_hz in the mapping)")
        labels, extra = _file_labels(path, o, rx)
        block_labels = meta.pop("block_labels", None)
        file_sensor = meta.pop("sensor", None)
        if file_sensor is not None and self.sensor_from_file is None:
            self.sensor_from_file = file_sensor
        if block_labels and not labels.get("texture"):
            labels["texture"] = "?"  # each block has its own (below)
        if not labels.get("texture"):
            raise RecordingImportError(f"{path}: no texture label: give --label-pattern, --texture or a mapping")
        labels["texture"] = str(labels["texture"])
        times = meta.pop("time_s", None)
        self.regridded = times is not None
        if times is not None:
            blocks[0], src_rate, grid = onto_grid(blocks[0], times, o.rate_hz, str(path),
                                                  unit=meta["time_column"]["unit"], repeated=o.repeated_stamps)
            meta["time_grid"] = grid
            self.notes.append(grid_text(path.name, grid))
            self.regridded = True
        self._name_choices(path, meta)
        self._name_gaps(path, meta)
        self.steps["read"].append({"file": str(path), **meta, "rate_hz": src_rate, "blocks": len(blocks)})
        attrs = {"source_file": path.name, "source_format": meta["format"], "source_rate_hz": src_rate,
                 **{k: str(v) for k, v in extra.items()}}
        rig = self.rig_period(path, meta)
        for bi, block in enumerate(blocks):
            lab = dict(labels)
            if block_labels:
                lab.update({k: (str(v) if k == "texture" else float(v)) for k, v in block_labels[bi].items()})
            self._add_block(path, bi, len(blocks), self._counts(path, block, src_rate), lab,
                            {**attrs, **({"source_block": bi} if len(blocks) > 1 else {})}, rig)

    def rig_period(self, path: Path, meta: Mapping[str, Any]) -> tuple[float | None, str]:
        """The rig's press period for ``path``, s, and where it was declared: the file's own (the mapping's
        ``[files."NAME"] press_period_s``, else an NPZ's ``press_period_s``), else the import's (--press-period-s,
        the mapping's ``press_period_s``); None when nobody declared it."""
        for key in (path.name, path.stem, str(path)):
            own = (self.opts.per_file.get(key) or {}).get("press_period_s")
            if own is not None:
                where = f'the mapping\'s [files."{key}"]'
                return declared_press_period(own, f"{path}: {where} press_period_s"), where
        if meta.get("press_period_s") is not None:
            return declared_press_period(meta["press_period_s"], f"{path}: press_period_s"), \
                f"{path.name}'s press_period_s"
        return self.opts.press_period_s, "--press-period-s"

    def _name_gaps(self, path: Path, meta: dict[str, Any]) -> None:
        """Refuse the holes inside a trial that an NWB series' or an XDF stream's own time stamps or a CSV time
        column show, and the frames rigctl's XDF stream lost (closing them changes the timing: never silently),
        unless ``close_gaps`` (``--close-gaps``); then name them (the samples around them joined back to back or,
        for a time column, interpolated across: declared in the ledger)."""
        gaps, lost = meta.get("gaps") or [], int(meta.get("lost_frames") or 0)
        grid_gaps = (meta.get("time_grid") or {}).get("gaps") or []
        if not self.opts.close_gaps and (gaps or lost or grid_gaps):
            said = [f"{len(gaps or grid_gaps)} gap(s) in the time stamps ({gaps_text(gaps or grid_gaps)})"
                    if gaps or grid_gaps else "", f"{lost} frame(s) lost (the stream's frame numbers skip)" if lost
                    else ""]
            raise RecordingImportError(
                f"{path}: {'; '.join(x for x in said if x)} inside a trial: closing them changes the timing: cut the "
                f"file at the gap, or give --close-gaps to {'interpolate across' if grid_gaps else 'join'} them "
                "(declared in the import's ledger)")
        if gaps:
            self.notes.append(f"{path.name}: {len(gaps)} gap(s) in the time stamps ({gaps_text(gaps)}): the samples "
                              "on either side are joined back to back (--close-gaps; in the ledger)")
        if lost:
            self.notes.append(f"{path.name}: {lost} frame(s) lost (the stream's frame numbers skip): the frames on "
                              "either side are joined back to back (--close-gaps; in the ledger)")

    def _name_choices(self, path: Path, meta: dict[str, Any]) -> None:
        """Name what was chosen for the user: the series of a file that holds several, a CSV's unusual dialect."""
        candidates = meta.get("candidates") or []
        if len(candidates) > 1:
            self.notes.append(f"{path.name}: read {meta['variable']!r} of {', '.join(candidates)} (choose with "
                              "--variable)")
        dialect = meta.get("csv") or {}
        said = ["decimal comma" if dialect.get("decimal") == "," else "",
                "a trailing delimiter dropped" if dialect.get("trailing_delimiter") else ""]
        if any(said):
            self.notes.append(f"{path.name}: read as {dialect['delimiter']!r}-separated, "
                              + ", ".join(x for x in said if x))

    def _counts(self, path: Path, block: np.ndarray, src_rate: float) -> np.ndarray:
        """Resample and scale steps: one block as uint16 counts at the import's one output rate."""
        o, x, rate = self.opts, block, src_rate
        if self.n_ch is None:
            self.n_ch = block.shape[1]
        elif block.shape[1] != self.n_ch:
            raise RecordingImportError(f"{path}: {block.shape[1]} channels, earlier files have {self.n_ch}")
        if o.resample_hz:
            x, rs = resample(x, src_rate, float(o.resample_hz))
            rate = rs["to_hz"]
            self.steps["resampling"] = dict(rs)
        if self.out_rate is None:
            self.out_rate = rate
        elif not math.isclose(self.out_rate, rate, rel_tol=1e-9):
            raise RecordingImportError(f"{path}: {rate:g} Hz, earlier files are {self.out_rate:g} Hz: give --resample")
        held = repeated_samples(block)
        if held > REPEATED_SAMPLES_FLAG * block.shape[0]:  # a board or logger that held its reading: named
            self.notes.append(f"{path.name}: {held} of {block.shape[0]} samples repeat the one before on all "
                              f"{block.shape[1]} channels (a held reading? counted per trial: rigctl info)")
        counts, clipped = to_counts(x, o.adc_bits, volts_ref=o.volts_ref, scale=o.scale, offset=o.offset,
                                    clip=o.clip, where=str(path))
        self.n_clipped += clipped
        if clipped:  # asked for by name (--clip), and said
            self.notes.append(f"{path.name}: {clipped} of {counts.size} values clipped to the {o.adc_bits}-bit range "
                              f"0..{(1 << o.adc_bits) - 1} (--clip)")
        return counts

    def _add_block(self, path: Path, bi: int, n_blocks: int, counts: np.ndarray, labels: dict[str, Any],
                   attrs: dict[str, Any], rig: tuple[float | None, str] = (None, "")) -> None:
        """Segment step: the block's trials, each with its provenance (file, first and last sample, cycle); ``rig``:
        the rig's press period, s, and where it was declared (:meth:`rig_period`)."""
        spec, rate = self.opts.segment, float(self.out_rate or 0.0)
        try:
            cut = segment(counts, rate, spec, rig_period_s=rig[0], rig_period_from=rig[1])
        except RecordingImportError as exc:
            raise RecordingImportError(f"{path}: {exc}") from None
        if spec is None and counts.shape[0] >= LONG_TRIAL_S * rate > 0:
            self.notes.append(f"{path.name}: one trial of {counts.shape[0] / rate:.0f} s: a continuous recording? "
                              "try --segment cycles (press-and-slide cycles) or --segment threshold")
        if spec is not None:
            self.steps["segmentation"] = spec.record()
            name = path.name if n_blocks == 1 else f"{path.name}[{bi}]"
            self.rows.append(cut.row(name, rate))
            if self.skip_bad and cut.press_problem:
                raise RecordingImportError(f"{path}: {cut.press_problem}")
            if not cut.bounds:
                raise RecordingImportError(
                    f"{path}: no trial found by --segment {spec.method} ({cut.rejected} partial cycles or short runs "
                    "rejected); its texture would be missing: check the file or give another --segment")
        for si, ((a, b), ci) in enumerate(zip(cut.bounds, cut.cycle_index)):
            lab = dict(labels)
            if len(cut.bounds) > 1 or n_blocks > 1:
                lab.pop("repeat", None)  # numbered per condition
            prov: dict[str, Any] = {"source_first_sample": a, "source_last_sample": b - 1}
            if spec is not None:
                prov.update({"segment_index": si, "cycle_index": ci, "segment_start_s": a / rate,
                             "segment_stop_s": b / rate})
                if cut.period_s is not None:
                    prov["cycle_period_s"] = cut.period_s
            held = repeated_samples(counts[a:b])  # counted per trial like a dropped frame (rigctl info shows it)
            self.trials.append(ImportedTrial(np.ascontiguousarray(counts[a:b]), lab,
                                             {**attrs, **prov, **({"repeated_samples": held} if held else {})}))

    def add_or_refuse(self, path: Path, rx: re.Pattern[str] | None) -> None:
        """:meth:`add_file`, or with a file refused (RecordingImportError), nothing of it kept: the file and the
        reason recorded in the session's import steps (``refused``) and named in :attr:`notes` (``--skip-bad``)."""
        kept = (len(self.trials), len(self.rows), len(self.notes), self.n_ch, self.out_rate)
        try:
            self.add_file(path, rx)
        except RecordingImportError as exc:
            del self.trials[kept[0]:], self.rows[kept[1]:], self.notes[kept[2]:]
            if not self.trials:
                self.n_ch, self.out_rate = kept[3], kept[4]
            reason = str(exc).removeprefix(f"{path}: ")
            self.steps.setdefault("refused", []).append({"file": str(path), "reason": reason})
            self.notes.append(f"refused {path.name}: {reason}")

    def layout(self) -> SensorLayout:
        """The session's sensor layout: an NWB file's own (unless the options name one), else from the options."""
        o = self.opts
        assert self.out_rate is not None and self.n_ch is not None
        if self.sensor_from_file is not None and o.sensor is None and o.layout is None and o.channels in (None, self.n_ch):
            try:
                got = SensorLayout.from_dict(dict(self.sensor_from_file)).with_rate(self.out_rate)
                if got.n_channels == self.n_ch:
                    return got
            except (TypeError, ValueError, KeyError):
                pass
        return _resolve_layout(self.n_ch, self.out_rate, channels=o.channels, layout=o.layout, sensor=o.sensor,
                               adc_bits=o.adc_bits)

    def session_attrs(self) -> dict[str, Any]:
        """The session's root attributes recording every step."""
        self.steps["value_scale"] = self.opts.value_scale(self.n_clipped)
        if self.rows:
            self.steps["segments"] = self.rows
        return {"import_steps": json.dumps(self.steps, default=str),
                "resampling": json.dumps(self.steps["resampling"] or {"method": "none"}),
                "segmentation": json.dumps(self.steps["segmentation"] or {"method": "none"}),
                "label_pattern": self.opts.label_pattern or ""}


def import_recordings(files: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], *,
                      mapping: str | os.PathLike[str] | Mapping[str, Any] | None = None,
                      options: ImportOptions | None = None, overwrite: bool = False,
                      progress: ProgressCallback | None = None, skip_bad: bool = False,
                      **given: Any) -> dict[str, Any]:
    """Import recordings (CSV, NPY/NPZ, MAT, NWB) into a session file; the steps are in the module docstring.

    Parameters
    ----------
    files : recording files (format from the extension).
    out : session file (``.h5``) to write; refused if it exists (without ``overwrite``) or is one of ``files``.
    mapping : TOML mapping path (or an already-loaded dict).
    options : the settings as an :class:`ImportOptions`; or, instead, the command line's values as keywords
        (``given``, merged over the mapping by :meth:`ImportOptions.resolve`): ``rate_hz`` (Hz; else the mapping's
        or an NWB file's), ``channels``, ``layout`` (``ROWSxCOLSxLAYERS``; default the files' column count),
        ``label_pattern``, ``texture`` (of every file nothing else labels), ``resample_hz``, ``segment_spec``
        (:func:`rigctl.storage.segmentation.parse_segment`), ``align`` ("onset" | "none"), ``pre_ms``,
        ``volts_ref`` (V: one count is V/2^bits volts), ``adc_bits`` (default 10), ``nan`` ("refuse" | "hold" |
        "interpolate").
    progress : callback receiving :class:`rigctl.core.progress.ProgressEvent` s: stage ``"reading recordings"``
        (done/total = files), then ``"writing trials"`` (done/total = trials).
    skip_bad : a file refused (RecordingImportError: no trial found, NaN refused, wrong channel count, ...) is left
        out, named in ``warnings`` and recorded with its reason in the session's import steps (``refused``), and
        the import goes on (``rigctl import --skip-bad``); refused if every file is.

    Returns
    -------
    dict: ``path``, ``n_trials``, ``samples``, ``rate_hz``, ``n_channels``, ``textures``, ``steps``,
    ``segments`` (the per-file table's rows: file, period_s, trials, rejected, first_start_s; empty without
    ``--segment``), ``warnings`` (outlier files, :func:`rigctl.storage.segmentation.outlier_warnings`; refused files;
    a file imported whole as one trial of a minute or more) and ``refused`` (``{file, reason}`` per refused file).

    Raises
    ------
    RecordingImportError (a ValueError) with one line for the user (a file that yields no trial is one, named);
    FileExistsError for an existing ``out``.
    """
    opts = options if options is not None else ImportOptions.resolve(mapping, **given)
    paths = [Path(f) for f in files]
    if not paths:
        raise RecordingImportError("no input files")
    out = Path(out)
    _check_paths(paths, out, overwrite)
    rx = parse_label_pattern(opts.label_pattern) if opts.label_pattern else None
    run = _Import(opts, skip_bad=skip_bad)
    bar = Stage(progress, "reading recordings", len(paths), unit="file")
    for path in paths:
        if skip_bad:
            run.add_or_refuse(path, rx)
        else:
            run.add_file(path, rx)
        bar.advance(1)
    if not run.trials:
        raise RecordingImportError(f"every file was refused: {'; '.join(run.notes)}")
    layout = run.layout()
    textures = TextureSet.from_dict(dict(opts.texture_set)) if opts.texture_set else None
    flags = outlier_warnings(run.rows)  # carried in the session: info, encode and analyze say them too
    summary = write_imported_session(out, run.trials, layout=layout, textures=textures, kind="imported",
                                     attrs={**run.session_attrs(), FLAGS_ATTR: json.dumps(flags)},
                                     rig_config={"source": "rigctl import", "sensor": layout.to_dict()},
                                     protocol_name="import", overwrite=overwrite, progress=progress)
    summary.update(steps=run.steps, segments=run.rows,
                   warnings=flags + run.notes,
                   label_ranges=label_ranges(t.labels for t in run.trials),
                   refused=run.steps.get("refused", []))
    return summary
