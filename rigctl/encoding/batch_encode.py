"""One batch of trials -> SA/RA spike trains and the features of every variant (the paper's encoding, Fig. 1B).

:func:`encode_batch` is what :func:`rigctl.encoding.pipeline.encode_session` runs on each batch of a session (and what
a caller runs to encode new trials the same way: :class:`rigctl.encoding.params.EncodeParams`);
:func:`trains_to_features` turns spike trains into the SR/SC features (eq. 2's speed scaling per variant).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rigctl.core.sensor import SensorLayout
from rigctl.encoding.features import (
    realtime_features,
    realtime_features_unscaled,
    spike_features,
)
from rigctl.encoding.fused import on_threads, run_fused
from rigctl.encoding.izhikevich import Ragged, _at_model_rate, as_ragged
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.sizing import windows_for
from rigctl.encoding.speed import incremental_scale, speed_coefficient
from rigctl.encoding.spikes import SpikeTrains
from rigctl.storage.encoded import ALL_VARIANTS, MAIN_VARIANTS, VARIANTS

__all__ = ["encode_batch", "trains_to_features"]


def _sa_ra(rg: Ragged, offset, scale, sa_gains: list[np.ndarray], p: EncodeParams):
    """SA trains for each gain matrix in ``sa_gains`` and the RA trains, (n_trials, n_ch) each: one pass of the
    fused kernel over the raw readings (:mod:`rigctl.encoding.fused`)."""
    izh = p.izhikevich
    res = run_fused(rg.data, rg.starts, offset=offset, scale=scale, sa_gains=sa_gains, k_sa=p.k_sa, ra=True,
                    k_ra=p.k_ra, cutoff_hz=p.cutoff_hz, rectify=p.rectify_ra, fs=p.fs_hz,
                    izhikevich=(izh["a"], izh["b"], izh["c"], izh["d"], izh["v_peak"]), dtype=np.dtype(p.kernel_dtype))
    return list(res.sa), res.ra


def _realtime_taxels(p: EncodeParams, n_ch: int, layout: SensorLayout | None = None) -> list[int]:
    if p.realtime_taxels is not None:
        return [int(t) for t in p.realtime_taxels if int(t) < n_ch] or list(range(n_ch))
    if layout is not None and layout.n_channels == n_ch:
        return list(layout.layer_channels(0))
    return list(range(min(9, n_ch)))  # the paper's top layer


def encode_batch(rg: Ragged, *, offset, scale, speed_mm_s, coeffs=None, coeffs_label_free=None,
                 window_speed=None, variants=ALL_VARIANTS, params: EncodeParams | None = None,
                 store_spikes=MAIN_VARIANTS, rate_hz: float | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Encode a batch of trials into every requested variant.

    To encode new trials like an encoded file (e.g. live classification), pass
    ``params=EncodeParams.from_dict(open_encoded(path).parameters)`` (same windows, so the same feature columns) and
    the trials' ``rate_hz``.

    Parameters
    ----------
    rg : Ragged readings (n_trials trials of (n_i, n_ch)), e.g. uint16 ADC counts, at ``rate_hz``; anything
        :func:`rigctl.encoding.izhikevich.as_ragged` takes.
    rate_hz : the readings' rate, Hz; None = already at the model's rate ``params.fs_hz`` (1 kHz). Other rates are
        resampled to it first (:mod:`rigctl.encoding.rate`).
    offset, scale : (n_ch,) normalisation ``(x - offset) * scale`` -> [0, 1].
    speed_mm_s : (n_trials,) trial speed (setpoint) for eq. (2), mm/s; may be NaN when no speed-scaled variant is
        asked for (and for ``realtime_speed_scaled`` when ``window_speed`` is given).
    coeffs, coeffs_label_free : (n_trials, n_ch) force coefficients (eq. 1) or None (-> 1).
    window_speed : list of (n_windows,) mm/s per trial (real-time variant) or None (-> constant speed_mm_s).
    variants : names from :data:`rigctl.storage.encoded.ALL_VARIANTS`.
    store_spikes : variants whose spike trains are returned.
    params : :class:`EncodeParams`; ``n_windows_unscaled`` None means the longest trial of this batch.

    Returns
    -------
    features : {variant: (n_trials, n_features) float32}
    spikes : {variant: SpikeTrains (n_trials, 2 n_ch)} (real-time variants: (n_trials, n_realtime_taxels))

    Raises
    ------
    ValueError for an unknown variant, or a speed that is not positive and finite for a speed-scaled variant.
    """
    p = params or EncodeParams()
    rg = as_ragged(rg)
    if rate_hz is not None:
        rg, _ = _at_model_rate(rg, rate_hz, p.fs_hz)
    sa_by, ra = _encode_trains(rg, offset, scale, coeffs, coeffs_label_free, variants, p)
    return trains_to_features(sa_by, ra, rg.lengths, np.asarray(speed_mm_s, np.float64), variants=variants, params=p,
                              window_speed=window_speed, store_spikes=store_spikes)


