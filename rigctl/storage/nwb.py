"""NWB export of a session (and its encoded spike trains) with pynwb: the format neuroscience labs exchange data in.

:func:`export_nwb` writes one NWB 2 file holding

- ``acquisition/taxels``: a :class:`pynwb.TimeSeries` of every recorded trial's taxel readings, back to back,
  ``(n_samples, n_channels)`` uint16 ADC counts at the sensor's rate (``rate``; ``conversion = 1 / adc_max``, so
  ``data * conversion`` is the fraction of the ADC's full scale, ``unit`` says so). Session time is *recorded* time:
  trial ``k`` starts where trial ``k - 1`` ended (the dead time between trials, plate changes and settling, is left
  out; each trial's wall-clock start is the trials table's ``started_utc``). Frames the board sent but the host lost
  are missing, not filled (the trials table's ``dropped_frames`` counts them);
- ``acquisition/load_cell_force`` (g) and ``acquisition/drum_speed`` (mm/s): the drum controller's traces (a
  handheld session: ``acquisition/tracker_velocity`` (mm/s) and ``acquisition/tracker_position`` (mm along the
  plate), the tracker's samples) with
  timestamps on the same session time (a trace whose times are regular within 1 ns, as a simulated session's 50 Hz
  traces are, with NWB's ``starting_time`` and ``rate`` instead, the same times: nwbinspector's advice);
- the **trials table**: one row per recorded trial (start/stop time in session time; ``trial_id``, ``texture``,
  ``group``, ``speed_mm_s`` and ``force_g`` setpoints, ``profile``, ``duration_s``, ``status``, ``n_samples``,
  ``dropped_frames``, ``crc_errors``, ``started_utc``, measured ``force_mean_g`` and ``speed_mean_mm_s``);
- ``processing/misc/plan``: the whole plan (every planned trial with its status: complete, pending, failed);
- **devices** ``taxel_sensor`` (the :class:`rigctl.core.sensor.SensorLayout` as JSON in its description: layers,
  receptor types, pitch, rate, ADC bits, channel names) and ``drum_rig`` (the rig configuration JSON); the texture
  set as JSON in ``processing/misc``'s description;
- with an encoded file: the **Units table**, one unit per spiking neuron of each exported variant (SA and RA per
  taxel; paper eqs. 3-5), its spike times over the whole session (each trial's spikes shifted by the trial's start),
  and columns ``variant``, ``receptor`` (SA/RA), ``taxel``, ``taxel_label``, ``layer``, ``receptor_type``,
  ``time_base`` ("session" or, for speed-scaled variants, "speed-scaled": eq. 2 scales spike times by the trial's
  speed, so such times are trial start + scaled time, not the moment of the spike).

The file is written by pynwb and checked with the NWB inspector in the tests. :func:`read_nwb_summary` reads the
parts back (the round trip test and ``rigctl info``-like use).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.progress import ProgressCallback, Stage
from rigctl.storage import encoded as _encoded
from rigctl.storage.outputs import OutputTarget, output_file
from rigctl.storage.session import TrialStatus, open_session
from rigctl.storage.validate import check_beside

__all__ = ["NwbExportError", "NwbExportParams", "NwbSummary", "export_nwb", "read_nwb_summary",
           "default_spike_variants", "check_spike_variants", "estimate_nwb_bytes"]


class NwbExportError(ValueError):
    """The export cannot be made as asked (no recorded trial, an encoded file of other trials, an unknown variant)."""


@dataclass
class NwbSummary:
    """What an NWB file exported by rigctl holds (:func:`export_nwb` returns it; :func:`read_nwb_summary` reads it).

    ``n_samples`` taxel samples over ``n_trials`` trials of ``n_channels`` channels at ``rate_hz``; ``units`` spike
    trains per variant; ``spikes`` spike counts per variant."""

    path: Path
    n_trials: int = 0
    n_samples: int = 0
    n_channels: int = 0
    rate_hz: float = 0.0
    units: dict[str, int] = field(default_factory=dict)
    spikes: dict[str, int] = field(default_factory=dict)


def default_spike_variants(enc: Any) -> list[str]:
    """The variants exported as units when none are asked for: the stored ones whose spike times are in real time
    (not speed-scaled)."""
    return [v for v in enc.spike_variants if not (v in _encoded.VARIANTS and _encoded.VARIANTS[v].speed_scaled)]


#: taxel samples handed to HDF5 at once (36 MB of the paper's 18 taxels): one block read of the session per chunk
_BLOCK_SAMPLES = 1 << 20
#: rows of an HDF5 chunk of ``acquisition/taxels``: 10 s of every channel at 1 kHz (a user reads a time range)
TAXEL_CHUNK_ROWS = 10_000
#: values per HDF5 chunk of the Units table's ``spike_times`` (512 KiB: a user reads one unit's train, a slice)
SPIKE_CHUNK = 65_536


def _blocks(lengths: Sequence[int] | np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive ranges ``(i0, i1)`` of items whose lengths sum to at most ``limit`` (at least one item each), taken
    greedily from the first. Non-negative integer lengths: one search of their running sum per block (the export
    asks this of every unit's 24,000 trials at paper size: ~0.3 CPU-s a variant item by item); others item by item."""
    arr = np.asarray(lengths)
    if arr.ndim == 1 and arr.dtype.kind in "iub" and (arr.size == 0 or int(arr.min()) >= 0):
        ends = np.cumsum(arr, dtype=np.int64)  # ends[i]: the lengths of items 0..i summed
        blocks, i0, n = [], 0, int(arr.size)
        while i0 < n:
            base = int(ends[i0 - 1]) if i0 else 0  # item i joins the block of i0 while ends[i] - base <= limit
            i1 = max(i0 + 1, int(np.searchsorted(ends, base + limit, side="right")))
            blocks.append((i0, i1))
            i0 = i1
        return blocks
    out, i0, acc = [], 0, 0
    for i, n in enumerate(lengths):
        if i > i0 and acc + int(n) > limit:
            out.append((i0, i))
            i0, acc = i, 0
        acc += int(n)
    if i0 < len(lengths):
        out.append((i0, len(lengths)))
    return out


