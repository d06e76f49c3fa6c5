"""Encode a whole session: normalisation, force coefficients, SA/RA spikes, speed scaling, features -> one file.

The paper's pipeline (Fig. 1B; Methods): per-taxel 0-1 normalisation over the whole dataset -> force invariance
(eq. 1, input scaling of SA) -> spiking activity encoding (eqs. 3-5) -> speed invariance (eq. 2) -> SR/SC features.

Passes over the session (trials are read in batches; a paper-sized dataset, 24,000 trials of 2-6 s x 18 taxels,
is 3 GB as uint16 and 12 GB as float64, so nothing float64 is held for more than a batch):

1. **Range pass:** per-taxel min/max over every trial (:class:`~rigctl.encoding.normalise.TaxelRange`); the raw
   ``uint16`` readings are kept in memory for the force fit, as long as they fit ``fit_memory_bytes`` (default
   4 GB, i.e. the paper-sized dataset). If they do not, an even subsample of trials per condition is kept instead
   (each coefficient then comes from fewer trials; the count used is stored in the attributes). The kernel
   normalises ``uint16`` counts on the fly, so the fit never makes a float copy.
2. **Force fit** (once, all coefficients together): per (texture, taxel, speed, force) and label-free per
   (taxel, speed, force). A session without a 500 g reference for some (texture, speed) gets coefficients 1 and
   an attribute saying so.
3. **Encode pass:** batches of ``batch_trials`` trials are encoded (SA with C = 1 and with C, RA once) and turned
   into features of every variant; in this process with numba using all cores, or as tasks on a Dask cluster
   (``scheduler`` = an address, or ``"local"`` for a local cluster of processes). Workers read the session file
   themselves (so it must be on a path they can see) and return features and spike trains; this process writes
   them in trial order.

Output file (HDF5)::

    /trials                  table: trial_id, texture, group, speed_mm_s, force_g, profile, duration_s, n_samples
    /features/<variant>      (n_trials, n_features) float32
    /spikes/<variant>/       spike_times (s) + spike_times_index (row ends), NWB-style; row = trial*36 + train
    /force_coefficients      table (texture, speed_mm_s, force_g, taxel, coeff, converged, target_rate, rate)
    /force_coefficients_label_free
    /normalisation/          taxel_min, taxel_max (ADC counts)
    attrs: parameters (JSON), n_not_converged, n_coefficients, source session, ...

Variants: ``original`` (2160 features), ``speed_scaled`` (720), ``force_scaled`` (2160), ``speed_force_scaled``
(720), the label-free force variants ``force_scaled_label_free`` / ``speed_force_scaled_label_free``, and the
real-time features (9 top-layer SA trains x 20 windows = 180) ``realtime_original`` / ``realtime_speed_scaled``.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import h5py
import numpy as np

from rigctl.encoding.features import (N_WINDOWS_REALTIME, N_WINDOWS_SCALED, N_WINDOWS_UNSCALED, realtime_features,
                                      realtime_features_unscaled, spike_features)
from rigctl.encoding.filters import ra_input
from rigctl.encoding.force import C_MAX, EPSILON, REFERENCE_FORCE_G, ForceScaler
from rigctl.encoding.izhikevich import FS_HZ, K_RA, K_SA, Ragged, _trains_from_raster, as_ragged, run_izhikevich
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.spikes import SpikeTrains
from rigctl.encoding.speed import (REALTIME_REFERENCE_SPEED_MM_S, REFERENCE_SPEED_MM_S, WINDOW_S,
                                   incremental_scale, speed_coefficient, window_speeds)

from rigctl.texture_set import texture_group  # re-exported

__all__ = ["MAIN_VARIANTS", "ALL_VARIANTS", "EncodeParams", "encode_session", "encode_batch", "texture_group",
           "read_encoded"]

MAIN_VARIANTS = ("original", "speed_scaled", "force_scaled", "speed_force_scaled")
LABEL_FREE_VARIANTS = ("force_scaled_label_free", "speed_force_scaled_label_free")
REALTIME_VARIANTS = ("realtime_original", "realtime_speed_scaled")
ALL_VARIANTS = MAIN_VARIANTS + LABEL_FREE_VARIANTS + REALTIME_VARIANTS

@dataclass
class EncodeParams:
    """Parameters of an encoding run (stored as JSON in the output's ``parameters`` attribute)."""

    fs_hz: float = FS_HZ
    k_sa: float = K_SA
    k_ra: float = K_RA
    cutoff_hz: float = 20.0
    rectify_ra: bool = True
    reference_speed_mm_s: float = REFERENCE_SPEED_MM_S
    realtime_reference_speed_mm_s: float = REALTIME_REFERENCE_SPEED_MM_S
    reference_force_g: float = REFERENCE_FORCE_G
    epsilon: float = EPSILON
    c_max: float = C_MAX
    window_s: float = WINDOW_S
    n_windows_scaled: int = N_WINDOWS_SCALED
    n_windows_unscaled: int = N_WINDOWS_UNSCALED
    n_windows_realtime: int = N_WINDOWS_REALTIME
    realtime_taxels: list = field(default_factory=lambda: list(range(9)))
    izhikevich: dict = field(default_factory=lambda: {"a": 0.02, "b": 0.2, "c": -65.0, "d": 6.0, "v_peak": 30.0})


# ---------------------------------------------------------------------------------------------------------- batch work
def _sa_ra(rg: Ragged, offset, scale, sa_gains: list[np.ndarray], p: EncodeParams):
    """SA trains for each gain matrix in ``sa_gains`` and the RA trains, (n_trials, n_ch) each."""
    out = []
    for gains in sa_gains:
        counts, raster, _ = run_izhikevich(rg, k=p.k_sa, gain=gains, offset=offset, scale=scale)
        out.append(_trains_from_raster(raster, rg.starts, counts, p.fs_hz))
    ra_in = rg.map_trials(lambda tr: ra_input((tr - offset) * scale, cutoff_hz=p.cutoff_hz, fs=p.fs_hz,
                                              rectify=p.rectify_ra))
    counts, raster, _ = run_izhikevich(ra_in, k=p.k_ra)
    return out, _trains_from_raster(raster, ra_in.starts, counts, p.fs_hz)


def encode_batch(rg: Ragged, *, offset, scale, speed_mm_s, coeffs=None, coeffs_label_free=None,
                 window_speed=None, variants=ALL_VARIANTS, params: EncodeParams | None = None,
                 store_spikes=MAIN_VARIANTS) -> tuple[dict, dict]:
    """Encode a batch of trials into every requested variant.

    Parameters
    ----------
    rg : Ragged raw readings (n_trials trials of (n_i, n_ch)), e.g. uint16 ADC counts.
    offset, scale : (n_ch,) normalisation ``(x - offset) * scale`` -> [0, 1].
    speed_mm_s : (n_trials,) trial speed (setpoint) for eq. (2).
    coeffs, coeffs_label_free : (n_trials, n_ch) force coefficients (eq. 1) or None (-> 1).
    window_speed : list of (n_windows,) mm/s per trial (real-time variant) or None (-> constant speed_mm_s).
    variants : names from :data:`ALL_VARIANTS`.
    store_spikes : variants whose spike trains are returned.

    Returns
    -------
    features : {variant: (n_trials, n_features) float32}
    spikes : {variant: SpikeTrains (n_trials, 2 n_ch)}
    """
    p = params or EncodeParams()
    n, n_ch = rg.n_trials, rg.n_channels
    speed = np.asarray(speed_mm_s, np.float64)
    ones = np.ones((n, n_ch))
    need_force = any(v.startswith(("force", "speed_force")) and not v.endswith("label_free") for v in variants)
    need_lf = any(v.endswith("label_free") for v in variants)
    gain_list = [ones]
    if need_force:
        gain_list.append(ones if coeffs is None else coeffs)
    if need_lf:
        gain_list.append(ones if coeffs_label_free is None else coeffs_label_free)
    sas, ra = _sa_ra(rg, offset, scale, gain_list, p)
    sa_by = {"none": sas[0]}
    if need_force:
        sa_by["force"] = sas[1]
    if need_lf:
        sa_by["lf"] = sas[-1]
    coef = speed_coefficient(speed, p.reference_speed_mm_s)
    ra_scaled = ra.scale_times(coef) if any(v.startswith("speed") for v in variants) else None
    feats, spikes = {}, {}
    table = {
        "original": ("none", False), "speed_scaled": ("none", True), "force_scaled": ("force", False),
        "speed_force_scaled": ("force", True), "force_scaled_label_free": ("lf", False),
        "speed_force_scaled_label_free": ("lf", True),
    }
    for v in variants:
        if v in table:
            which, scaled = table[v]
            sa = sa_by[which]
            if scaled:
                sa_v, ra_v = sa.scale_times(coef), ra_scaled
                feats[v] = spike_features(sa_v, ra_v, n_windows=p.n_windows_scaled, window_s=p.window_s,
                                          sr_factor=coef)
            else:
                sa_v, ra_v = sa, ra
                feats[v] = spike_features(sa_v, ra_v, n_windows=p.n_windows_unscaled, window_s=p.window_s)
            if v in store_spikes:
                spikes[v] = SpikeTrains.hstack([sa_v, ra_v])
        elif v in REALTIME_VARIANTS:
            taxels = [t for t in p.realtime_taxels if t < n_ch] or list(range(n_ch))
            sa9 = sa_by["none"].select_trains(taxels)
            if v == "realtime_original":
                feats[v] = realtime_features_unscaled(sa9, rg.lengths / p.fs_hz, n_windows=p.n_windows_realtime,
                                                      window_s=p.window_s)
            else:
                ws = window_speed
                if ws is None:
                    ws = [np.full(max(1, math.ceil(round(L / p.fs_hz / p.window_s, 9))), s)
                          for L, s in zip(rg.lengths, speed)]
                scaled, edges = incremental_scale(sa9, ws, p.realtime_reference_speed_mm_s, p.window_s)
                feats[v] = realtime_features(scaled, edges, n_windows=p.n_windows_realtime, window_s=p.window_s)
            if v in store_spikes:
                spikes[v] = sa9
        else:
            raise ValueError(f"unknown variant {v!r}; choose from {ALL_VARIANTS}")
    return feats, spikes


def _read_batch(session_path, ids, labels_speed, want_window_speed, window_s):
    from rigctl.storage.session import open_session

    arrays, wspeeds = [], []
    with open_session(session_path) as s:
        for i, tid in enumerate(ids):
            tr = s.trial(int(tid))
            arrays.append(np.asarray(tr.taxels))
            if want_window_speed:
                dur = tr.taxels.shape[0] / FS_HZ
                if tr.speed_mm_s.size:
                    wspeeds.append(window_speeds(tr.speed_time_s, tr.speed_mm_s, dur, window_s))
                else:
                    wspeeds.append(np.full(max(1, math.ceil(round(dur / window_s, 9))), labels_speed[i]))
    return as_ragged(arrays), (wspeeds if want_window_speed else None)


def _batch_task(session_path, ids, speed, coeffs, coeffs_lf, offset, scale, variants, store_spikes, params,
                n_threads=None):
    """One unit of work (runs in this process or on a Dask worker): read, encode, featurise a batch."""
    if n_threads:
        import numba

        numba.set_num_threads(min(int(n_threads), numba.config.NUMBA_NUM_THREADS))
    want_ws = "realtime_speed_scaled" in variants
    rg, ws = _read_batch(session_path, ids, speed, want_ws, params.window_s)
    return encode_batch(rg, offset=offset, scale=scale, speed_mm_s=speed, coeffs=coeffs,
                        coeffs_label_free=coeffs_lf, window_speed=ws, variants=variants, params=params,
                        store_spikes=store_spikes)


# ---------------------------------------------------------------------------------------------------------- session
def _labels(session, ids):
    plan = session.plan
    row_of = {int(t): i for i, t in enumerate(plan["trial_id"])}
    rows = plan[[row_of[t] for t in ids]]
    names = plan.dtype.names

    def col(name, default):
        return rows[name] if name in names else np.full(len(ids), default)

    return {
        "trial_id": np.asarray(ids, dtype=np.uint32),
        "texture": np.asarray(col("texture", ""), dtype=str),
        "speed_mm_s": np.asarray(col("speed_mm_s", np.nan), dtype=np.float64),
        "force_g": np.asarray(col("force_g", np.nan), dtype=np.float64),
        "profile": np.asarray(col("profile", "constant"), dtype=str),
    }


def _trials_table(labels, n_samples, fs):
    dt = np.dtype([("trial_id", "u4"), ("texture", "S8"), ("group", "S24"), ("speed_mm_s", "f4"),
                   ("force_g", "f4"), ("profile", "S24"), ("duration_s", "f4"), ("n_samples", "u4")])
    out = np.zeros(len(labels["trial_id"]), dtype=dt)
    out["trial_id"] = labels["trial_id"]
    out["texture"] = np.char.encode(labels["texture"].astype(str), "utf-8")
    out["group"] = np.array([texture_group(t) for t in labels["texture"]], dtype="S24")
    out["speed_mm_s"] = labels["speed_mm_s"]
    out["force_g"] = labels["force_g"]
    out["profile"] = np.char.encode(labels["profile"].astype(str), "utf-8")
    out["n_samples"] = n_samples
    out["duration_s"] = n_samples / fs
    return out


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


def _fit_forces(fit_rg, labels_fit, offset, scale, p: EncodeParams, label_free: bool):
    scaler = ForceScaler(label_free=label_free, reference_force_g=p.reference_force_g, eps=p.epsilon,
                         c_max=p.c_max, k=p.k_sa, fs=p.fs_hz)
    try:
        scaler.fit(fit_rg, labels_fit["texture"], labels_fit["speed_mm_s"], labels_fit["force_g"], offset=offset,
                   scale=scale)
    except ValueError as exc:
        warnings.warn(f"force coefficients not fitted ({exc}); using C = 1", stacklevel=3)
        return None, str(exc)
    return scaler, ""


def _client(scheduler, workers):
    from dask.distributed import Client, LocalCluster

    if scheduler == "local":
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        return Client(cluster), cluster
    return Client(scheduler), None


def encode_session(session_path, out_path, *, variants=ALL_VARIANTS, batch_trials: int = 256,
                   scheduler: str | None = None, workers: int | None = None, progress: bool = True,
                   trial_ids=None, store_spikes=MAIN_VARIANTS, fit_memory_bytes: float = 4e9,
                   params: EncodeParams | None = None) -> Path:
    """Encode a session file (``rigctl.storage.session``) into an encoded file (layout: module docstring).

    Parameters
    ----------
    session_path : path of a session .h5 (complete trials are encoded, in plan order).
    out_path : the encoded .h5 to write (replaced; written under ``<name>.part`` and renamed when done).
    variants : subset of :data:`ALL_VARIANTS`.
    batch_trials : trials per batch (memory: about batch_trials x 6 s x 18 x 30 bytes).
    scheduler : None -> this process (numba, all cores); ``"local"`` -> a local Dask cluster of ``workers``
        processes; an address ``"tcp://host:8786"`` -> that Dask cluster (workers must see ``session_path``).
    workers : worker processes for ``scheduler="local"`` (default: cores).
    progress : tqdm progress bars on stderr.
    trial_ids : optional subset of trial ids.
    store_spikes : variants whose spike trains are written under /spikes.
    fit_memory_bytes : memory allowed for the raw readings kept for the force fit (see module docstring).

    Returns
    -------
    Path of the written file.

    Raises
    ------
    FileNotFoundError / SessionError from :func:`rigctl.storage.session.open_session`; ValueError for unknown
    variants or a session without complete trials.
    """
    from tqdm.auto import tqdm

    from rigctl.storage.session import open_session

    p = params or EncodeParams()
    variants = tuple(variants)
    bad = [v for v in variants if v not in ALL_VARIANTS]
    if bad:
        raise ValueError(f"unknown variants {bad}; choose from {ALL_VARIANTS}")
    store_spikes = tuple(v for v in store_spikes if v in variants)
    session_path, out_path = Path(session_path), Path(out_path)
    t_start = time.time()

    # ---- pass 1: labels, per-taxel range, raw readings for the force fit
    with open_session(session_path) as s:
        ids = s.completed_ids() if trial_ids is None else [int(t) for t in trial_ids]
        if not ids:
            raise ValueError(f"{session_path} has no complete trials")
        labels = _labels(s, ids)
        keys = np.array([f"{t}|{v:.3f}|{f:.3f}" for t, v, f in zip(labels["texture"], labels["speed_mm_s"],
                                                                     labels["force_g"])])
        plan_dur = {int(r["trial_id"]): float(r["duration_s"]) for r in s.plan} if "duration_s" in s.plan.dtype.names \
            else {}
        est = np.array([plan_dur.get(t, 6.0) * p.fs_hz * 18 * 2 for t in ids])
        keep = set(_fit_subsample(keys, est, fit_memory_bytes).tolist())
        rng_ = TaxelRange()
        fit_arrays, fit_idx, n_samples = [], [], np.zeros(len(ids), dtype=np.int64)
        for i, tid in enumerate(tqdm(ids, desc="range pass", unit="trial", disable=not progress)):
            x = np.asarray(s.trial(tid).taxels)
            n_samples[i] = x.shape[0]
            rng_.update(x)
            if i in keep:
                fit_arrays.append(x)
                fit_idx.append(i)
    if np.any(n_samples == 0):
        raise ValueError("a complete trial has no samples")
    offset, scale = rng_.offset_scale()

    # ---- force coefficients (once, for the whole dataset)
    fit_rg = as_ragged(fit_arrays)
    del fit_arrays
    fit_idx = np.asarray(fit_idx)
    labels_fit = {k: v[fit_idx] for k, v in labels.items()}
    need_force = any("force" in v for v in variants)
    scaler = scaler_lf = None
    fit_note = fit_note_lf = "not requested"
    if need_force:
        if progress:
            print(f"fitting force coefficients on {fit_rg.n_trials} trials ...", flush=True)
        scaler, fit_note = _fit_forces(fit_rg, labels_fit, offset, scale, p, label_free=False)
        scaler_lf, fit_note_lf = _fit_forces(fit_rg, labels_fit, offset, scale, p, label_free=True)
    del fit_rg
    coeffs = scaler.coefficients_for(labels["texture"], labels["speed_mm_s"], labels["force_g"]) if scaler else None
    coeffs_lf = (scaler_lf.coefficients_for(labels["texture"], labels["speed_mm_s"], labels["force_g"])
                 if scaler_lf else None)

    # ---- pass 2: encode in batches
    batches = [np.arange(i, min(i + batch_trials, len(ids))) for i in range(0, len(ids), batch_trials)]
    part = out_path.with_name(out_path.name + ".part")
    n_ch = int(offset.size)
    client = cluster = None
    try:
        with h5py.File(part, "w") as out:
            out.create_dataset("trials", data=_trials_table(labels, n_samples, p.fs_hz))
            norm = out.create_group("normalisation")
            norm.create_dataset("taxel_min", data=rng_.minimum)
            norm.create_dataset("taxel_max", data=rng_.maximum)
            norm.attrs["source"] = "whole dataset (per-taxel min/max over every encoded trial)"
            for name, sc, note in (("force_coefficients", scaler, fit_note),
                                   ("force_coefficients_label_free", scaler_lf, fit_note_lf)):
                if sc is not None:
                    ds = out.create_dataset(name, data=sc.table())
                    ds.attrs["n_not_converged"] = sc.n_not_converged_
                    ds.attrs["n_coefficients"] = sc.fit_.n_coefficients
                    ds.attrs["n_iter"] = sc.fit_.n_iter
                    ds.attrs["n_fit_trials"] = int(fit_idx.size)
                    out.attrs[f"{name}_n_not_converged"] = sc.n_not_converged_
                    out.attrs[f"{name}_n_coefficients"] = sc.fit_.n_coefficients
                else:
                    out.attrs[f"{name}_note"] = note
            feat_ds, spk = {}, {}
            fgrp = out.create_group("features")
            sgrp = out.create_group("spikes")
            for v in store_spikes:
                g = sgrp.create_group(v)
                n_tr = len(p.realtime_taxels) if v in REALTIME_VARIANTS else 2 * n_ch
                g.create_dataset("spike_times", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1 << 16,),
                                 compression="gzip", compression_opts=1)
                g.create_dataset("spike_times_index", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1 << 14,),
                                 compression="gzip", compression_opts=1)
                g.attrs["n_trains"] = n_tr
                g.attrs["unit"] = "s"
                g.attrs["trains"] = "SA taxels 0..n-1 then RA taxels 0..n-1" if v not in REALTIME_VARIANTS \
                    else "SA, real-time taxels"
                spk[v] = g
            pos = 0

            def write(batch, result):
                nonlocal pos
                feats, spikes = result
                for v, f in feats.items():
                    if v not in feat_ds:
                        feat_ds[v] = fgrp.create_dataset(v, shape=(len(ids), f.shape[1]), dtype="f4",
                                                         chunks=(min(256, len(ids)), f.shape[1]))
                    feat_ds[v][batch[0] : batch[-1] + 1] = f
                for v, st in spikes.items():
                    g = spk[v]
                    base = g["spike_times"].shape[0]
                    n_new = st.spike_times.size
                    g["spike_times"].resize((base + n_new,))
                    g["spike_times"][base:] = st.spike_times
                    m = g["spike_times_index"].shape[0]
                    g["spike_times_index"].resize((m + st.n_rows,))
                    g["spike_times_index"][m:] = st.spike_times_index + base
                pos += len(batch)

            args = [(str(session_path), [ids[i] for i in b], labels["speed_mm_s"][b],
                     None if coeffs is None else coeffs[b], None if coeffs_lf is None else coeffs_lf[b],
                     offset, scale, variants, store_spikes, p) for b in batches]
            bar = tqdm(total=len(ids), desc="encoding", unit="trial", disable=not progress)
            if scheduler is None:
                for b, a in zip(batches, args):
                    write(b, _batch_task(*a))
                    bar.update(len(b))
            else:
                from dask.distributed import as_completed

                client, cluster = _client(scheduler, workers)
                futures = [client.submit(_batch_task, *a, n_threads=1, pure=False) for a in args]
                index_of = {f.key: i for i, f in enumerate(futures)}
                done, next_i = {}, 0
                for fut in as_completed(futures):
                    done[index_of[fut.key]] = fut.result()
                    fut.release()
                    while next_i in done:  # spikes are appended in trial order
                        write(batches[next_i], done.pop(next_i))
                        bar.update(len(batches[next_i]))
                        next_i += 1
            bar.close()
            out.attrs["parameters"] = json.dumps(asdict(p))
            out.attrs["source_session"] = str(session_path)
            out.attrs["variants"] = json.dumps(list(variants))
            out.attrs["n_trials"] = len(ids)
            out.attrs["n_taxels"] = n_ch
            out.attrs["feature_layout"] = ("train-major: [SA_0 windows, ..., SA_n-1, RA_0, ..., RA_n-1]; SR spikes/s "
                                           "(speed-scaled: x speed/120), SC counts; 100 ms windows")
            out.attrs["encode_seconds"] = time.time() - t_start
            out.attrs["scheduler"] = str(scheduler)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    os.replace(part, out_path)
    return out_path


def read_encoded(path, variant: str = "speed_force_scaled") -> tuple[np.ndarray, np.ndarray]:
    """``(features (n_trials, n_features) float32, trials table)`` of an encoded file."""
    with h5py.File(path, "r") as f:
        return f["features"][variant][()], f["trials"][()]
