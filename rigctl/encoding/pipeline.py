"""Encode a whole session: normalisation, force coefficients, SA/RA spikes, speed scaling, features -> one file.

The paper's pipeline (Fig. 1B; Methods): per-taxel 0-1 normalisation over the whole dataset -> force invariance
(eq. 1, input scaling of SA) -> spiking activity encoding (eqs. 3-5) -> speed invariance (eq. 2) -> SR/SC features.

The data drive every shape: the session's sensor layout (:class:`rigctl.core.sensor.SensorLayout`) gives the channel
count (SA and RA trains per taxel: ``2 x n_channels`` trains, ``2 x n_channels x n_windows`` features), its sample
rate the time base, its texture set (:class:`rigctl.core.textures.TextureSet`) each trial's group.

**Rate.** The Izhikevich model steps in 1 ms (:data:`rigctl.encoding.rate.MODEL_RATE_HZ`, one step per sample at
the paper's 1 kHz). A session at another rate is resampled to 1 kHz first (:mod:`rigctl.encoding.rate`,
``scipy.signal.resample_poly``), as an explicit, logged step recorded in the encoded file (``input_rate_hz``,
``model_rate_hz``, ``resampled``, ``resampling`` attributes); at 1 kHz the readings go to the kernel unchanged.
Spike times are in seconds of the recording either way (a 1 s trial at 100 Hz has spikes within 1 s).

**Windows.** Window length (``window_s``, default 100 ms) and counts are :class:`EncodeParams`: speed-scaled
variants use ``n_windows_scaled`` (default 20, i.e. 2 s at the reference speed, the paper's; None = the longest
trial in scaled time, whole trials), unscaled ones
``n_windows_unscaled`` (default: enough windows for the longest trial of the file, ``ceil(longest / window_s)``;
60 for the paper's dataset, whose longest trials are 6 s), the real-time ones ``n_windows_realtime`` (20).

**Speed.** Only the speed-scaled variants (eq. 2: ``speed_scaled``, ``speed_force_scaled``,
``speed_force_scaled_label_free``, ``realtime_speed_scaled``) need each trial's speed; a trial whose speed is NaN
(e.g. an imported recording) is fine for the others. Asked for explicitly (``variants=[...]``, ``rigctl encode
--variant``), a speed-scaled variant with trials lacking a speed is an error naming the trials; with the default
(all variants), those variants are skipped with a warning and listed in the file's ``skipped_variants`` attribute.
(``realtime_speed_scaled`` uses a trial's measured speed trace when it has one, its speed label otherwise.)

Passes over the session (trials are read in batches; a paper-sized dataset, 24,000 trials of 2-6 s x 18 taxels,
is 3 GB as uint16 and 12 GB as float64, so nothing float64 is held for more than a batch):

1. **Range pass:** per-taxel min/max over every trial (of the model input, i.e. after resampling if any:
   :class:`~rigctl.encoding.normalise.TaxelRange`); the model input is kept in memory for the force fit, as long
   as it fits ``fit_memory_bytes`` (default 1 GB: about 7,000 of the paper's 2-6 s trials as uint16). If it does
   not, an even subsample of trials per condition is kept instead (each coefficient then comes from fewer trials:
   at the paper's size (3.5 GB of counts) about 29 of each condition's 100; the count used is stored in the
   attributes), and the encode pass reads each batch again. Peak memory is therefore independent of the dataset's
   size: ``fit_memory_bytes`` plus one batch's readings and spike trains plus the libraries (about 1.6 GB at the
   defaults; measured in ``benchmarks/bench_paper.py``). The kernel normalises ``uint16`` counts on the fly, so the fit never makes a float
   copy of 1 kHz sessions. The counts kept (the fit's subsample, or every trial) are those the trial validator
   read for its check, handed over as it passes them (:class:`rigctl.storage.validate.KeptTaxels`), not read again;
   where the batches are read again, the range is folded from the per-taxel extremes the validator found in them.
2. **Force fit** (once, all coefficients together): per (texture, taxel, speed, force) and label-free per
   (taxel, speed, force). A session without a 500 g reference for some (texture, speed) gets coefficients 1 and
   an attribute saying so.
3. **Encode pass:** batches of ``batch_trials`` trials are encoded (SA with C = 1 and with C, RA once) and turned
   into features of every variant; in this process with numba using all cores, or as tasks on a Dask cluster
   (``scheduler`` = an address, or ``"local"`` for a local cluster of processes). Workers read the session file
   themselves (so it must be on a path they can see) and return features and spike trains; this process writes
   them in trial order.

The output is written by :class:`rigctl.storage.encoded.EncodedWriter` (layout and schema there) and read with
:func:`rigctl.storage.encoded.open_encoded`. Variants and their names: :data:`rigctl.storage.encoded.VARIANTS`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
import warnings
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.cluster import dask_client
from rigctl.core.progress import ProgressCallback, Stage, note as progress_note
from rigctl.core.provenance import PROVENANCE_ATTR, provenance_json, software_provenance
from rigctl.core.sensor import SensorLayout
from rigctl.encoding.batch_encode import (
    _encode_read,
    _realtime_taxels,
    _tick_source,
    encode_batch,
    trains_to_features,
)
from rigctl.encoding.force import ForceCoefficients, fit_scalers
from rigctl.encoding.fused import kernels_cached
from rigctl.encoding.izhikevich import Ragged, as_ragged
from rigctl.encoding.lengths import crop_samples, length_imbalance
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.rate import RateConversion, rate_conversion
from rigctl.encoding.sizing import windows_for
from rigctl.encoding.speed import (
    speed_coefficient,
    window_speeds,
)
from rigctl.encoding.trial_labels import operator_paced, plan_labels, trial_labels
from rigctl.storage.encoded import ALL_VARIANTS, MAIN_VARIANTS, VARIANTS, EncodedWriter
from rigctl.storage.outputs import check_output

__all__ = ["EncodeParams", "encode_session", "encode_batch", "trains_to_features", "SpeedMissingError", "windows_for"]

log = logging.getLogger(__name__)


class SpeedMissingError(ValueError):
    """A speed-scaled variant was asked for, but some trials have no speed (NaN or <= 0 mm/s)."""


def _cropped(blk, crop_s: float | None, rate_hz: float):
    """``blk`` (a :class:`rigctl.storage.session.TaxelBlock`) with every trial cut to its first ``crop_s`` seconds
    (its speed trace too); unchanged when ``crop_s`` is None. A trial shorter than that is refused (ValueError,
    checked in the range pass)."""
    n = crop_samples(crop_s, rate_hz)
    if n is None:
        return blk
    lengths = np.diff(blk.starts)
    keep = np.minimum(lengths, n)
    data = np.concatenate([blk.data[blk.starts[i]:blk.starts[i] + keep[i]] for i in range(len(lengths))]) \
        if len(lengths) else blk.data
    traces = None if blk.speed_traces is None else [(t[t < crop_s], v[t < crop_s]) for t, v in blk.speed_traces]
    return dataclasses.replace(blk, data=data, starts=np.concatenate([[0], np.cumsum(keep)]).astype(np.int64),
                               speed_traces=traces)


def _model_input(blk, ids, labels_speed, want_window_speed, window_s, conv: RateConversion):
    """A :class:`rigctl.storage.session.TaxelBlock` -> the model input (a Ragged of the raw counts, or resampled
    trials if ``conv`` says so) and, if asked, each trial's window speeds (its measured speed trace, else its speed
    label)."""
    lengths = np.diff(blk.starts)
    if conv.resampled:
        rg = as_ragged([conv.apply(blk.data[blk.starts[i]:blk.starts[i + 1]]) for i in range(len(ids))])
    else:
        rg = Ragged(blk.data, blk.starts)
    wspeeds = None
    if want_window_speed:
        wspeeds = []
        for i in range(len(ids)):
            dur = lengths[i] / conv.input_rate_hz
            t, v = blk.speed_traces[i]
            wspeeds.append(window_speeds(t, v, dur, window_s) if v.size else
                           np.full(windows_for(dur, window_s), labels_speed[i]))
    return rg, wspeeds


def _read_batch(session_path, ids, labels_speed, want_window_speed, window_s, conv: RateConversion,
                crop_s: float | None = None):
    """Model input of the trials ``ids`` read in one block (:meth:`rigctl.storage.session.Session.read_taxels`)
    and, if asked, their window speeds (:func:`_model_input`)."""
    from rigctl.storage.session import open_session

    with open_session(session_path) as s:
        blk = s.read_taxels([int(t) for t in ids], traces=want_window_speed)
    return _model_input(_cropped(blk, crop_s, conv.input_rate_hz), ids, labels_speed, want_window_speed, window_s,
                        conv)


def _batch_task(session_path, ids, speed, coeffs, coeffs_lf, offset, scale, variants, store_spikes, params,
                n_threads=None):
    """One unit of work (runs in this process or on a Dask worker): read, encode, featurise a batch."""
    if n_threads:
        import numba

        numba.set_num_threads(min(int(n_threads), numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    want_ws = "realtime_speed_scaled" in variants
    conv = rate_conversion(params.input_rate_hz, params.fs_hz) if params.input_rate_hz else \
        RateConversion(params.fs_hz, params.fs_hz)
    rg, ws = _read_batch(session_path, ids, speed, want_ws, params.window_s, conv, params.crop_s)
    return _encode_read(rg, ws, speed, coeffs, coeffs_lf, offset, scale, variants, store_spikes, params)


def _add_spike_tables(writer, store_spikes, n_ch: int, p: EncodeParams) -> None:
    """Make the ``/spikes`` tables of ``store_spikes`` (bases before their speed-scaled twins) in the encoded file.

    Spike times are stored as ticks of the model step (``1 / fs``) times a per-trial scale (:func:`_time_scale`):
    1, or eq. 2's speed / reference for the speed-scaled variants, which share their unscaled base's ticks when it is
    stored too. The real-time speed-scaled variant (100 ms batches of their own scale) keeps float64 times."""
    tick_s = 1.0 / float(p.fs_hz)  # the fused kernel's time step (run_fused: time = sample * (1 / fs))
    for v in store_spikes:
        info = VARIANTS[v]
        if info.realtime:
            taxels = p.realtime_taxels or []  # set by encode_session before the tables are made
            n_trains, trains = len(taxels), f"SA, real-time taxels {taxels}"
        else:
            n_trains, trains = 2 * n_ch, "SA taxels 0..n-1 then RA taxels 0..n-1"
        if info.realtime and info.speed_scaled:
            writer.add_spikes(v, n_trains, trains)
            continue
        base = _tick_source(v, store_spikes)
        writer.add_spikes(v, n_trains, trains, tick_s=tick_s, ticks_from=base if base not in (None, v) else None)


def _time_scale(variant: str, speed_mm_s, p: EncodeParams):
    """The per-trial factor a stored variant's times carry beyond ``ticks x tick_s`` (:func:`_add_spike_tables`):
    eq. 2's speed / reference for the speed-scaled variants, None (1) otherwise."""
    info = VARIANTS[variant]
    return speed_coefficient(speed_mm_s, p.reference_speed_mm_s) if info.speed_scaled and not info.realtime else None