class _Chunks:
    """hdmf data iterator over a 1-d or 2-d dataset written in blocks (the whole is never in memory): ``parts``
    yields ``(array, n_done)`` blocks in row order; after a block is handed to HDF5 the bar ``stage`` advances by the
    items (trials, units) it held, one event each; the output ``target`` is checked before each block (the disk
    refused the previous one: stop there, one line, the part file removed)."""

    def __init__(self, parts: Iterator[tuple[np.ndarray, int]], shape: tuple[int, ...], dtype: Any, chunks: tuple[int, ...],
                 bar: Stage, target: OutputTarget | None = None) -> None:
        self._parts, self._shape, self._chunks = parts, shape, chunks
        self._dtype: np.dtype[Any] = np.dtype(dtype)
        self._bar, self._target = bar, target
        self._at, self._pending = 0, 0

    def __iter__(self) -> Any:
        return self

    def __len__(self) -> int:
        return int(self._shape[0])

    def __next__(self) -> Any:
        from hdmf.data_utils import DataChunk

        if self._target is not None:
            self._target.check()
        for _ in range(self._pending):
            self._bar.advance(1)  # the previous block has been handed to HDF5
        self._pending = 0
        data, n_items = next(self._parts)  # StopIteration ends the write
        data = np.asarray(data, dtype=self._dtype)
        sel = (np.s_[self._at:self._at + data.shape[0]],) + (np.s_[:],) * (data.ndim - 1)
        self._at += data.shape[0]
        self._pending = n_items
        return DataChunk(data=data, selection=sel)

    def recommended_chunk_shape(self) -> tuple[int, ...]:
        return (max(1, min(self._shape[0], self._chunks[0])),) + self._chunks[1:]

    def recommended_data_shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def dtype(self) -> np.dtype[Any]:
        return self._dtype

    @property
    def maxshape(self) -> tuple[int, ...]:
        return self._shape


def _taxel_blocks(session: Any, ids: Sequence[int], n_samples: Sequence[int]) -> Iterator[tuple[np.ndarray, int]]:
    """The trials' taxels back to back, one block read (:meth:`Session.read_taxels`) of up to :data:`_BLOCK_SAMPLES`
    samples at a time."""
    for i0, i1 in _blocks(n_samples, _BLOCK_SAMPLES):
        yield session.read_taxels(ids[i0:i1]).data, i1 - i0


def _chunks(*args: Any, **kw: Any) -> Any:
    """A :class:`_Chunks` registered as an hdmf ``AbstractDataChunkIterator`` (hdmf imported only when exporting)."""
    from hdmf.data_utils import AbstractDataChunkIterator

    return type("Chunks", (_Chunks, AbstractDataChunkIterator), {})(*args, **kw)


def _start_time(text: Any) -> _dt.datetime:
    try:
        t = _dt.datetime.fromisoformat(str(text))
    except ValueError:
        t = _dt.datetime.now(_dt.UTC)
    return t if t.tzinfo else t.replace(tzinfo=_dt.UTC)


def _train_columns(layout: Any, n_trains: int) -> list[tuple[str, int, str, str, str]]:
    """(receptor, taxel, taxel label, layer, receptor type) per train: SA taxels then RA taxels (the encoder's order),
    or SA of the first layer for the real-time variants."""
    labels = layout.channel_labels()
    layer_of = [layout.channel_position(c)[0] for c in range(layout.n_channels)]
    chans = list(range(layout.n_channels))
    if n_trains == 2 * layout.n_channels:
        pairs = [("SA", c) for c in chans] + [("RA", c) for c in chans]
    else:  # real-time variants: SA trains of the first layer's taxels
        pairs = [("SA", c) for c in chans[:n_trains]]
    return [(rec, c, labels[c], layout.layers[layer_of[c]].name, layout.layers[layer_of[c]].receptor)
            for rec, c in pairs]


@dataclass(frozen=True)
class NwbExportParams:
    """What :func:`export_nwb` exports and how it writes (the parameter object of the export's steps).

    encoded_path : optional ``rigctl encode`` output of the session: its spike trains become the Units table.
    variants : the variants whose spike trains are exported (None: :func:`default_spike_variants`).
    overwrite : replace an existing output (False: FileExistsError).
    keep_nonfinite : export trials whose force or speed traces hold NaN/inf (default: excluded, as by the
        validator).
    experimenter, institution, lab : the NWB file's ``experimenter`` (names, "Last, First" as DANDI asks),
        ``institution`` and ``lab``; empty / None: the rig config's keys of those names if the session's config has
        them, else left out (never a placeholder).
    """

    encoded_path: Path | None = None
    variants: tuple[str, ...] | None = None
    overwrite: bool = False
    keep_nonfinite: bool = False
    experimenter: tuple[str, ...] = ()
    institution: str | None = None
    lab: str | None = None


