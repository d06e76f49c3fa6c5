"""Spiking features: SA spike rate (SR) and RA spike count (SC) in non-overlapping 100 ms windows (Methods,
feature extraction).

Drum dataset: 36 trains per trial (18 SA then 18 RA; ``2 x n_channels`` for other sensors). Speed-scaled trials are
2 s long (the reference speed's trial length) -> 20 windows -> 720 features; unscaled trials are 2-6 s -> 60
windows, zero-padded -> 2160 (the pipeline's default covers the longest trial of each file). The SA
spike rate of a speed-scaled trial is multiplied by the eq. (2) coefficient ``j / 120``: contracting a trial by
``j / 120`` raises its spike rate by ``120 / j``, and this brings it back ("the SR must be normalized by the speed
scaling coefficient as well to make the SR of the windows match between different trial speeds").

Feature order of a row: train-major, ``[SA_0 w_0..w_{n-1}, SA_1 ..., SA_17 ..., RA_0 ..., RA_17 ...]``.

Real-time experiment: 9 SA trains x 20 windows = 180 features. Speed-scaled: the SR of each scaled-time window is
its spike count divided by the *real-time* duration of that window (the paper's normalisation "by a coefficient
representing the real-time duration of that scaled-time window"); unscaled: the last 20 windows of the trial, or the
trial's windows zero-padded to 20.
"""

from __future__ import annotations

import numpy as np

from rigctl.encoding.speed import REALTIME_REFERENCE_SPEED_MM_S, WINDOW_S, floor_speeds, scaled_edges
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["N_WINDOWS_SCALED", "N_WINDOWS_UNSCALED", "N_WINDOWS_REALTIME", "spike_features", "realtime_features",
           "realtime_rates", "realtime_features_unscaled", "counted_realtime_features"]

N_WINDOWS_SCALED = 20  #: 2 s at the reference speed
#: the paper's dataset: 6 s, its longest trial (40 mm/s); the pipeline's default covers each file's longest trial
N_WINDOWS_UNSCALED = 60
N_WINDOWS_REALTIME = 20


def spike_features(sa: SpikeTrains, ra: SpikeTrains | None, *, n_windows: int, window_s: float = WINDOW_S,
                   sr_factor=None, ra_counts: np.ndarray | None = None, time_scale=None) -> np.ndarray:
    """SR of the SA trains and SC of the RA trains per window, flattened per trial.

    Parameters
    ----------
    sa : SpikeTrains (n_trials, n_sa) (s; scaled time for speed-scaled variants).
    ra : SpikeTrains (n_trials, n_ra) or None (the real-time system has SA only).
    n_windows : windows per train (20 speed-scaled, 60 unscaled); spikes past the last window are dropped, windows
        past the trial's end are 0 (zero padding).
    sr_factor : scalar or (n_trials,) multiplier of the SA spike rate (the speed coefficient ``j / 120`` for
        speed-scaled variants; 1 otherwise).
    ra_counts : ``ra.window_counts(window_s, n_windows)`` when already counted ((n_trials, n_ra, n_windows); the
        encoder's variants share one RA train, unscaled or speed-scaled), else None (counted here).
    time_scale : None, or scalar or (n_trials,): the trains' times are those of ``sa.scale_times(time_scale)``
        (and ``ra``'s, unless ``ra_counts`` is given): eq. 2's scaling, counted without the scaled copies.

    Returns
    -------
    (n_trials, (n_sa + n_ra) * n_windows) float32: spikes/s for SA columns, spike counts for RA columns.

    Raises
    ------
    ValueError
        if ``sa`` and ``ra`` have different trial counts.
    """
    sr = sa.window_counts(window_s, n_windows, time_scale) / window_s
    if sr_factor is not None:
        sr *= np.broadcast_to(np.asarray(sr_factor, np.float64), (sa.n_trials,))[:, None, None]
    parts = [sr.reshape(sa.n_trials, -1)]
    if ra is not None:
        if ra.n_trials != sa.n_trials:
            raise ValueError("sa and ra must have the same number of trials")
        counts = ra.window_counts(window_s, n_windows, time_scale) if ra_counts is None else ra_counts
        parts.append(counts.reshape(ra.n_trials, -1))
    return np.concatenate(parts, axis=1).astype(np.float32)


