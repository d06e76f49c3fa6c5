"""FabricSlide recordings (real tactile data, MIT licence): loading, resampling to 1 kHz, 10-bit mapping, import.

Source: Wang et al. (2022), "Fabric Classification Using a Finger-Shaped Tactile Sensor via Robotic Sliding",
Front. Neurorobot. 16:808222 (repository wngfra/FabricSlide); the subset lives in ``../shared/data/fabricslide``
(its README describes it). Files ``fabric/<Fabric>_F<force>_V<velocity>mmps_<repeat>.csv`` and
``board/Board10mm_F<force>_V<velocity>mmps_0.csv``; columns ``timestamp`` (ms, ~28 ms apart), ``proximity1``,
``proximity2`` (ignored), ``channel1`` ... ``channel16`` (bias-subtracted capacitance counts).

How the 16 taxels sit in the rig's 18-channel layout (docs/wire-protocol.md): FabricSlide ``channel1`` ...
``channel16`` -> channels 0-15 in order; channels 16-17 carry the constant :data:`FILL_COUNTS` and are marked absent
(``channel_present`` attribute, 16 x True + 2 x False). The CPM-Finger's taxels are not a 3x3x2 grid, so the
top/bottom-layer meaning of channels 0-17 does not apply to this data.

10-bit map (deterministic, linear, documented in the session attributes): ``adc = clip(rint(counts * scale +
offset), 0, 1023)`` with ``scale = 1``, ``offset = 0`` by default: the recorded values are integer counts between
about 2 and 850, so the map keeps them exactly where no interpolation happened.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Iterable

import numpy as np

N_CHANNELS = 16
N_TAXELS = 18
FILL_COUNTS = 0
#: ``channel_present`` attribute of imported sessions and replays: channels 0-15 real, 16-17 absent
CHANNEL_PRESENT = np.array([True] * N_CHANNELS + [False] * (N_TAXELS - N_CHANNELS))
DEFAULT_SCALE = 1.0
DEFAULT_OFFSET = 0.0

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

    @property
    def speed_mm_s(self) -> float:
        """``abs(velocity_mm_s)``."""
        return abs(self.velocity_mm_s)

    @property
    def direction(self) -> int:
        """+1 or -1: the sign of the velocity."""
        return 1 if self.velocity_mm_s >= 0 else -1


def parse_name(name: str) -> dict:
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
                     readings=np.ascontiguousarray(readings, dtype=np.float64), **labels)


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


def to_adc(values: np.ndarray, *, scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET,
           fill: int = FILL_COUNTS) -> np.ndarray:
    """Map (m, 16) counts to the rig's (m, 18) 10-bit layout: ``clip(rint(v * scale + offset), 0, 1023)``.

    Channels 0-15 = FabricSlide channel1-16; channels 16-17 = ``fill`` (absent, see :data:`CHANNEL_PRESENT`).

    Returns
    -------
    (m, 18) uint16
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != N_CHANNELS:
        raise ValueError(f"values must be (m, {N_CHANNELS}), got {v.shape}")
    out = np.full((v.shape[0], N_TAXELS), int(fill), dtype=np.uint16)
    out[:, :N_CHANNELS] = np.clip(np.rint(v * scale + offset), 0, 1023).astype(np.uint16)
    return out


def _n_samples(rec: Recording, trim: float) -> int:
    m = int(math.floor(rec.timestamp_ms[-1] - rec.timestamp_ms[0])) + 1
    return m - 2 * int(round(trim * m))


def recording_adc(rec: Recording, *, scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET,
                  fill: int = FILL_COUNTS, trim: float = 0.0) -> np.ndarray:
    """A recording resampled to 1 kHz and mapped to 10 bits: ``(m, 18) uint16``.

    ``trim`` drops that fraction of the resampled samples at each end (the arm's acceleration ramps; the
    FabricSlide README suggests 0.10-0.15).
    """
    _, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
    if trim:
        if not 0 <= trim < 0.5:
            raise ValueError("trim must be in [0, 0.5)")
        k = int(round(trim * values.shape[0]))
        values = values[k:values.shape[0] - k]
    return to_adc(values, scale=scale, offset=offset, fill=fill)