@dataclass
class _Timeline:
    """The exported trials on session time: ids, samples per trial, start/stop s, their attributes."""

    ids: list[int]
    n: list[int]
    starts: np.ndarray
    stops: np.ndarray
    lead: float
    attrs: list[dict[str, Any]]


def check_spike_variants(encoded_path: str | os.PathLike[str], variants: Sequence[str] | None) -> list[str]:
    """The variants of ``encoded_path`` to export (``variants``, or :func:`default_spike_variants`), checked before
    any work. Raises NwbExportError naming a variant without stored spike trains."""
    with _encoded.open_encoded(encoded_path) as enc:
        chosen = list(variants) if variants else default_spike_variants(enc)
        for v in chosen:
            if v not in enc.spike_variants:
                raise NwbExportError(f"{encoded_path} holds no spike trains of {v!r} (stored: "
                                     f"{', '.join(enc.spike_variants) or 'none'}; encode without --no-spikes)")
    return chosen


def estimate_nwb_bytes(session_path: str | os.PathLike[str], encoded_path: Any = None) -> int:
    """About how many bytes :func:`export_nwb` writes, at most: the taxels uncompressed (``samples x channels x 2``)
    of every complete trial (schema 4: from the recording index, so the estimate costs no pass over the data; the
    validator may exclude some) or of the usable ones (older files) plus the traces, plus the encoded file's size
    when its spike trains are exported (checked against the free space before the export starts)."""
    from rigctl.storage.validate import precheck, usable_trials

    with open_session(session_path) as s:
        if s._flat:  # schema 4: the recording index holds every trial's sample count
            ids = precheck(s)  # the trials the validator does not refuse before reading data
            rows, _ = s.index_rows(ids)
            n = int(rows["n_samples"].sum())
        else:  # older files: a damaged trial's attributes may not read, so the usable ones
            ids = usable_trials(s).ids
            n = sum(int(c["n_samples"]) for c in s.trial_counts(ids))
        total = n * s.layout.n_channels * 2 + n // 10 * 16 + 64 * 1024 * (1 + len(ids) // 100)
    if encoded_path is not None:
        total += Path(encoded_path).stat().st_size
    return int(total)


def export_nwb(session_path: str | os.PathLike[str], out_path: str | os.PathLike[str], *, encoded_path: Any = None,
               variants: Sequence[str] | None = None, progress: ProgressCallback | None = None,
               overwrite: bool = False, params: NwbExportParams | None = None,
               keep_nonfinite: bool = False) -> NwbSummary:
    """Write the session (and the spike trains of an encoded file of it) as an NWB file (module doc), under the
    output policy of :mod:`rigctl.storage.outputs` (writer lock, ``<name>.part`` renamed when complete, a full disk
    one line with nothing left behind).

    Parameters
    ----------
    session_path : a rigctl session file (``rigctl acquire`` / ``import`` / ``sim dataset`` output).
    out_path : the NWB file to write.
    encoded_path, variants, overwrite, keep_nonfinite : see :class:`NwbExportParams` (``params`` gives them all
        at once).
    progress : optional callback receiving :class:`rigctl.core.progress.ProgressEvent` s: stage ``"reading
        traces"`` then ``"writing NWB"`` (done/total = trials, advanced as each trial's taxels are written).

    Returns
    -------
    NwbSummary

    Raises
    ------
    NwbExportError
        No usable trial; an encoded file whose trials are not the session's; a variant without stored trains
        (checked before anything is written).
    rigctl.storage.session.SessionError, rigctl.storage.encoded.NotEncodedError
        Unreadable inputs.
    FileExistsError, rigctl.storage.outputs.OutputLocked, rigctl.storage.outputs.OutputWriteError
        The output policy (:func:`rigctl.storage.outputs.output_file`).
    """
    if params is None:
        params = NwbExportParams(encoded_path=None if encoded_path is None else Path(encoded_path),
                                 variants=tuple(variants) if variants else None, overwrite=overwrite,
                                 keep_nonfinite=keep_nonfinite)
    chosen = check_spike_variants(params.encoded_path, params.variants) if params.encoded_path is not None else []
    out_path = Path(out_path)
    with open_session(session_path) as s:
        # a large session's trials are checked by the validator in a process of its own while this one exports the
        # trials that pass its checks made without reading data (usable unless the data exclude some: then, and
        # only then, the export is made again with the validator's trials before anything is renamed into place)
        beside = check_beside(s, session_path)
        try:
            ids = None if beside is None else beside.guess
            while True:
                try:
                    timeline = _timeline(s, session_path, params.keep_nonfinite, ids)
                    return _export(s, session_path, out_path, params, chosen, timeline, progress, beside)
                except _Guessed as exc:
                    ids, beside = exc.ids, None
                except Exception:
                    if beside is None:
                        raise
                    beside.adopt(s)  # an error of the guessed trials (then export the usable ones), or the file's?
                    usable = _usable(s, session_path, params.keep_nonfinite)
                    if usable == ids:
                        raise
                    ids, beside = usable, None
        finally:
            if beside is not None:
                beside.close()


