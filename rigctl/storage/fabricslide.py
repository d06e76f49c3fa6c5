"""FabricSlide recordings (real tactile data, MIT licence): loading, resampling to 1 kHz, 10-bit counts, import.

Source: Wang et al. (2022), "Fabric Classification Using a Finger-Shaped Tactile Sensor via Robotic Sliding",
Front. Neurorobot. 16:808222 (repository wngfra/FabricSlide); the subset lives in ``../shared/data/fabricslide``
(its README describes it). Files ``fabric/<Fabric>_F<force>_V<velocity>mmps_<repeat>.csv`` and
``board/Board10mm_F<force>_V<velocity>mmps_0.csv``; columns ``timestamp`` (ms, ~28 ms apart), ``proximity1``,
``proximity2`` (ignored), ``channel1`` ... ``channel16`` (bias-subtracted capacitance counts).

The FabricSlide preset of ``rigctl import`` (:func:`import_fabricslide`, command ``rigctl import-fabricslide``):
the 16 taxels as 16 channels (:data:`FABRICSLIDE_SENSOR`, channel k = ``channel<k+1>``; the CPM-Finger's taxels are
not a regular grid, so the layout is one row of 16; no padding), the fabrics and the Board10mm recordings in one
file with their texture set (:data:`FABRICSLIDE_TEXTURES`: groups ``fabric`` and ``board``).

10-bit map (deterministic, linear, documented in the session attributes): ``adc = clip(rint(counts * scale +
offset), 0, 1023)`` with ``scale = 1``, ``offset = 0`` by default: the recorded values are integer counts between
about 2 and 850, so the map keeps them exactly where no interpolation happened.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet

N_CHANNELS = 16
DEFAULT_SCALE = 1.0
DEFAULT_OFFSET = 0.0
RATE_HZ = 1000.0
FABRICS = ("BeigeCotton", "BrownCotton", "Canvas", "Linen")
BOARDS = ("Board10mm",)

#: the CPM-Finger as rigctl sees it after the import: 16 taxels in one row (not a regular grid; the source gives no
#: pitch, the 5 mm default is not a measurement), resampled to 1 kHz, 10-bit counts
FABRICSLIDE_SENSOR = SensorLayout.grid(
    1, N_CHANNELS, 1, sample_rate_hz=RATE_HZ, adc_bits=10, layer_names=("taxels",), receptors=("",),
    channel_names=[f"channel{k + 1}" for k in range(N_CHANNELS)], name="FabricSlide CPM-Finger (16 taxels)")

#: the four fabrics and the ridged board, grouped; codes are positions in this set (stable for every import)
FABRICSLIDE_TEXTURES = TextureSet.from_dict({"name": "FabricSlide", "textures": [*FABRICS, *BOARDS],
                                             "groups": {"fabric": list(FABRICS), "board": list(BOARDS)}})

_NAME = re.compile(r"^(?P<label>[A-Za-z0-9]+)_F(?P<force>\d+)_V(?P<vel>[-+]?\d+(?:\.\d+)?)mmps_(?P<rep>\d+)\.csv$")


@dataclasses.dataclass
class Recording:
    """One FabricSlide trial.

    Attributes
    ----------
    path : Path
    label : str
        Fabric name (``BeigeCotton``, ``BrownCotton``, ``Canvas``, ``Linen``) or ``Board10mm``.
    kind : {"fabric", "board"}
    force_setpoint : float
        The arm's force-loop setpoint (120-250; not newtons or grams: the loop holds the mean taxel reading).
    velocity_mm_s : float
        Signed sliding velocity, mm/s (the sign is the direction).
    repeat : int
    timestamp_ms : (n,) float64
        Sample times, ms (repeated timestamps removed, the first sample of each kept).
    readings : (n, 16) float64
        Capacitance counts of channel1 ... channel16.
    """

    path: Path
    label: str
    kind: str
    force_setpoint: float
    velocity_mm_s: float
    repeat: int
    timestamp_ms: np.ndarray
    readings: np.ndarray
    #: rows dropped for repeating the time stamp of the row before (the first of each kept)
    repeated_stamps: int = 0

    @property
    def speed_mm_s(self) -> float:
        """``abs(velocity_mm_s)``."""
        return abs(self.velocity_mm_s)

    @property
    def direction(self) -> int:
        """+1 or -1: the sign of the velocity."""
        return 1 if self.velocity_mm_s >= 0 else -1


def parse_name(name: str) -> dict[str, Any]:
    """Labels from a FabricSlide file name.

    Returns
    -------
    dict with ``label`` (str), ``force_setpoint`` (float), ``velocity_mm_s`` (float, signed), ``repeat`` (int).

    Raises
    ------
    ValueError
        If the name does not follow ``<Label>_F<force>_V<velocity>mmps_<repeat>.csv``.
    """
    m = _NAME.match(Path(name).name)
    if not m:
        raise ValueError(f"{name!r} is not a FabricSlide file name (<Label>_F<force>_V<velocity>mmps_<repeat>.csv)")
    return {"label": m["label"], "force_setpoint": float(m["force"]), "velocity_mm_s": float(m["vel"]),
            "repeat": int(m["rep"])}


def read_recording(path: str | Path, kind: str | None = None) -> Recording:
    """Read one FabricSlide CSV file.

    Raises
    ------
    ValueError
        On a bad file name, fewer than 19 columns, or fewer than 2 samples.
    """
    path = Path(path)
    labels = parse_name(path.name)
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.shape[1] < 3 + N_CHANNELS:
        raise ValueError(f"{path}: expected timestamp, proximity1, proximity2 and 16 channels; got {data.shape[1]} "
                         "columns")
    ts = data[:, 0]
    order = np.argsort(ts, kind="stable")
    ts, data = ts[order], data[order]
    keep = np.concatenate(([True], np.diff(ts) != 0))  # first sample of each repeated timestamp
    ts, readings = ts[keep], data[keep, 3:3 + N_CHANNELS]
    if ts.size < 2:
        raise ValueError(f"{path}: fewer than 2 distinct timestamps")
    kind = kind or ("board" if labels["label"].lower().startswith("board") else "fabric")
    return Recording(path=path, kind=kind, timestamp_ms=ts.astype(np.float64),
                     readings=np.ascontiguousarray(readings, dtype=np.float64),
                     repeated_stamps=int(np.count_nonzero(~keep)), **labels)


def list_files(directory: str | Path, *, include_board: bool = False, pattern: str = "*.csv") -> list[Path]:
    """The FabricSlide CSV files under ``directory`` (``fabric/``, and ``board/`` if asked), sorted by name.

    Raises
    ------
    FileNotFoundError
        If ``directory/fabric`` does not exist.
    """
    directory = Path(directory)
    fabric = directory / "fabric"
    if not fabric.is_dir():
        raise FileNotFoundError(f"{fabric} does not exist (expected the FabricSlide subset: fabric/ and board/)")
    files = sorted(fabric.glob(pattern))
    if include_board and (directory / "board").is_dir():
        files += sorted((directory / "board").glob(pattern))
    return files


def load_fabricslide(directory: str | Path, *, include_board: bool = False, pattern: str = "*.csv"
                     ) -> list[Recording]:
    """Load the FabricSlide recordings.

    Parameters
    ----------
    directory : path
        The subset's directory (``../shared/data/fabricslide``).
    include_board : bool
        Also load the Board10mm recordings (a ridged board, 20 mm period; a clean speed-scaling check).
    pattern : str
        Glob of file names to load (e.g. ``"Canvas_*"``), default all.

    Returns
    -------
    list of :class:`Recording`, fabric files sorted by name, then board files.
    """
    return [read_recording(p) for p in list_files(directory, include_board=include_board, pattern=pattern)]


def resample_to_1khz(timestamp_ms: np.ndarray, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of readings onto a 1 ms grid starting at the first timestamp.

    Parameters
    ----------
    timestamp_ms : (n,) float
        Strictly increasing sample times, ms (as in :attr:`Recording.timestamp_ms`).
    readings : (n, c) float
        Values at those times.

    Returns
    -------
    grid_ms : (m,) float64
        ``timestamp_ms[0] + arange(m)`` with ``m = floor(timestamp_ms[-1] - timestamp_ms[0]) + 1``.
    values : (m, c) float64
        ``numpy.interp`` of each column at the grid times.

    Raises
    ------
    ValueError
        If the timestamps are not strictly increasing or the shapes disagree.
    """
    ts = np.asarray(timestamp_ms, dtype=np.float64)
    x = np.asarray(readings, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != ts.shape[0]:
        raise ValueError(f"readings {x.shape} must be (n, c) with n = len(timestamp_ms) = {ts.shape[0]}")
    if ts.size < 2 or np.any(np.diff(ts) <= 0):
        raise ValueError("timestamps must be strictly increasing (remove repeated timestamps first)")
    m = int(math.floor(ts[-1] - ts[0])) + 1
    grid = ts[0] + np.arange(m, dtype=np.float64)
    out = np.empty((m, x.shape[1]), dtype=np.float64)
    for c in range(x.shape[1]):
        out[:, c] = np.interp(grid, ts, x[:, c])
    return grid, out


def to_adc(values: np.ndarray, *, scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET) -> np.ndarray:
    """Map (m, 16) counts to 10-bit ADC counts: ``clip(rint(v * scale + offset), 0, 1023)``.

    Returns
    -------
    (m, 16) uint16, channel k = FabricSlide ``channel<k+1>``.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != N_CHANNELS:
        raise ValueError(f"values must be (m, {N_CHANNELS}), got {v.shape}")
    return np.clip(np.rint(v * scale + offset), 0, FABRICSLIDE_SENSOR.adc_max).astype(np.uint16)


def _n_samples(rec: Recording, trim: float) -> int:
    m = int(math.floor(rec.timestamp_ms[-1] - rec.timestamp_ms[0])) + 1
    return m - 2 * int(round(trim * m))


def recording_adc(rec: Recording, *, scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET,
                  trim: float = 0.0) -> np.ndarray:
    """A recording resampled to 1 kHz and mapped to 10 bits: ``(m, 16) uint16``.

    ``trim`` drops that fraction of the resampled samples at each end (the arm's acceleration ramps; the
    FabricSlide README suggests 0.10-0.15).
    """
    _, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
    if trim:
        if not 0 <= trim < 0.5:
            raise ValueError("trim must be in [0, 0.5)")
        k = int(round(trim * values.shape[0]))
        values = values[k:values.shape[0] - k]
    return to_adc(values, scale=scale, offset=offset)


def _declare(rec: Recording, declared: dict[str, Any], *, scale: float, offset: float, close_gaps: bool,
             clip: bool) -> None:
    """Add what importing ``rec`` changes to ``declared`` (the import's ledger record); ValueError for a gap in its
    time stamps without ``close_gaps`` or a reading the map puts outside 0..1023 without ``clip`` (one line)."""
    from rigctl.storage.time_column import gaps_text, stamp_gaps

    gaps = stamp_gaps(rec.timestamp_ms / 1000.0)
    if gaps and not close_gaps:
        raise ValueError(f"{rec.path}: {len(gaps)} gap(s) in the time stamps ({gaps_text(gaps)}): interpolating "
                         "across them changes the timing: give --close-gaps to close them (declared in the ledger)")
    mapped = np.rint(rec.readings * scale + offset)
    outside = int(np.count_nonzero((mapped < 0) | (mapped > FABRICSLIDE_SENSOR.adc_max)))
    if outside and not clip:
        raise ValueError(f"{rec.path}: {outside} readings map outside the 10-bit range 0..1023 (scale {scale:g}, "
                         f"offset {offset:g}): give --clip to pin them (counted, declared in the ledger)")
    declared["rows_in"] += int(rec.timestamp_ms.size) + rec.repeated_stamps
    declared["samples_out"] += int(math.floor(rec.timestamp_ms[-1] - rec.timestamp_ms[0])) + 1
    declared["repeated_stamps"] += rec.repeated_stamps
    declared["gaps"] += len(gaps)
    declared["clipped_values"] += outside  # (readings; the 1 kHz grid between them never overshoots them)


def fabricslide_textures(labels: Iterable[str]) -> TextureSet:
    """:data:`FABRICSLIDE_TEXTURES`, with any label it does not know appended (sorted) to the ``fabric`` group."""
    extra = sorted(set(labels) - set(FABRICSLIDE_TEXTURES.labels))
    if not extra:
        return FABRICSLIDE_TEXTURES
    fabrics = [lab for lab in (*FABRICS, *extra) if not lab.lower().startswith("board")]
    boards = [*BOARDS, *(lab for lab in extra if lab.lower().startswith("board"))]
    return TextureSet.from_dict({"name": "FabricSlide", "textures": [*fabrics, *boards],
                                 "groups": {"fabric": fabrics, "board": boards}})


def import_fabricslide(directory: str | Path, out_path: str | Path, *, include_board: bool = True,
                       pattern: str = "*.csv", trim: float = 0.10, scale: float = DEFAULT_SCALE,
                       offset: float = DEFAULT_OFFSET, overwrite: bool = False,
                       progress: ProgressCallback | None = None, close_gaps: bool = False,
                       clip: bool = False) -> dict[str, Any]:
    """The FabricSlide preset of ``rigctl import``: the recordings as one session file (kind ``"fabricslide"``),
    16 channels at 1 kHz, 10 bits (:data:`FABRICSLIDE_SENSOR`), fabrics and board together.

    Labels (in the ``/plan`` table): ``texture`` = the fabric's name (``BeigeCotton`` ... or ``Board10mm``) from
    the texture set :data:`FABRICSLIDE_TEXTURES` (groups ``fabric``/``board``, codes fixed by the set);
    ``speed_mm_s`` = ``abs(velocity)``; ``force_g`` = the arm's force setpoint (not grams: attribute
    ``force_unit``); ``duration_s`` = samples / 1000 after trimming; ``repeat``. Trial attributes: ``fabric``,
    ``velocity_mm_s`` (signed), ``direction`` (+1/-1), ``source_file``, ``trim_fraction``. The speed trace holds the
    nominal speed at 10 Hz; there is no load-cell trace. Steps (linear resampling from the timestamps, the 10-bit
    map, the trim) are root attributes (``adc_map``, ``resampling``, ``import_steps``).

    ``progress`` receives :class:`rigctl.core.progress.ProgressEvent` s: stage ``"FabricSlide import"``, done/total =
    files read then trials written (2 per file).

    Nothing silent (issue 77 item 1): a gap in a file's time stamps (:func:`rigctl.storage.time_column.stamp_gaps`)
    is refused unless ``close_gaps`` (then interpolated across), readings the 10-bit map puts outside 0..1023 unless
    ``clip``; the regridding, the repeated stamps dropped, the gaps closed and the values clipped are declared in
    ``import_steps`` (``fabricslide``: the ledger, :mod:`rigctl.storage.ledger`).

    Returns
    -------
    dict with ``path``, ``n_trials``, ``samples``, ``labels`` (the texture labels present), ``textures``, ``steps``
    (the recorded import steps: :func:`rigctl.storage.ledger.ledger` of them is what changed the values).

    Raises
    ------
    FileNotFoundError (no files), FileExistsError (``out_path`` exists without ``overwrite``), ValueError (a gap or a
    value outside the map refused, one line naming the file).
    """
    from rigctl.core.trial import TrialData
    from rigctl.storage.importers import _check_paths, write_session

    files = list_files(directory, include_board=include_board, pattern=pattern)
    if not files:
        raise FileNotFoundError(f"no FabricSlide files matching {pattern!r} under {directory}")
    _check_paths(files, Path(out_path), overwrite)
    names = [parse_name(p.name) for p in files]
    textures = fabricslide_textures(n["label"] for n in names)
    bar = Stage(progress, "FabricSlide import", 2 * len(files), unit="file")
    recs: list[Any] = []
    plan: list[dict[str, Any]] = []
    declared = {"files": len(files), "rows_in": 0, "samples_out": 0, "repeated_stamps": 0, "gaps": 0,
                "clipped_values": 0}
    for i, path in enumerate(files):
        rec = read_recording(path)
        _declare(rec, declared, scale=scale, offset=offset, close_gaps=close_gaps, clip=clip)
        recs.append(rec)
        plan.append({"trial_id": i, "texture": rec.label, "speed_mm_s": rec.speed_mm_s,
                     "force_g": rec.force_setpoint, "duration_s": _n_samples(rec, trim) / RATE_HZ,
                     "profile": "constant", "repeat": rec.repeat})
        bar.advance(1)
    adc_map = {"formula": "adc = clip(rint(counts * scale + offset), 0, 1023)", "scale": scale, "offset": offset,
               "resampling": "linear interpolation onto a 1 ms grid from the first timestamp; repeated timestamps: "
               "first sample kept", "trim_fraction_each_end": trim}
    resampling = {"method": "linear interpolation (numpy.interp) from the timestamps", "from_hz": "irregular (~35.7)",
                  "to_hz": RATE_HZ}
    samples = 0
    steps = {"preset": "fabricslide", "adc_map": adc_map, "resampling": resampling, "files": len(files),
             "fabricslide": declared}

    def items() -> Iterator[Any]:
        nonlocal samples
        for i, rec in enumerate(recs):
            adc = recording_adc(rec, scale=scale, offset=offset, trim=trim)
            n = adc.shape[0]
            t = np.arange(0, n, 100) / RATE_HZ
            samples += n
            bar.advance(1)
            yield i, TrialData(
                taxels=adc, speed_mm_s=np.full(t.size, rec.speed_mm_s), speed_time_s=t, layout=FABRICSLIDE_SENSOR,
                attrs={"fabric": rec.label, "velocity_mm_s": rec.velocity_mm_s, "direction": rec.direction,
                       "source_file": f"{rec.kind}/{rec.path.name}", "trim_fraction": trim, "source": "fabricslide"})

    write_session(
        out_path, plan, items(), layout=FABRICSLIDE_SENSOR, textures=textures, kind="fabricslide",
        protocol_name="fabricslide-import", overwrite=overwrite,
        rig_config={"source": "FabricSlide (wngfra/FabricSlide, MIT licence)", "directory": str(directory),
                    "sensor": "CPM-Finger capacitive, 16 taxels", "adc_map": adc_map},
        attrs={"adc_map": json.dumps(adc_map), "resampling": json.dumps(resampling),
               "segmentation": json.dumps({"method": "none (one file = one trial)"}),
               "import_steps": json.dumps(steps),
               "force_unit": "FabricSlide arm force-loop setpoint (not grams)",
               "channel_map": "channel k = FabricSlide channel<k+1> (16 channels)"})
    present = sorted({p["texture"] for p in plan}, key=textures.code)
    return {"path": str(out_path), "n_trials": len(recs), "samples": samples, "labels": present,
            "textures": list(textures.labels), "steps": steps}


def iter_adc_blocks(recordings: Iterable[Recording], **kw: Any) -> Iterable[np.ndarray]:
    """``recording_adc`` of each recording in turn (for replay)."""
    for rec in recordings:
        yield recording_adc(rec, **kw)