def _fit_subsample(keys, nbytes, budget):
    """Indices of trials kept for the force fit: all if they fit ``budget`` bytes, else an even subsample per
    condition."""
    total = nbytes.sum()
    if total <= budget:
        return np.arange(keys.size)
    frac = budget / total
    keep = []
    for k in np.unique(keys):
        idx = np.flatnonzero(keys == k)
        m = max(1, int(len(idx) * frac))
        keep.append(idx[np.linspace(0, len(idx) - 1, m).round().astype(int)])
    return np.sort(np.concatenate(keep))


def _fit_forces(fit_rg, labels_fit, offset, scale, p: EncodeParams):
    """Both groupings of eq. (1) (per texture, label-free) in one bisection (one kernel pass per step for both).
    Returns [(scaler or None, note)] for per texture, then label-free."""
    scalers = [ForceCoefficients(label_free=lf, reference_force_g=p.reference_force_g, eps=p.epsilon, c_max=p.c_max,
                           k=p.k_sa, fs=p.fs_hz) for lf in (False, True)]
    errors = fit_scalers(scalers, fit_rg, labels_fit["texture"], labels_fit["speed_mm_s"], labels_fit["force_g"],
                         offset=offset, scale=scale)
    out = []
    for sc, err in zip(scalers, errors):
        if err:
            warnings.warn(f"force coefficients not fitted ({err}); using C = 1", stacklevel=3)
        out.append((None if err else sc, err))
    return out