class _Guessed(Exception):
    """The trials exported were not the validator's (:class:`rigctl.storage.validate.Beside`): ``ids`` are."""

    def __init__(self, ids: list[int]) -> None:
        super().__init__(ids)
        self.ids = ids


def _export(s: Any, session_path: Any, out_path: Path, params: NwbExportParams, chosen: list[str],
            timeline: _Timeline, progress: ProgressCallback | None, beside: Any) -> NwbSummary:
    """The NWB file of ``timeline``'s trials; with ``beside``, renamed into place only if they are the validator's
    (else :class:`_Guessed`, the part file removed)."""
    nwb = _new_nwbfile(s, out_path, params)
    summary = NwbSummary(out_path, n_trials=len(timeline.ids), n_samples=int(sum(timeline.n)),
                         n_channels=s.layout.n_channels, rate_hz=float(s.layout.sample_rate_hz))
    with output_file(out_path, overwrite=params.overwrite, kind="nwb") as target:
        _add_taxels(nwb, s, timeline, progress, target)
        _add_traces(nwb, s, timeline, Stage(progress, "reading traces", len(timeline.ids)))
        _add_trials_table(nwb, s, timeline)
        _add_plan(nwb, s)
        _add_provenance(nwb, session_path, params.encoded_path)
        if params.encoded_path is not None:
            _add_units(nwb, params.encoded_path, timeline.ids, timeline.starts, s.layout, chosen, summary,
                       progress, target)
        _write(nwb, target)
        if beside is not None:
            beside.adopt(s)
            usable = _usable(s, session_path, params.keep_nonfinite)
            if usable != timeline.ids:
                raise _Guessed(usable)
    return summary


def _usable(s: Any, session_path: Any, keep_nonfinite: bool) -> list[int]:
    """The usable trials (:func:`rigctl.storage.validate.usable_trials`), the excluded ones warned of; none is an
    :class:`NwbExportError`."""
    from rigctl.storage.validate import TrialsExcluded, usable_trials

    # the one trial validator: excluded trials said, as by info and encode
    report = usable_trials(s, keep_nonfinite=keep_nonfinite)
    if not report.ids:
        raise NwbExportError(f"{session_path} has no usable recorded trial to export"
                             + (f" ({report.summary()})" if report.excluded else ""))
    if report.excluded:
        warnings.warn(f"{session_path}: {report.summary()}", TrialsExcluded, stacklevel=4)
    return list(report.ids)


def _timeline(s: Any, session_path: Any, keep_nonfinite: bool = False, ids: list[int] | None = None) -> _Timeline:
    """The usable trials (:func:`_usable`; or ``ids``) back to back on session time."""
    if ids is None:
        ids = _usable(s, session_path, keep_nonfinite)
    rate = float(s.layout.sample_rate_hz)
    attrs = s.trial_counts(ids)
    n = [int(a.get("n_samples", 0)) for a in attrs]
    if not all(n):  # trials encoded on the finger's board hold spikes and counts, no taxel series to export
        raise NwbExportError(f"{session_path}: trials {[t for t, k in zip(ids, n) if not k][:5]} hold no taxel frames "
                             "(encoded on the board: docs/session-format.md); NWB export takes taxel recordings")
    first = s.trial(ids[0])  # traces may start before the first frame (settling): session time starts there
    lead = max(0.0, -min([0.0] + [float(t.min()) for t in (first.force_time_s, first.speed_time_s) if t.size]))
    starts = lead + np.concatenate([[0], np.cumsum(n)[:-1]]) / rate
    return _Timeline(ids, n, starts, starts + np.asarray(n) / rate, lead, attrs)


def _new_nwbfile(s: Any, out_path: Path, params: NwbExportParams) -> Any:
    """The NWBFile with its session metadata (:class:`NwbExportParams`' experimenter, institution and lab), subject
    (the artificial sensor) and devices."""
    from pynwb import NWBFile
    from pynwb.file import Subject

    layout = s.layout
    cfg = s.rig_config if isinstance(s.rig_config, dict) else {}
    experimenter = list(params.experimenter) or ([str(cfg["experimenter"])] if cfg.get("experimenter") else None)
    institution = params.institution or (str(cfg["institution"]) if cfg.get("institution") else None)
    lab = params.lab or (str(cfg["lab"]) if cfg.get("lab") else None)
    nwb = NWBFile(
        session_description=f"rigctl session: protocol {s.protocol_name or '?'} on {cfg.get('mode', 'a rig')}",
        identifier=str(s.attrs.get("session_id") or out_path.stem),
        session_start_time=_start_time(s.attrs.get("created_utc", "")),
        experiment_description="Tactile texture drum rig: taxel readings, drum speed and load-cell force per "
                               "trial (rigctl; Invariant neuromorphic representations of tactile stimuli ...)",
        source_script="rigctl export nwb", source_script_file_name="rigctl",
        keywords=["touch", "tactile sensor", "texture", "taxel", "neuromorphic", "Izhikevich"],
        institution=institution, experimenter=experimenter, lab=lab,
    )
    # NWB expects a subject: here the "subject" touched is an artificial sensor, no animal
    nwb.subject = Subject(subject_id=layout.name or "taxel_sensor", species="none (artificial tactile sensor)",
                          description="artificial tactile sensor on a texture drum rig: " + layout.describe(),
                          sex="U", age="P0D")
    nwb.create_device(name="taxel_sensor", description=layout.to_json())
    nwb.create_device(name="drum_rig", description=json.dumps(s.rig_config, default=str))
    return nwb