def realtime_features(sa_scaled: SpikeTrains, scaled_edges: list[np.ndarray], *,
                      n_windows: int = N_WINDOWS_REALTIME, window_s: float = WINDOW_S) -> np.ndarray:
    """Real-time speed-scaled SR features (Methods, real-time feature extraction).

    Parameters
    ----------
    sa_scaled : SpikeTrains (n_trials, n_trains) from :func:`rigctl.encoding.speed.incremental_scale`.
    scaled_edges : its second output (scaled time of each real-time window edge, per trial).

    Returns
    -------
    (n_trials, n_trains * n_windows) float32 spikes/s: count in scaled window ``[k w, (k+1) w)`` divided by the
    real-time duration of that window (0 where the window lies past the trial's end).
    """
    counts = sa_scaled.window_counts(window_s, n_windows)  # (T, n, W)
    return realtime_rates(counts, scaled_edges, window_s=window_s)


def counted_realtime_features(counts: np.ndarray, speeds_mm_s: np.ndarray, *,
                               reference_mm_s: float = REALTIME_REFERENCE_SPEED_MM_S,
                               window_s: float = WINDOW_S) -> np.ndarray:
    """One scan's speed-scaled SR features from the scaled-window counts an on-board encoder reports (the Uno
    encoder image's counts frame, docs/wire-protocol.md 1.5) and the speed each real-time window was scaled with
    (:func:`rigctl.devices.encoder_stream.applied_speeds`): what :func:`realtime_features` gives on the same spikes.

    Parameters
    ----------
    counts : (n_trains, n_windows) spikes per train and scaled window ``[k w, (k+1) w)``.
    speeds_mm_s : (n_real_windows,) mm/s (floored at 0: :func:`rigctl.encoding.speed.floor_speeds`).

    Returns
    -------
    (n_trains * n_windows,) float32 spikes/s.

    Raises
    ------
    ValueError
        ``counts`` not 2-D, or no speeds, or a non-finite one.
    """
    counts = np.asarray(counts)
    if counts.ndim != 2:
        raise ValueError(f"counts must be (n_trains, n_windows), got shape {counts.shape}")
    v = floor_speeds(speeds_mm_s)
    return realtime_rates(counts[None], [scaled_edges(v, reference_mm_s, window_s)], window_s=window_s)[0]


def realtime_rates(counts: np.ndarray, scaled_edges: list[np.ndarray], *, window_s: float = WINDOW_S) -> np.ndarray:
    """The speed-scaled SR features of scaled-window spike counts: :func:`realtime_features` after its counting,
    also the host's side of an encoder that reports counts (the on-board encoder, ``arduino/common/sa_encoder.h``).

    Parameters
    ----------
    counts : (n_trials, n_trains, n_windows) spikes in scaled windows ``[k w, (k+1) w)``.
    scaled_edges : per trial, the scaled time (s) of each real-time window edge (from the window speeds:
        :func:`rigctl.encoding.speed.incremental_scale`'s second output).
    window_s : w, s.

    Returns
    -------
    (n_trials, n_trains * n_windows) float32 spikes/s: each count divided by the real-time duration of its window
    (0 where the window lies past the trial's end).
    """
    counts = np.asarray(counts, np.float64)
    n_windows = counts.shape[2]
    bounds = np.arange(n_windows + 1) * window_s
    out = np.zeros_like(counts)
    for t, edges in enumerate(scaled_edges):
        real_edges = np.arange(edges.size) * window_s
        # inverse of the monotone map real -> scaled; windows past the end get zero duration
        real_b = np.interp(bounds, edges, real_edges)
        dur = np.diff(real_b)
        ok = (dur > 1e-9) & (bounds[:-1] < edges[-1])
        out[t][:, ok] = counts[t][:, ok] / dur[ok]
    return out.reshape(counts.shape[0], -1).astype(np.float32)


def realtime_features_unscaled(sa: SpikeTrains, duration_s, *, n_windows: int = N_WINDOWS_REALTIME,
                               window_s: float = WINDOW_S) -> np.ndarray:
    """Real-time unscaled SR features: the last ``n_windows`` 100 ms windows of each trial, or all its windows
    zero-padded at the end to ``n_windows``.

    Parameters
    ----------
    sa : SpikeTrains (n_trials, n_trains), real time s.
    duration_s : scalar or (n_trials,) trial lengths, s.

    Returns
    -------
    (n_trials, n_trains * n_windows) float32 spikes/s.
    """
    dur = np.broadcast_to(np.asarray(duration_s, np.float64), (sa.n_trials,))
    n_real = np.ceil(np.round(dur / window_s, 9)).astype(np.int64)
    max_w = int(max(n_real.max(initial=0), n_windows))
    rates = sa.window_counts(window_s, max_w) / window_s
    out = np.zeros((sa.n_trials, sa.n_trains, n_windows))
    for t in range(sa.n_trials):
        w = int(n_real[t])
        if w >= n_windows:
            out[t] = rates[t, :, w - n_windows : w]
        else:
            out[t, :, :w] = rates[t, :, :w]
    return out.reshape(sa.n_trials, -1).astype(np.float32)