def _trial_list(ids) -> str:
    ids = [int(t) for t in ids]
    shown = ", ".join(str(t) for t in ids[:10])
    return shown + (f" (+{len(ids) - 10} more)" if len(ids) > 10 else "")


def _check_speeds(variants, explicit, labels, has_trace) -> tuple[tuple[str, ...], dict[str, Any]]:
    """Drop (default variants) or refuse (explicit ones) the speed-scaled variants when some trials have no speed.
    Returns the variants to encode and {skipped variant: reason}."""
    speed = labels["speed_mm_s"]
    no_speed = ~(np.isfinite(speed) & (speed > 0))
    keep, skipped = [], {}
    for v in variants:
        info = VARIANTS[v]
        missing = no_speed & ~has_trace if info.realtime else no_speed
        if not info.speed_scaled or not missing.any():
            keep.append(v)
            continue
        bad = labels["trial_id"][missing]
        reason = (f"{v} scales spike times by each trial's speed (eq. 2), but {bad.size} of {speed.size} trials have "
                  f"no speed (NaN or <= 0 mm/s): trials {_trial_list(bad)}")
        if explicit:
            raise SpeedMissingError(reason + "; encode without the speed-scaled variants (e.g. --variant original "
                                    "--variant force_scaled) or record the trials' speeds")
        skipped[v] = reason
        warnings.warn(f"skipping {reason}", stacklevel=3)
    return tuple(keep), skipped