def _encode_trains(rg: Ragged, offset: Any, scale: Any, coeffs: Any, coeffs_label_free: Any, variants: Any,
                  p: EncodeParams) -> tuple[dict[str, SpikeTrains], SpikeTrains]:
    """The first half of :func:`encode_batch`: the SA trains the ``variants`` need, by :func:`_sa_key` ("none",
    "force", "lf"; (n_trials, n_ch) each), and the RA trains, from readings ``rg`` at the model's rate (arguments
    as :func:`encode_batch`'s). Raises ValueError for an unknown variant."""
    n, n_ch = rg.n_trials, rg.n_channels
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise ValueError(f"unknown variants {bad}; choose from {ALL_VARIANTS}")
    info = [VARIANTS[v] for v in variants]
    ones = np.ones((n, n_ch))
    need_force = any(i.force_scaled and not i.label_free for i in info)
    need_lf = any(i.label_free for i in info)
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
    return sa_by, ra


def _sa_key(info: Any) -> str:
    """Which SA trains a variant (its :class:`rigctl.storage.encoded.VariantInfo`) is made of: "lf" (the
    label-free force coefficients), "force" (the per-texture ones) or "none" (C = 1)."""
    return "lf" if info.label_free else "force" if info.force_scaled else "none"


def _unscaled_twin(variant: str) -> str | None:
    """The variant without speed scaling whose trains ``variant``'s are (the variant itself when it is not
    speed-scaled; eq. 2's factor apart otherwise); None for the real-time variants (scaled window by window)."""
    info = VARIANTS[variant]
    if info.realtime:
        return None
    return next((b for b, i in VARIANTS.items() if not i.speed_scaled and not i.realtime
                 and (i.force_scaled, i.label_free) == (info.force_scaled, info.label_free)), None)