def _add_provenance(nwb: Any, session_path: Any, encoded_path: Any) -> None:
    """``/scratch/rigctl_provenance`` (:data:`rigctl.storage.provenance.NWB_PROVENANCE`): the export's provenance
    with the session's (and the encoded file's) nested, as JSON text."""
    from rigctl.core.provenance import provenance_json, software_provenance
    from rigctl.storage.provenance import NWB_PROVENANCE, ProvenanceError, read_provenance

    def of(path: Any) -> Any:
        try:
            return read_provenance(path)
        except (ProvenanceError, OSError):
            return None

    prov = software_provenance(source_session={"path": str(session_path), "provenance": of(session_path)},
                               encoded=None if encoded_path is None else {"path": str(encoded_path),
                                                                          "provenance": of(encoded_path)})
    nwb.add_scratch(provenance_json(prov), name=NWB_PROVENANCE.split("/")[-1],
                    description="rigctl provenance (JSON): software, git state, host, command line, and the "
                                "session's own (firmware, protocol, rig config, calibration)")


def _add_taxels(nwb: Any, s: Any, tl: _Timeline, progress: ProgressCallback | None, target: OutputTarget) -> None:
    """``acquisition/taxels``: every trial's readings back to back, written chunk by chunk while the file is
    written (the bar advances as each trial reaches the file; a refused write stops the export there)."""
    from pynwb import TimeSeries

    layout = s.layout
    chunks = _chunks(_taxel_blocks(s, tl.ids, tl.n), (int(sum(tl.n)), layout.n_channels), np.uint16,
                     (TAXEL_CHUNK_ROWS, layout.n_channels), Stage(progress, "writing NWB", len(tl.ids)), target)
    nwb.add_acquisition(TimeSeries(
        name="taxels", data=chunks, unit="fraction of the ADC full scale", conversion=1.0 / layout.adc_max,
        resolution=1.0 / layout.adc_max, rate=float(layout.sample_rate_hz), starting_time=float(tl.lead),
        description=f"taxel readings, ({sum(tl.n)}, {layout.n_channels}) uint16 ADC counts "
                    f"({layout.adc_bits}-bit) of the sensor taxel_sensor; channels "
                    f"{', '.join(layout.channel_labels())}; trials back to back (recorded time)",
        comments=layout.describe()))


def _add_traces(nwb: Any, s: Any, tl: _Timeline, bar: Stage) -> None:
    """``acquisition/load_cell_force`` and ``drum_speed`` on session time; the trials' measured means kept in
    ``tl.attrs`` (``_force_mean_g``, ``_speed_mean_mm_s``) for the trials table."""
    from pynwb import TimeSeries

    handheld = (s.rig_config or {}).get("mode") == "handheld"
    # one array per series and block of trials (a trial's few hundred samples each in an array of its own, 4 x 24,000
    # of them at paper size, fragmented the heap: 0.36 GB kept for 0.13 GB of traces)
    force_t: list[np.ndarray] = []
    force: list[np.ndarray] = []
    speed_t: list[np.ndarray] = []
    speed: list[np.ndarray] = []
    k = 0
    for i0, i1 in _blocks([1] * len(tl.ids), 4096):
        block: tuple[list[np.ndarray], ...] = ([], [], [], [])
        for ft, fv, vt, vv in s.read_traces(tl.ids[i0:i1]):
            if handheld:  # the tracker's samples kept around a scan: only those inside it (trials abut here)
                inside = (vt >= 0) & (vt <= tl.stops[k] - tl.starts[k])
                vt, vv = vt[inside], vv[inside]
            for parts, x in zip(block, (tl.starts[k] + ft, fv, tl.starts[k] + vt, vv)):
                parts.append(x)
            tl.attrs[k]["_force_mean_g"] = float(np.mean(fv)) if fv.size else np.nan
            tl.attrs[k]["_speed_mean_mm_s"] = float(np.mean(vv)) if vv.size else np.nan
            bar.advance(1)
            k += 1
        for joined, parts in zip((force_t, force, speed_t, speed), block):
            joined.append(np.concatenate(parts) if parts else np.zeros(0))
        del block
    series = [("load_cell_force", "g", force_t, force, "load-cell force"),
              ("drum_speed", "mm/s", speed_t, speed, "measured drum surface speed")]
    if handheld:  # no drum, no load cell: the tracker's velocity and position
        pos_t, pos = [], []
        for k, tid in enumerate(tl.ids):
            d = s.trial(int(tid))
            inside = (d.position_time_s >= 0) & (d.position_time_s <= tl.stops[k] - tl.starts[k])
            pos_t.append(tl.starts[k] + d.position_time_s[inside])
            pos.append(d.position_mm[inside])
        series = [("tracker_velocity", "mm/s", speed_t, speed, "the finger's speed of each 100 ms window (position change, floored at 0)"),
                  ("tracker_position", "mm", pos_t, pos, "the tracker's position along the plate, from its start")]
    for name, unit, t_parts, v_parts, what in series:
        ts = np.concatenate(t_parts) if t_parts else np.zeros(0)
        vs = np.concatenate(v_parts) if v_parts else np.zeros(0)
        t_parts.clear()
        v_parts.clear()
        if not np.all(ts[1:] >= ts[:-1]):  # trials' traces that overlap (sorted already: the stable order is theirs)
            order = np.argsort(ts, kind="stable")
            ts, vs = ts[order], vs[order]
        rate = _regular_rate(ts)
        when: dict[str, Any] = ({"timestamps": ts} if rate is None else  # regular: NWB's rate (nwbinspector asks it)
                                {"starting_time": float(ts[0]), "rate": rate})
        nwb.add_acquisition(TimeSeries(name=name, data=vs, unit=unit, **when,
                                       description=f"{what} of each trial, on the taxels' session time"))