def encode_session(session_path, out_path, *, variants=None, batch_trials: int = 256,
                   scheduler: str | None = None, workers: int | None = None,
                   progress: ProgressCallback | None = None,
                   trial_ids=None, store_spikes=MAIN_VARIANTS, fit_memory_bytes: float = 1e9,
                   params: EncodeParams | None = None, overwrite: bool = False,
                   keep_nonfinite: bool = False, taxel_range: TaxelRange | None = None) -> Path:
    """Encode a session file (``rigctl.storage.session``) into an encoded file (:mod:`rigctl.storage.encoded`).

    Parameters
    ----------
    session_path : path of a session .h5 (complete trials are encoded, in plan order).
    out_path : the encoded .h5 to write (written under ``<name>.part`` and renamed when done).
    variants : subset of :data:`rigctl.storage.encoded.ALL_VARIANTS`; None = all of them, except speed-scaled ones
        when some trials have no speed (skipped with a warning; see the module docstring).
    batch_trials : trials per batch (memory: about batch_trials x 6 s x n_channels x 30 bytes at 1 kHz).
    scheduler : None -> this process (numba, all cores); ``"local"`` -> a local Dask cluster of ``workers``
        processes; an address ``"tcp://host:8786"`` -> that Dask cluster (workers must see ``session_path``).
    workers : worker processes for ``scheduler="local"`` (default: cores).
    progress : callback receiving :class:`rigctl.core.progress.ProgressEvent` s: stages ``"reading trials"`` (the
        range pass) and ``"encoding"`` (done/total = trials), and notes (a first run's kernel compilation,
        resampling, lossy trials, the force fit).
    trial_ids : optional subset of trial ids.
    store_spikes : variants whose spike trains are written under /spikes.
    fit_memory_bytes : memory allowed for the readings kept for the force fit (see module docstring).
    params : :class:`EncodeParams` (window length and counts, model constants); ``input_rate_hz`` is set from the
        session's layout, ``n_windows_unscaled`` None from the longest trial.
    overwrite : replace an existing ``out_path`` (False: FileExistsError).
    keep_nonfinite : encode trials whose force or speed traces hold NaN/inf (the validator's ``keep_nonfinite``;
        default: excluded like damaged trials).
    taxel_range : normalise with this per-taxel range (ADC counts of the model input) instead of the session's own:
        the paper's one initial range (another block's, e.g. a handheld training block's
        ``EncodedFile.normalisation``: ``rigctl encode --range-from TRAINING.enc.h5``); its taxel count must be the
        session's (ValueError). Recorded as the file's ``range_from`` attribute (its ``source``).

    Returns
    -------
    Path of the written file.

    Raises
    ------
    FileNotFoundError / SessionError from :func:`rigctl.storage.session.open_session`; FileExistsError (see
    ``overwrite``); :class:`SpeedMissingError` (a ValueError) when an explicitly asked speed-scaled variant meets
    trials without a speed; ValueError for unknown variants, a session without complete trials, or a sample rate
    that cannot be resampled to the model's.
    """
    run = EncodeRun.of(session_path, out_path, variants=variants, batch_trials=batch_trials, scheduler=scheduler,
                       workers=workers, trial_ids=trial_ids, store_spikes=store_spikes,
                       fit_memory_bytes=fit_memory_bytes, overwrite=overwrite, keep_nonfinite=keep_nonfinite,
                       taxel_range=taxel_range)
    p = replace(params) if params is not None else EncodeParams()
    t_start = time.time()
    read = _range_pass(run, p, progress)  # pass 1: labels, per-taxel range, the model input kept for the fit
    imbalance = length_imbalance(read.labels["texture"], read.duration_s, speed_mm_s=read.labels["speed_mm_s"],
                                 force_g=read.labels["force_g"], profile=read.labels["profile"],
                                 operator_paced=read.operator_paced)
    if imbalance:  # a label hidden in the trial length (rigctl.encoding.lengths)
        warnings.warn(f"{run.session_path}: {imbalance}", stacklevel=2)
    variants_, skipped = _check_speeds(run.variants, run.explicit, read.labels, read.has_trace)
    if not variants_:
        raise SpeedMissingError("nothing to encode: " + "; ".join(skipped.values()))
    run = replace(run, variants=variants_, store_spikes=tuple(sorted(  # bases before their speed-scaled twins
        (v for v in run.store_spikes if v in variants_), key=lambda v: VARIANTS[v].speed_scaled)))
    windows_note = _fix_windows(p, read)
    force = _force_pass(run, p, read, progress)  # once, for the whole dataset
    writer = EncodedWriter(run.out_path, layout=read.layout, textures=read.textures, trials=_trials_table(read),
                           parameters=asdict(p), overwrite=run.overwrite, attrs={
                               "input_rate_hz": read.conv.input_rate_hz, "model_rate_hz": read.conv.model_rate_hz,
                               "resampled": read.conv.resampled, "resampling": read.conv.describe(),
                               "windows_note": windows_note, "skipped_variants": skipped,
                               "source_session": str(run.session_path), "variants": list(run.variants),
                               "range_from": "" if run.taxel_range is None else str(run.taxel_range.source),
                               "excluded_trials": {str(k): v for k, v in read.excluded.items()},
                               "lossy_trials": sorted(read.lossy), "lost_frames": int(sum(read.lossy.values())),
                               "operator_paced": read.operator_paced,
                               PROVENANCE_ATTR: provenance_json(_provenance(run, p))})
    try:
        _write_tables(writer, run, p, read, force)
        _encode_pass(writer, run, p, read, force, progress)  # pass 2: encode in batches
        n_ch = int(read.offset.size)
        writer.set_attrs(
            parameters=json.dumps(asdict(p)),
            feature_layout=(f"train-major: [SA_0 windows, ..., SA_n-1, RA_0, ..., RA_n-1] for n = {n_ch} taxels; "
                            f"SR spikes/s (speed-scaled: x speed/{p.reference_speed_mm_s:g}), SC counts; "
                            f"{p.window_s * 1000:g} ms windows: {p.n_windows_unscaled} unscaled, "
                            f"{p.n_windows_scaled} speed-scaled, {p.n_windows_realtime} real-time"),
            encode_seconds=time.time() - t_start, scheduler=str(run.scheduler))
    except BaseException:
        writer.abort()
        raise
    return writer.close()