def import_fabricslide(directory: str | Path, out_path: str | Path, *, include_board: bool = False,
                       pattern: str = "*.csv", trim: float = 0.10, scale: float = DEFAULT_SCALE,
                       offset: float = DEFAULT_OFFSET, overwrite: bool = False, progress: bool = True) -> dict:
    """Write the FabricSlide recordings as a session file (kind ``"fabricslide"``), taxels at 1 kHz, 10 bits.

    Labels (in the ``/plan`` table, so every analysis runs on this data): ``texture`` = a one-character code of
    the fabric (``"1"`` ... in sorted label order, fabrics before the board: BeigeCotton 1, BrownCotton 2, Canvas 3,
    Linen 4, Board10mm 5; the root attribute ``texture_labels`` maps codes to names and
    every trial has a ``fabric`` attribute); ``speed_mm_s`` = ``abs(velocity)``; ``force_g`` = the arm's force
    setpoint (not grams: attribute ``force_unit``); ``duration_s`` = samples / 1000 after trimming; ``repeat``.
    Trial attributes: ``fabric``, ``velocity_mm_s`` (signed), ``direction`` (+1/-1), ``source_file``,
    ``channel_present``, ``trim_fraction``. The speed trace holds the nominal speed at 10 Hz; there is no
    load-cell trace. The mapping and the channel layout are root attributes too (``adc_map``, ``channel_present``).

    Returns
    -------
    dict with ``path``, ``n_trials``, ``samples``, ``labels`` (code -> name).
    """
    from rigctl.storage.session import SessionWriter, TrialData

    files = list_files(directory, include_board=include_board, pattern=pattern)
    if not files:
        raise FileNotFoundError(f"no FabricSlide files matching {pattern!r} under {directory}")
    names = [parse_name(p.name) for p in files]
    # fabrics first, then boards, each sorted: a fabric keeps its code whether or not the board is included
    labels = sorted({n["label"] for n in names}, key=lambda lab: (lab.lower().startswith("board"), lab))
    if len(labels) > 9:
        raise ValueError(f"at most 9 distinct labels fit the one-character texture code, got {len(labels)}")
    code = {lab: str(i + 1) for i, lab in enumerate(labels)}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=2 * len(files), unit="file", desc="FabricSlide import")
    recs, plan = [], []
    for i, path in enumerate(files):
        rec = read_recording(path)
        recs.append(rec)
        plan.append({"trial_id": i, "texture": code[rec.label], "speed_mm_s": rec.speed_mm_s,
                     "force_g": rec.force_setpoint, "duration_s": _n_samples(rec, trim) / 1000.0,
                     "profile": "constant", "repeat": rec.repeat})
        if bar is not None:
            bar.update(1)
    adc_map = {"formula": "adc = clip(rint(counts * scale + offset), 0, 1023)", "scale": scale, "offset": offset,
               "fill_channels_16_17": FILL_COUNTS, "resampling": "linear interpolation onto a 1 ms grid from the "
               "first timestamp; repeated timestamps: first sample kept", "trim_fraction_each_end": trim}
    writer = SessionWriter.create(
        out_path, plan=plan, protocol_source="", protocol_name="fabricslide-import", protocol_format="none",
        rig_config={"source": "FabricSlide (wngfra/FabricSlide, MIT licence)", "directory": str(directory),
                    "sensor": "CPM-Finger capacitive, 16 taxels", "adc_map": adc_map},
        kind="fabricslide", overwrite=overwrite,
        attrs={"texture_labels": json.dumps({v: k for k, v in code.items()}), "channel_present": CHANNEL_PRESENT,
               "adc_map": json.dumps(adc_map), "force_unit": "FabricSlide arm force-loop setpoint (not grams)",
               "channel_map": "channels 0-15 = FabricSlide channel1-16; channels 16-17 absent (constant fill)"})
    samples = 0

    def items():
        nonlocal samples
        for i, rec in enumerate(recs):
            adc = recording_adc(rec, scale=scale, offset=offset, trim=trim)
            n = adc.shape[0]
            t = np.arange(0, n, 100) / 1000.0
            samples += n
            if bar is not None:
                bar.update(1)
            yield i, TrialData(
                taxels=adc, speed_mm_s=np.full(t.size, rec.speed_mm_s), speed_time_s=t,
                attrs={"fabric": rec.label, "velocity_mm_s": rec.velocity_mm_s, "direction": rec.direction,
                       "source_file": f"{rec.kind}/{rec.path.name}", "channel_present": CHANNEL_PRESENT,
                       "trim_fraction": trim, "source": "fabricslide"})

    try:
        writer.write_trials(items())
    finally:
        if bar is not None:
            bar.close()
    return {"path": str(out_path), "n_trials": len(recs), "samples": samples,
            "labels": {v: k for k, v in code.items()}}


def iter_adc_blocks(recordings: Iterable[Recording], **kw) -> Iterable[np.ndarray]:
    """``recording_adc`` of each recording in turn (for replay)."""
    for rec in recordings:
        yield recording_adc(rec, **kw)