def _regular_rate(t: np.ndarray, tolerance_s: float = 1e-9) -> float | None:
    """The rate (Hz) of times ``t`` (s, (n,)) that are ``t[0] + i / rate`` within ``tolerance_s`` each (so stored
    with NWB's ``starting_time`` and ``rate`` they are the same times), or None (fewer than 3, or not regular: gaps
    between trials, a clock's jitter)."""
    t = np.asarray(t, np.float64)
    if t.size < 3:
        return None
    step = (t[-1] - t[0]) / (t.size - 1)
    if not step > 0 or np.max(np.abs(t[0] + np.arange(t.size) * step - t)) > tolerance_s:
        return None
    return float(1.0 / step)


def _add_trials_table(nwb: Any, s: Any, tl: _Timeline) -> None:
    """The trials table: one row per exported trial (setpoints, counters, measured means)."""
    from hdmf.common import VectorData

    ids, attrs, textures = tl.ids, tl.attrs, s.textures
    by_id = {int(r["trial_id"]): r for r in s.plan}
    columns: dict[str, tuple[str, Any]] = {
        "trial_id": ("rigctl trial id", np.asarray(ids, np.int64)),
        "texture": ("texture plate label", [str(by_id[t]["texture"]) for t in ids]),
        "group": ("texture group (the texture set's groups; '' when none)",
                  [textures.group_of(str(by_id[t]["texture"])) or "" for t in ids]),
        "speed_mm_s": ("drum surface speed setpoint, mm/s (ramp: mean)",
                       np.asarray([by_id[t]["speed_mm_s"] for t in ids], np.float64)),
        "force_g": ("force setpoint, g", np.asarray([by_id[t]["force_g"] for t in ids], np.float64)),
        "profile": ("velocity profile", [str(by_id[t]["profile"]) for t in ids]),
        "duration_s": ("planned duration, s", np.asarray([by_id[t]["duration_s"] for t in ids], np.float64)),
        "status": ("trial status", [TrialStatus(int(by_id[t]["status"])).name.lower() for t in ids]),
        "n_samples": ("taxel samples recorded", np.asarray(tl.n, np.int64)),
        "dropped_frames": ("frames lost on the taxel link within the trial (counted, not filled)",
                           np.asarray([int(a.get("dropped_frames", 0)) for a in attrs], np.int64)),
        "crc_errors": ("frames rejected by their CRC while the trial was captured",
                       np.asarray([int(a.get("crc_errors", 0)) for a in attrs], np.int64)),
        "started_utc": ("wall-clock start of the trial (UTC, ISO 8601)",
                        [str(a.get("started_utc", "")) for a in attrs]),
        "force_mean_g": ("mean measured force, g", np.asarray([a["_force_mean_g"] for a in attrs], np.float64)),
        "speed_mean_mm_s": ("mean measured surface speed, mm/s",
                            np.asarray([a["_speed_mean_mm_s"] for a in attrs], np.float64)),
    }
    from pynwb.epoch import TimeIntervals

    table = [("start_time", "Start time of epoch, in seconds", np.asarray(tl.starts, np.float64)),
             ("stop_time", "Stop time of epoch, in seconds", np.asarray(tl.stops, np.float64))]
    table += [(name, desc, values) for name, (desc, values) in columns.items()]
    nwb.trials = TimeIntervals(  # whole columns at once (pynwb's add_trial per row: ~2 ms a trial)
        name="trials", description="experimental trials", id=list(range(len(ids))),
        columns=[VectorData(name=name, description=desc, data=values) for name, desc, values in table])


def _add_plan(nwb: Any, s: Any) -> None:
    """``processing/misc/plan``: every planned trial with its status; the texture set in the module's description."""
    from hdmf.common import DynamicTable, VectorData
    from pynwb.base import ProcessingModule

    plan = s.plan
    module = ProcessingModule(name="misc", description="rigctl metadata; texture set: " + s.textures.to_json())
    nwb.add_processing_module(module)
    module.add(DynamicTable(name="plan", description="every planned trial of the protocol, with its status", columns=[
        VectorData(name="trial_id", description="rigctl trial id", data=np.asarray(plan["trial_id"], np.int64)),
        VectorData(name="texture", description="texture plate label", data=[str(x) for x in plan["texture"]]),
        VectorData(name="speed_mm_s", description="speed setpoint, mm/s",
                   data=np.asarray(plan["speed_mm_s"], np.float64)),
        VectorData(name="force_g", description="force setpoint, g", data=np.asarray(plan["force_g"], np.float64)),
        VectorData(name="status", description="complete, pending or failed",
                   data=[TrialStatus(int(x)).name.lower() for x in plan["status"]]),
    ]))