@dataclass(frozen=True)
class EncodeRun:
    """How :func:`encode_session` runs (what it computes is :class:`EncodeParams`): the files, the variants, the
    batches, where the work runs, the memory for the force fit. ``explicit``: the variants were asked for."""

    session_path: Path
    out_path: Path
    variants: tuple[str, ...]
    explicit: bool
    batch_trials: int = 256
    scheduler: str | None = None
    workers: int | None = None
    trial_ids: tuple[int, ...] | None = None
    store_spikes: tuple[str, ...] = MAIN_VARIANTS
    fit_memory_bytes: float = 1e9
    overwrite: bool = False
    keep_nonfinite: bool = False
    taxel_range: TaxelRange | None = None  # the range to normalise with (None: the session's own)

    @classmethod
    def of(cls, session_path: Any, out_path: Any, *, variants: Any, trial_ids: Any, store_spikes: Any,
           **kw: Any) -> "EncodeRun":
        """Checked: known variants, the output policy (:func:`rigctl.storage.outputs.check_output`) before any
        work. Raises ValueError, FileExistsError, OutputError."""
        chosen = tuple(ALL_VARIANTS if variants is None else variants)
        bad = [v for v in chosen if v not in VARIANTS]
        if bad:
            raise ValueError(f"unknown variants {bad}; choose from {', '.join(ALL_VARIANTS)}")
        run = cls(Path(session_path), Path(out_path), chosen, variants is not None,
                  trial_ids=None if trial_ids is None else tuple(int(t) for t in trial_ids),
                  store_spikes=tuple(store_spikes), **kw)
        if run.out_path.exists() and not run.overwrite:
            raise FileExistsError(f"{run.out_path} exists (pass overwrite=True / --overwrite to replace it)")
        check_output(run.out_path, overwrite=True, inputs=(run.session_path,), kind="encoded")
        return run


def _provenance(run: EncodeRun, p: EncodeParams) -> dict[str, Any]:
    """The encoded file's provenance: this process's, the encoder's parameters and variants, and the source
    session's own provenance (``rigctl.core.provenance``) with its UUID."""
    from rigctl.storage.provenance import ProvenanceError, read_provenance

    try:
        source: dict[str, Any] | None = read_provenance(run.session_path)
    except (ProvenanceError, OSError):
        source = None
    return software_provenance(encoder={"parameters": asdict(p), "variants": list(run.variants)},
                               source_session={"path": str(run.session_path), "provenance": source})


@dataclass
class _Read:
    """What the range pass learnt: the session's sensor and labels, the trials' lengths, the per-taxel range,
    the batches (kept in memory when they fit) and the readings kept for the force fit."""

    layout: SensorLayout
    textures: Any
    ids: list[int]
    labels: dict[str, Any]
    conv: RateConversion
    batches: list[np.ndarray]
    keep_all: bool
    kept: list[Any]
    fit_blocks: list[Any]
    fit_idx: np.ndarray
    n_samples: np.ndarray
    has_trace: np.ndarray
    lossy: dict[int, int]
    excluded: dict[int, str]
    offset: np.ndarray
    scale: np.ndarray
    rng: TaxelRange
    #: the trials' lengths are the operator's (a handheld session: scans bounded by positions on the plate)
    operator_paced: bool = False

    @property
    def duration_s(self) -> np.ndarray:
        return self.n_samples / self.conv.input_rate_hz


@dataclass
class _Force:
    """The force fit's scalers (per texture, label-free; None when not fitted), their notes and per-trial
    coefficients."""

    scaler: Any = None
    scaler_lf: Any = None
    note: str = "not requested"
    note_lf: str = "not requested"
    coeffs: Any = None
    coeffs_lf: Any = None
    n_fit_trials: int = 0


def _usable_ids(s: Any, run: EncodeRun, kept: Any = None) -> tuple[list[int], dict[int, str]]:
    """The trials to encode (the validator's usable ones, or the asked ones that are usable) and the excluded;
    ``kept``: the validator's :class:`~rigctl.storage.validate.KeptTaxels`."""
    from rigctl.storage.ledger import use_warnings
    from rigctl.storage.validate import TrialsExcluded, usable_trials

    # the one trial validator: damaged trials excluded, with their reasons
    report = usable_trials(s, keep_nonfinite=run.keep_nonfinite, kept=kept)
    ids = report.ids if run.trial_ids is None else [t for t in run.trial_ids if t not in report.excluded]
    if report.excluded:
        warnings.warn(f"{run.session_path}: {report.summary()}", TrialsExcluded, stacklevel=4)
    for line in use_warnings(s.attrs, report.repeated_samples, ids):  # held readings, the import's flags: said
        warnings.warn(line, stacklevel=4)
    if not ids:
        raise ValueError(f"{run.session_path} has no usable complete trials"
                         + (f" ({report.summary()})" if report.excluded else ""))
    return ids, report.excluded