def trains_to_features(sa_by: dict[str, Any], ra: SpikeTrains, lengths, speed_mm_s, *, variants, params: EncodeParams,
                       window_speed=None, store_spikes=()) -> tuple[dict[str, Any], dict[str, Any]]:
    """Speed scaling (eq. 2) and SR/SC features of already encoded trains, for each variant (the second half of
    :func:`encode_batch`; :class:`rigctl.encoding.estimators.FeatureExtractor` calls it on its own).

    Parameters
    ----------
    sa_by : {"none": SA trains with C = 1, "force": with the per-texture coefficients, "lf": with the label-free
        ones} (n_trials, n_ch) :class:`SpikeTrains`; only the keys the variants use are needed.
    ra : RA trains (n_trials, n_ch). lengths : (n_trials,) samples per trial at ``params.fs_hz``.
    speed_mm_s : (n_trials,) mm/s (eq. 2). window_speed, store_spikes : as :func:`encode_batch`.
    params : windows and constants; ``n_windows_unscaled`` / ``n_windows_scaled`` None = the longest trial here.

    Returns
    -------
    (features {variant: (n_trials, n_features) float32}, spikes {variant: SpikeTrains})
    """
    p = params
    info = [VARIANTS[v] for v in variants]
    lengths = np.asarray(lengths)
    speed = np.asarray(speed_mm_s, np.float64)
    n_ch = ra.n_trains
    n_unscaled = p.n_windows_unscaled
    if n_unscaled is None:
        n_unscaled = windows_for(lengths.max(initial=1) / p.fs_hz, p.window_s)
    n_scaled = p.n_windows_scaled
    coef = None
    if any(i.speed_scaled and not i.realtime for i in info):
        coef = speed_coefficient(speed, p.reference_speed_mm_s)
        if n_scaled is None:
            n_scaled = windows_for(float(np.max(lengths / p.fs_hz * coef, initial=0.0)), p.window_s)
    # the RA trains' window counts, unscaled and speed-scaled: counted once each, before the variants share them
    ra_counts: dict[bool, np.ndarray] = {}
    if any(not i.realtime and not i.speed_scaled for i in info):
        ra_counts[False] = ra.window_counts(p.window_s, n_unscaled)
    if any(not i.realtime and i.speed_scaled for i in info):
        ra_counts[True] = ra.window_counts(p.window_s, n_scaled, coef)  # type: ignore[arg-type]  # set above
    done: dict[str, tuple[np.ndarray, Any]] = {}

    def one(v: str, i: Any) -> tuple[np.ndarray, Any]:
        """Variant ``v``'s features and, if stored, its spike trains (None otherwise)."""
        if not i.realtime:
            sa = sa_by[_sa_key(i)]
            if i.speed_scaled:  # the scaled times counted as made, made only for a stored variant
                f = spike_features(sa, ra, n_windows=n_scaled,  # type: ignore[arg-type]  # set with coef
                                   window_s=p.window_s, sr_factor=coef, ra_counts=ra_counts[True], time_scale=coef)
                parts = [sa.scale_times(coef), ra.scale_times(coef)] if v in store_spikes else []
            else:
                f = spike_features(sa, ra, n_windows=n_unscaled, window_s=p.window_s, ra_counts=ra_counts[False])
                parts = [sa, ra]
            return f, SpikeTrains.hstack(parts) if v in store_spikes else None
        sa_rt = sa_by["none"].select_trains(_realtime_taxels(p, n_ch))
        if not i.speed_scaled:
            f = realtime_features_unscaled(sa_rt, lengths / p.fs_hz, n_windows=p.n_windows_realtime,
                                           window_s=p.window_s)
        else:
            ws = window_speed
            if ws is None:
                speed_coefficient(speed)  # the same check (positive, finite) as the other speed variants
                ws = [np.full(windows_for(L / p.fs_hz, p.window_s), s) for L, s in zip(lengths, speed)]
            scaled, edges = incremental_scale(sa_rt, ws, p.realtime_reference_speed_mm_s, p.window_s)
            f = realtime_features(scaled, edges, n_windows=p.n_windows_realtime, window_s=p.window_s)
        return f, sa_rt if v in store_spikes else None

    def run(a: int, b: int) -> None:
        for v, i in jobs[a:b]:
            done[v] = one(v, i)

    # the variants side by side on the encoder's threads (numba's count, the calling thread among them: the window
    # counts and gathers are nogil kernels, the rest numpy), the largest first; each variant's work is its own, so
    # the features are those of one after the other, bit for bit
    jobs = sorted(zip(variants, info), key=lambda vi: (vi[1].realtime, vi[1].speed_scaled))
    on_threads(run, len(jobs), 1)
    feats = {v: done[v][0] for v in variants}
    spikes = {v: done[v][1] for v in variants if done[v][1] is not None}
    return feats, spikes


def _encode_read(rg, ws, speed, coeffs, coeffs_lf, offset, scale, variants, store_spikes, params):
    """Encode and featurise a batch already read (the model input ``rg`` and window speeds ``ws``): what
    :func:`encode_batch` gives, except that a variant the file stores as ticks (:func:`_tick_source`) gets the
    (ticks, row ends) of its unscaled trains (:meth:`SpikeTrains.hstack_ticks`, made once for a base and its
    speed-scaled twin) instead of its SpikeTrains: the same numbers in the file, without the float64 copies."""
    sa_by, ra = _encode_trains(rg, offset, scale, coeffs, coeffs_lf, variants, params)
    sources = {v: _tick_source(v, store_spikes) for v in store_spikes}
    feats, spikes = trains_to_features(sa_by, ra, rg.lengths, np.asarray(speed, np.float64), variants=variants,
                                       params=params, window_speed=ws,
                                       store_spikes=[v for v, src in sources.items() if src is None])
    ticks: dict[str, Any] = {}
    for v, src in sources.items():
        if src is not None:
            if src not in ticks:
                ticks[src] = SpikeTrains.hstack_ticks([sa_by[_sa_key(VARIANTS[src])], ra], 1.0 / float(params.fs_hz))
            spikes[v] = ticks[src]
    return feats, spikes


def _tick_source(variant: str, stored) -> str | None:
    """The unscaled variant whose ticks a variant stored with ticks holds (:func:`rigctl.encoding.pipeline._add_spike_tables`): itself, or
    for a speed-scaled one its base when that is stored too; None for a variant stored otherwise (real-time: float64
    times; speed-scaled without its base: its own ticks from its scaled times)."""
    base = _unscaled_twin(variant)
    return base if base is not None and (base == variant or base in stored) else None