def _write(nwb: Any, target: OutputTarget) -> None:
    """Write ``nwb`` with pynwb into the output's part file (through its :class:`GuardedFile`)."""
    import h5py
    from pynwb import NWBHDF5IO

    h5 = h5py.File(target.h5_file(), "w")
    try:
        with NWBHDF5IO(file=h5, mode="w") as io:
            io.write(nwb)
    finally:
        h5.close()
    target.check()


def _add_units(nwb: Any, encoded_path: Any, ids: Any, starts: Any, layout: Any, variants: Any, summary: NwbSummary,
               progress: ProgressCallback | None = None, target: OutputTarget | None = None) -> None:
    """The Units table: one unit per neuron of each variant, spike times on session time. Its ``spike_times`` are
    written variant by variant while the file is written (stage ``"writing units"``, done/total = units), from the
    encoded file's tables with numpy (no Python object per spike)."""
    from hdmf.common import VectorData, VectorIndex
    from pynwb.misc import Units

    with _encoded.open_encoded(encoded_path) as enc:
        enc_ids = np.asarray(enc.trials["trial_id"], np.int64)
        row_of = {int(t): i for i, t in enumerate(enc_ids)}
        missing = [t for t in ids if t not in row_of]
        if missing:
            raise NwbExportError(f"{encoded_path} is not an encoding of this session: trials {missing[:5]} of the "
                                 "session are not in it")
        rows = np.asarray([row_of[int(t)] for t in ids], np.int64)
        chosen = list(variants)
        columns: dict[str, list[Any]] = {name: [] for name, _ in _UNIT_COLUMNS}
        ends, n_units = [], []
        for v in chosen:
            index, n_trains = enc.spike_index(v)  # the row ends only (the times: a variant at a time, below)
            lens = _unit_lengths(index, rows, n_trains)
            ends.append(lens.sum(axis=1))
            n_units.append(n_trains)
            scaled = v in _encoded.VARIANTS and _encoded.VARIANTS[v].speed_scaled
            for rec, c, label, layer, rtype in _train_columns(layout, n_trains):
                for name, value in zip(columns, (v, rec, c, label, layer, rtype,
                                                 "speed-scaled" if scaled else "session")):
                    columns[name].append(value)
            summary.units[v] = n_trains
            summary.spikes[v] = int(lens.sum())
    unit_ends = np.cumsum(np.concatenate(ends)) if ends else np.zeros(0, np.int64)
    total = int(unit_ends[-1]) if unit_ends.size else 0
    times = _chunks(_unit_spikes(encoded_path, chosen, rows, np.asarray(starts, np.float64)), (total,), np.float64,
                    (SPIKE_CHUNK,), Stage(progress, "writing units", int(sum(n_units)), unit="unit"), target)
    spike_times = VectorData(name="spike_times", description="the spike times for each unit in seconds", data=times)
    index = VectorIndex(name="spike_times_index", data=unit_ends.astype(_index_dtype(total)), target=spike_times)
    cols = [VectorData(name=name, description=desc, data=columns[name]) for name, desc in _UNIT_COLUMNS]
    nwb.units = Units(name="units", id=list(range(len(unit_ends))), columns=[*cols, index, spike_times],  # the index first (hdmf)
                      colnames=[*columns, "spike_times"], resolution=1.0 / float(layout.sample_rate_hz),
                      description="SA/RA spike trains of the Izhikevich encoding (paper eqs. 3-5), one unit per "
                                  "neuron of each exported variant, spike times in session time")


_UNIT_COLUMNS = (("variant", "encoding variant (paper Table 1 column)"),
                 ("receptor", "SA (k=100 on the reading) or RA (k=3 on the 20 Hz low-passed derivative)"),
                 ("taxel", "channel index in the sensor description"),
                 ("taxel_label", "channel name"), ("layer", "sensor layer"),
                 ("receptor_type", "the layer's receptor type"),
                 ("time_base", "'session', or 'speed-scaled': trial start + spike time scaled by eq. 2"))


def _index_dtype(largest: int) -> np.dtype[Any]:
    """The smallest unsigned integer type holding ``largest`` (what hdmf picks for a ragged column's index)."""
    for dt in (np.uint8, np.uint16, np.uint32):
        if largest <= np.iinfo(dt).max:
            return np.dtype(dt)
    return np.dtype(np.uint64)


def _unit_lengths(index: np.ndarray, rows: np.ndarray, n_trains: int) -> np.ndarray:
    """(n_trains, n_trials) spike counts of each unit in each exported trial (the encoded rows ``rows``), from the
    encoded file's row ends ``index`` (row ``trial * n_trains + train``)."""
    ends = index.reshape(-1, n_trains)
    begins = np.concatenate([[0], index[:-1]]).reshape(-1, n_trains)
    return np.asarray((ends[rows] - begins[rows]).T, np.int64)