def _range_pass(run: EncodeRun, p: EncodeParams, progress: ProgressCallback | None) -> _Read:
    """Pass 1: read the trials once, in blocks of ``batch_trials`` (the encode pass's batches): per-taxel range,
    lengths, lost frames; the blocks are kept for the force fit and the encode pass when they fit
    ``fit_memory_bytes``, else the fit keeps an even subsample and the encode pass reads each batch again."""
    from rigctl.storage.session import open_session

    with open_session(run.session_path) as s:
        kept = _kept_for_fit(s, run, p)
        ids, excluded = _usable_ids(s, run, kept)
        labels = trial_labels(s, ids)
        conv = rate_conversion(s.layout.sample_rate_hz, p.fs_hz)
        p.input_rate_hz, p.fs_hz = conv.input_rate_hz, conv.model_rate_hz
        log.info("rate: %s", conv.describe())
        if conv.resampled:
            progress_note(progress, "reading trials", f"resampling: {conv.describe()}")
        keep = _fit_keep(s, ids, labels, conv, run.fit_memory_bytes)
        keep_all = len(keep) == len(ids)
        want_ws = "realtime_speed_scaled" in run.variants
        bt = run.batch_trials
        batches = [np.arange(i, min(i + bt, len(ids))) for i in range(0, len(ids), bt)]
        read = _Read(s.layout, s.textures, ids, labels, conv, batches, keep_all, [], [], np.zeros(0, np.int64),
                     np.zeros(len(ids), dtype=np.int64), np.zeros(len(ids), dtype=bool), {}, excluded,
                     np.zeros(0), np.zeros(0), TaxelRange(), operator_paced(s, ids))
        if not kernels_cached():
            progress_note(progress, "reading trials", "compiling the encoding kernels (first run only: numba "
                                                      "caches them) ...")
        fit_idx: list[int] = []
        bar = Stage(progress, "reading trials", len(ids))
        known = None if keep_all or conv.resampled or p.crop_s is not None else _extremes_known(s, ids, run)
        for b in batches if known is None else ():
            b_ids = [ids[i] for i in b]
            blk = kept.block(s, b_ids, traces=want_ws) if keep_all else None
            blk = s.read_taxels(b_ids, traces=want_ws and keep_all) if blk is None else blk
            _check_crop(p.crop_s, np.diff(blk.starts) / conv.input_rate_hz, b_ids)
            blk = _cropped(blk, p.crop_s, conv.input_rate_hz)
            read.n_samples[b] = np.diff(blk.starts)
            read.has_trace[b] = blk.has_speed_trace
            read.lossy.update({int(t): int(n) for t, n in zip(b_ids, blk.dropped_frames) if n})
            rg, ws = _model_input(blk, b_ids, labels["speed_mm_s"][b], want_ws and keep_all, p.window_s, conv)
            del blk
            read.rng.update(rg.data)
            if keep_all:
                read.kept.append((rg, ws))
                read.fit_blocks.append(rg)
                fit_idx.extend(b.tolist())
            else:
                sel = [j for j, i in enumerate(b) if i in keep]
                if sel:
                    read.fit_blocks.append(rg.select(sel))
                    fit_idx.extend(b[sel].tolist())
            bar.advance(len(b))
        if known is not None:
            _range_from_extremes(s, read, known, keep, fit_idx, bar, kept)
    read.fit_idx = np.asarray(fit_idx, dtype=np.int64)
    _note_lossy(read, progress)
    if np.any(read.n_samples == 0):
        raise ValueError("a complete trial has no samples: trials "
                         f"{_trial_list(np.asarray(ids)[read.n_samples == 0])}")
    if run.taxel_range is not None:  # one normalisation for several blocks (the paper's initial range)
        given, n_own = run.taxel_range, 0 if read.rng.minimum is None else read.rng.minimum.size
        n_given = 0 if given.minimum is None else given.minimum.size
        if n_given != n_own:
            raise ValueError(f"the range given ({given.source or 'range_from'}) has {n_given} taxels, the session "
                             f"{n_own}")
        read.rng = given
    read.offset, read.scale = read.rng.offset_scale()
    return read


def _extremes_known(s: Any, ids: list[int], run: EncodeRun) -> dict[int, np.ndarray] | None:
    """Each trial's per-taxel extremes as the session's validator read them (``TrialReport.taxel_extremes``), when
    it has them for every trial of ``ids`` (schema 4), else None."""
    from rigctl.storage.validate import usable_trials

    known = usable_trials(s, keep_nonfinite=run.keep_nonfinite).taxel_extremes
    return known if known and all(t in known for t in ids) else None


def _range_from_extremes(s: Any, read: _Read, known: dict[int, np.ndarray], keep: set[int], fit_idx: list[int],
                         bar: Stage, kept: Any = None) -> None:
    """Pass 1 without reading every sample (a session whose batches are read again by the encode pass, neither
    resampled nor cropped): the per-taxel range folded from each trial's extremes the validator found in the same
    counts (the range over the raw counts is the same, exactly), the lengths, traces and lost frames from
    ``/recording/index``, and only the force fit's subsample read, in the batches' order (the same blocks as
    ``Ragged.select`` of the full read), or taken from the validator's read (``kept``) where it kept them."""
    index = s.recording_index()
    for b in read.batches:
        b_ids = [read.ids[i] for i in b]
        rows = [index[t] for t in b_ids]
        read.n_samples[b] = [int(r["n_samples"]) for r in rows]
        read.has_trace[b] = [int(r["n_speed"]) > 0 for r in rows]
        read.lossy.update({int(t): int(r["dropped_frames"]) for t, r in zip(b_ids, rows) if int(r["dropped_frames"])})
        ext = np.stack([known[t] for t in b_ids])  # (trials, 2, taxels)
        read.rng.fold(ext[:, 0].min(axis=0), ext[:, 1].max(axis=0), int(read.n_samples[b].sum()))
        sel = [j for j, i in enumerate(b) if i in keep]
        if sel:
            blk = None if kept is None else kept.block(s, [b_ids[j] for j in sel])
            blk = s.read_taxels([b_ids[j] for j in sel]) if blk is None else blk
            read.fit_blocks.append(Ragged(blk.data, blk.starts))
            fit_idx.extend(b[sel].tolist())
        bar.advance(len(b))