#: spikes of one unit decoded at a time (its trials in blocks): ~8 MB for each temporary array
_UNIT_BLOCK_SPIKES = 1 << 20
#: stored spikes of a group of units held at once (4-byte ticks: 128 MB): a variant is read once per group of its
#: units (a paper-size variant, ~10^8 spikes: 4 groups)
_UNIT_GROUP_SPIKES = 1 << 25
#: stored spikes read at once while a group's are gathered (a block of trials: 32 MB of ticks)
_UNIT_READ_SPIKES = 1 << 23


def _unit_groups(lens: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive units ``(j0, j1)`` whose stored spikes (``lens`` (n_trials, n_trains) counts of every encoded
    trial) sum to at most ``limit`` (at least one unit each)."""
    return _blocks(lens.sum(axis=0), limit)


def _group_raw(enc: Any, variant: str, lens: np.ndarray, j0: int, j1: int) -> np.ndarray:
    """The stored spikes of trains ``j0 .. j1 - 1`` of every encoded trial, trial after trial (the stored order
    without the other trains' spikes), read in blocks of trials of at most :data:`_UNIT_READ_SPIKES` spikes."""
    parts = []
    for t0, t1 in _blocks(lens.sum(axis=1), _UNIT_READ_SPIKES):
        raw = enc.spikes_stored(variant, slice(t0, t1))[0]
        keep = np.zeros(lens.shape[1], bool)
        keep[j0:j1] = True
        parts.append(raw[np.repeat(np.tile(keep, t1 - t0), lens[t0:t1].reshape(-1))])
        del raw
    return np.concatenate(parts) if parts else np.zeros(0, np.uint32)


def _unit_spikes(encoded_path: Any, variants: Sequence[str], rows: np.ndarray, starts: np.ndarray
                 ) -> Iterator[tuple[np.ndarray, int]]:
    """Each unit's spike times on session time (its train in each exported trial, shifted by the trial's start),
    unit after unit, variant after variant, each unit in blocks of at most :data:`_UNIT_BLOCK_SPIKES` spikes
    (``n_done`` 1 on a unit's last block). Memory: the stored spikes of a group of units (at most
    :data:`_UNIT_GROUP_SPIKES`, or one unit's) plus a block's; each unit's times are decoded as
    :meth:`rigctl.storage.encoded.EncodedFile.spikes` decodes them (the same operations, so the same numbers)."""
    with _encoded.open_encoded(encoded_path) as enc:
        for v in variants:
            _, tick_s, scale, index, n_trains = enc.spikes_stored(v, times=False)
            scale = scale[rows] if scale is not None and np.any(scale != 1.0) else None
            lens_all = np.diff(np.concatenate([[0], index])).reshape(-1, n_trains)  # (encoded trials, trains)
            for j0, j1 in _unit_groups(lens_all[rows], _UNIT_GROUP_SPIKES):
                raw = _group_raw(enc, v, lens_all, j0, j1)
                glens = lens_all[:, j0:j1]  # the group's rows, in the order they are in ``raw``
                begins = (np.cumsum(glens.reshape(-1)) - glens.reshape(-1)).reshape(glens.shape)[rows]
                lens = np.asarray(glens[rows].T, np.int64)  # (group's trains, exported trials)
                for j in range(j1 - j0):
                    blocks = _blocks(lens[j], _UNIT_BLOCK_SPIKES) or [(0, 0)]
                    for b, (i0, i1) in enumerate(blocks):  # the unit's trials in blocks: bounded temporaries
                        n = lens[j][i0:i1]
                        first = np.concatenate([[0], np.cumsum(n)[:-1]])
                        gather = np.repeat(begins[i0:i1, j] - first, n) + np.arange(int(n.sum()))
                        times = raw[gather].astype(np.float64)
                        del gather
                        if tick_s is not None:
                            times *= tick_s
                        if scale is not None:
                            times *= np.repeat(scale[i0:i1], n)
                        times += np.repeat(starts[i0:i1], n)  # (the same sum as starts + times: addition commutes)
                        yield times, int(b == len(blocks) - 1)
                del raw


def read_nwb_summary(path: str | os.PathLike[str]) -> tuple[NwbSummary, dict[str, np.ndarray]]:
    """Read an exported file back with pynwb: its :class:`NwbSummary` and the arrays ``taxels`` (all samples),
    ``trial_id``, ``start_time``, ``stop_time`` (the trials table)."""
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(str(path), "r") as io:
        nwb = io.read()
        ts = nwb.acquisition["taxels"]
        taxels = np.asarray(ts.data[()])
        trials = nwb.trials.to_dataframe()
        summary = NwbSummary(Path(path), n_trials=len(trials), n_samples=taxels.shape[0],
                             n_channels=taxels.shape[1], rate_hz=float(ts.rate))
        if nwb.units is not None:
            units = nwb.units.to_dataframe()
            for v, g in units.groupby("variant"):
                summary.units[str(v)] = len(g)
                summary.spikes[str(v)] = int(sum(len(x) for x in g["spike_times"]))
        arrays = {"taxels": taxels, "trial_id": trials["trial_id"].to_numpy(),
                  "start_time": trials["start_time"].to_numpy(), "stop_time": trials["stop_time"].to_numpy()}
    return summary, arrays