def _kept_for_fit(s: Any, run: EncodeRun, p: EncodeParams) -> Any:
    """What the validator's read keeps for pass 1 (:class:`~rigctl.storage.validate.KeptTaxels`): the force fit's
    subsample (every trial when they all fit ``fit_memory_bytes``) as chosen among the trials asked for, or all
    complete ones: the validator's usable trials unless it excludes some, when pass 1 reads what the subsample of the
    usable ones then lacks. So the fit's counts are read once, by the check. Nothing is kept for a rate the model
    cannot take (the encode then says so, after the check)."""
    from rigctl.storage.validate import KeptTaxels

    try:
        conv = rate_conversion(s.layout.sample_rate_hz, p.fs_hz)
    except ValueError:
        return KeptTaxels(s, ())
    ids = s.completed_ids()
    if run.trial_ids is not None:
        complete = set(ids)
        ids = [t for t in run.trial_ids if t in complete]
    keep = _fit_keep(s, ids, plan_labels(s, ids), conv, run.fit_memory_bytes) if ids else set()
    bt = run.batch_trials  # each batch's share of the subsample: the blocks pass 1 takes (as _range_pass's batches)
    return KeptTaxels(s, ([ids[i] for i in range(k, min(k + bt, len(ids))) if i in keep]
                          for k in range(0, len(ids), bt)))


def _check_crop(crop_s: float | None, duration_s: np.ndarray, ids: list[int]) -> None:
    """Refuse a crop longer than a trial (ValueError naming the trials: cropping cannot lengthen them)."""
    if crop_s is None:
        return
    short = [t for t, d in zip(ids, duration_s) if d + 1e-9 < crop_s]
    if short:
        raise ValueError(f"--crop-s {crop_s:g}: trials {_trial_list(np.asarray(short))} are shorter (shortest "
                         f"{float(np.min(duration_s)):.2f} s): crop to a length every trial has")


def _fit_keep(s: Any, ids: list[int], labels: dict[str, Any], conv: RateConversion, budget: float) -> set[int]:
    """Indices of the trials kept in memory for the force fit (all of them when they fit ``budget`` bytes)."""
    keys = np.array([f"{t}|{v:.3f}|{f:.3f}" for t, v, f in zip(labels["texture"], labels["speed_mm_s"],
                                                                 labels["force_g"])])
    plan_dur = ({int(r["trial_id"]): float(r["duration_s"]) for r in s.plan}
                if "duration_s" in (s.plan.dtype.names or ()) else {})
    item = 2 if not conv.resampled else 8  # bytes per kept value: uint16 counts, or float64 after resampling
    est = np.array([plan_dur.get(t, 6.0) * conv.model_rate_hz * s.layout.n_channels * item for t in ids])
    return set(_fit_subsample(keys, est, budget).tolist())


def _note_lossy(read: _Read, progress: ProgressCallback | None) -> None:
    """Kept trials recorded with lost frames are encoded as recorded, and said (failed trials never are)."""
    if not read.lossy:
        return
    lossy = read.lossy
    note = (f"{len(lossy)} of {len(read.ids)} trials were recorded with lost frames ({sum(lossy.values())} frames; "
            f"trials {_trial_list(sorted(lossy))}): encoded as recorded, listed in the lossy_trials attribute")
    log.warning("%s", note)
    progress_note(progress, "reading trials", note)


def _fix_windows(p: EncodeParams, read: _Read) -> str:
    """Window counts left to the data (None): from the longest trial (unscaled) or the longest in scaled time;
    the real-time taxels. Returns the note stored in the file."""
    duration_s = read.duration_s
    longest_s = float(duration_s.max())
    note = f"{p.n_windows_unscaled} unscaled windows of {p.window_s * 1000:g} ms (as asked)"
    if p.n_windows_unscaled is None:
        p.n_windows_unscaled = windows_for(longest_s, p.window_s)
        note = (f"{p.n_windows_unscaled} unscaled windows of {p.window_s * 1000:g} ms cover the longest trial "
                f"({longest_s:.3f} s)")
    if p.n_windows_scaled is None:
        speed = read.labels["speed_mm_s"]
        ok = np.isfinite(speed) & (speed > 0)
        scaled_s = float(np.max(duration_s[ok] * speed[ok] / p.reference_speed_mm_s, initial=0.0))
        p.n_windows_scaled = windows_for(scaled_s, p.window_s)
        note += (f"; {p.n_windows_scaled} speed-scaled windows cover the longest trial in scaled time "
                 f"({scaled_s:.3f} s at {p.reference_speed_mm_s:g} mm/s)")
    if p.realtime_taxels is None:
        p.realtime_taxels = _realtime_taxels(p, read.layout.n_channels, read.layout)
    log.info("windows: %s", note)
    return note


def _force_pass(run: EncodeRun, p: EncodeParams, read: _Read, progress: ProgressCallback | None) -> _Force:
    """Eq. (1)'s coefficients, once for the whole dataset (when a force-scaled variant is asked for); the kept
    fit readings are freed."""
    labels = read.labels
    labels_fit = {k: v[read.fit_idx] for k, v in labels.items()}
    fit_rg, read.fit_blocks = read.fit_blocks, []
    force = _Force(n_fit_trials=int(read.fit_idx.size))
    if any(VARIANTS[v].force_scaled for v in run.variants):
        progress_note(progress, "force fit", f"fitting force coefficients on {read.fit_idx.size} trials ...")
        (force.scaler, force.note), (force.scaler_lf, force.note_lf) = _fit_forces(fit_rg, labels_fit, read.offset,
                                                                                   read.scale, p)
    del fit_rg
    args = (labels["texture"], labels["speed_mm_s"], labels["force_g"])
    force.coeffs = force.scaler.coefficients_for(*args) if force.scaler else None
    force.coeffs_lf = force.scaler_lf.coefficients_for(*args) if force.scaler_lf else None
    return force


def _trials_table(read: _Read) -> dict[str, Any]:
    return {**read.labels, "group": np.array([read.textures.group_of(t) or "" for t in read.labels["texture"]],
                                             dtype=str),
            "duration_s": read.duration_s, "n_samples": read.n_samples}


def _write_tables(writer: EncodedWriter, run: EncodeRun, p: EncodeParams, read: _Read, force: _Force) -> None:
    """The normalisation, the force coefficient tables (or why there are none) and the spike tables."""
    writer.write_normalisation(read.rng.minimum, read.rng.maximum,
                               source="whole dataset (per-taxel min/max over every encoded trial, of the model input)")
    for lf, sc, note in ((False, force.scaler, force.note), (True, force.scaler_lf, force.note_lf)):
        if sc is not None:
            writer.write_force_coefficients(sc.table(), label_free=lf, n_not_converged=sc.n_not_converged_,
                                            n_coefficients=sc.fit_.n_coefficients, n_iter=sc.fit_.n_iter,
                                            n_fit_trials=force.n_fit_trials)
        else:
            writer.note_force_coefficients(note, label_free=lf)
    _add_spike_tables(writer, run.store_spikes, int(read.offset.size), p)


def _encode_pass(writer: EncodedWriter, run: EncodeRun, p: EncodeParams, read: _Read, force: _Force,
                 progress: ProgressCallback | None) -> None:
    """Pass 2: every batch encoded (here with numba on all cores, or as tasks on a Dask cluster) and written in
    trial order."""
    speed = read.labels["speed_mm_s"]

    def write(batch: np.ndarray, result: Any) -> None:
        feats, spikes = result
        for v, f in feats.items():
            writer.write_features(v, int(batch[0]), f)
        for v in run.store_spikes:  # bases before their speed-scaled twins
            if isinstance(spikes[v], tuple):  # (ticks, row ends): _encode_read
                ticks, ends = spikes[v]
                writer.append_spike_ticks(v, ticks, ends, _time_scale(v, speed[batch], p))
            else:
                writer.append_spikes(v, spikes[v], _time_scale(v, speed[batch], p))

    args = [(str(run.session_path), [read.ids[i] for i in b], speed[b],
             None if force.coeffs is None else force.coeffs[b], None if force.coeffs_lf is None else force.coeffs_lf[b],
             read.offset, read.scale, run.variants, run.store_spikes, p) for b in read.batches]
    bar = Stage(progress, "encoding", len(read.ids))
    if run.scheduler is None:
        from rigctl.storage.session import open_session

        want_ws = "realtime_speed_scaled" in run.variants
        with contextlib.ExitStack() as stack:
            s = None if read.keep_all else stack.enter_context(open_session(run.session_path))

            def load(bi: int) -> tuple[Any, Any]:
                """Batch ``bi``'s model input and window speeds."""
                if s is None:  # read in the range pass
                    rg_ws, read.kept[bi] = read.kept[bi], None  # freed as soon as encoded
                    return rg_ws
                ids_b = args[bi][1]  # read again (the file stays open: one header read for the whole pass)
                blk = _cropped(s.read_taxels(ids_b, traces=want_ws), p.crop_s, read.conv.input_rate_hz)
                return _model_input(blk, ids_b, speed[read.batches[bi]], want_ws, p.window_s, read.conv)

            def encode(loaded: Future[tuple[Any, Any]], a: tuple[Any, ...]) -> Any:
                rg, ws = loaded.result()
                return _encode_read(rg, ws, *a[2:])

            # a reader thread reads batch i + 1 while a worker thread encodes batch i (the kernels release the GIL)
            # and this thread writes batch i - 1: the reads' and the writes' serial time overlap the kernels'
            reader = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="rigctl-read"))
            pool = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="rigctl-encode"))
            ahead: deque[tuple[np.ndarray, Future[Any]]] = deque()
            nxt: Future[tuple[Any, Any]] | None = reader.submit(load, 0) if read.batches else None
            try:
                for bi, (b, a) in enumerate(zip(read.batches, args)):
                    cur, nxt = nxt, reader.submit(load, bi + 1) if bi + 1 < len(read.batches) else None
                    ahead.append((b, pool.submit(encode, cur, a)))  # type: ignore[arg-type]  # set for every batch
                    while len(ahead) > (1 if bi + 1 < len(read.batches) else 0):
                        done_b, fut = ahead.popleft()
                        write(done_b, fut.result())
                        bar.advance(len(done_b))
            finally:
                for fut in [f for _, f in ahead] + ([nxt] if nxt is not None else []):
                    fut.cancel()
        return
    from dask.distributed import as_completed

    client, cluster = dask_client(run.scheduler, run.workers)
    try:
        futures = [client.submit(_batch_task, *a, n_threads=1, pure=False) for a in args]
        index_of = {f.key: i for i, f in enumerate(futures)}
        done, next_i = {}, 0
        for fut in as_completed(futures):
            done[index_of[fut.key]] = fut.result()
            fut.release()
            while next_i in done:  # spikes are appended in trial order
                write(read.batches[next_i], done.pop(next_i))
                bar.advance(len(read.batches[next_i]))
                next_i += 1
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
