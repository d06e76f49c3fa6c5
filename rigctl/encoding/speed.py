"""Speed invariance: spike times scaled by scanning speed (paper eq. 2; Results and Methods, speed invariance).

Constant speed (the drum dataset)::

    IST_ijk^T = (j / 120) ST_ijk^T                 (2)

every spike time of a trial at speed ``j`` (mm/s) is multiplied by ``j / v_ref`` (``v_ref`` = 120 mm/s), so a
40 mm/s trial of 6 s is contracted to 2 s: time becomes "distance travelled / v_ref".

Changing speed (the real-time experiment, Methods): the reference is 100 mm/s and the scaling is done incrementally
in 100 ms batches of "real time", each by the speed measured over that window: the gaps between spikes inside
window ``w`` are multiplied by ``v_w / v_ref`` and the windows are laid end to end. This is the piecewise-linear
time map ``t -> T_w + (t - w * 0.1 s) * v_w / v_ref`` with ``T_w = sum_{m<w} 0.1 s * v_m / v_ref``.
"""

from __future__ import annotations

import numpy as np

from rigctl.core.handheld import SPEED_FLOOR_MM_S
from rigctl.encoding.spikes import SpikeTrains

__all__ = [
    "REFERENCE_SPEED_MM_S",
    "REALTIME_REFERENCE_SPEED_MM_S",
    "WINDOW_S",
    "speed_coefficient",
    "scale_spike_times",
    "window_speeds",
    "incremental_scale",
    "scaled_edges",
    "floor_speeds",
]

REFERENCE_SPEED_MM_S = 120.0  #: eq. (2) reference, drum dataset
REALTIME_REFERENCE_SPEED_MM_S = 100.0  #: reference of the real-time experiment
WINDOW_S = 0.1  #: 100 ms batches / feature windows


def floor_speeds(speeds_mm_s) -> np.ndarray:
    """Window speeds as eq. 2 scales with them: floored at :data:`rigctl.core.handheld.SPEED_FLOOR_MM_S` (0 mm/s: a
    window in which the hand stood still or slipped back adds no scaled time, as on the on-board encoder), float64.

    Raises
    ------
    ValueError
        if there are none, or one is not finite.
    """
    v = np.asarray(speeds_mm_s, dtype=np.float64)
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise ValueError("speeds must be non-empty and finite (mm/s)")
    return np.maximum(v, SPEED_FLOOR_MM_S)


def speed_coefficient(speed_mm_s, reference_mm_s: float = REFERENCE_SPEED_MM_S) -> np.ndarray:
    """``j / v_ref`` of eq. (2), float64 (any shape).

    Raises
    ------
    ValueError
        if a speed is not positive and finite.
    """
    s = np.asarray(speed_mm_s, dtype=np.float64)
    if np.any(~np.isfinite(s)) or np.any(s <= 0):
        raise ValueError("speeds must be positive and finite (mm/s)")
    return s / float(reference_mm_s)


def scale_spike_times(trains: SpikeTrains, speed_mm_s, reference_mm_s: float = REFERENCE_SPEED_MM_S) -> SpikeTrains:
    """Eq. (2): every spike time of trial ``t`` times ``speed_mm_s[t] / reference_mm_s``.

    Parameters
    ----------
    trains : SpikeTrains (n_trials, n_trains), s.
    speed_mm_s : scalar or (n_trials,) mm/s (constant speed of each trial).

    Returns
    -------
    SpikeTrains, same rows, times in "scaled" s.
    """
    return trains.scale_times(speed_coefficient(speed_mm_s, reference_mm_s))


def window_speeds(speed_time_s, speed_mm_s, duration_s: float, window_s: float = WINDOW_S) -> np.ndarray:
    """Mean speed (mm/s) of each real-time window ``[w*window_s, (w+1)*window_s)`` covering ``duration_s``.

    The speed trace (``speed_time_s`` s, ``speed_mm_s`` mm/s, e.g. a session trial's measured drum speed) is
    linearly interpolated on a 1 ms grid and averaged per window (held constant beyond its ends).

    Returns
    -------
    (ceil(duration_s / window_s),) float64 mm/s.

    Raises
    ------
    ValueError
        if the trace is empty.
    """
    t = np.asarray(speed_time_s, dtype=np.float64)
    v = np.asarray(speed_mm_s, dtype=np.float64)
    if t.size == 0 or v.size != t.size:
        raise ValueError("need a non-empty speed trace with matching times")
    order = np.argsort(t, kind="stable")
    n_win = max(1, int(np.ceil(round(duration_s / window_s, 9))))
    per = max(1, int(round(window_s * 1000)))
    grid = (np.arange(n_win * per) + 0.5) * (window_s / per)
    return np.interp(grid, t[order], v[order]).reshape(n_win, per).mean(axis=1)


def scaled_edges(speeds_mm_s: np.ndarray, reference_mm_s: float = REALTIME_REFERENCE_SPEED_MM_S,
                 window_s: float = WINDOW_S) -> np.ndarray:
    """The scaled time (s) of each real-time window edge of a scan whose windows had ``speeds_mm_s`` ((n,) mm/s):
    (n + 1,) ``[0, cumsum(v / reference * window_s)]``, eq. 2 applied window by window (what
    :func:`incremental_scale` maps spikes with and returns)."""
    v = np.asarray(speeds_mm_s, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(v / reference_mm_s * window_s)])


def incremental_scale(trains: SpikeTrains, speeds: list[np.ndarray],
                      reference_mm_s: float = REALTIME_REFERENCE_SPEED_MM_S,
                      window_s: float = WINDOW_S) -> tuple[SpikeTrains, list[np.ndarray]]:
    """Real-time speed invariance: scale spike times in successive 100 ms batches by each window's speed.

    Parameters
    ----------
    trains : SpikeTrains (n_trials, n_trains), real time in s.
    speeds : per trial, (n_windows_t,) mm/s of each real-time window (see :func:`window_speeds`), floored at 0
        (:func:`floor_speeds`). Spikes after the last window are scaled with the last window's speed.
    reference_mm_s : 100 mm/s in the paper's real-time experiment.

    Returns
    -------
    scaled : SpikeTrains, "scaled time" s.
    scaled_edges : per trial, (n_windows_t + 1,) the scaled time of each real-time window edge (the inverse map,
        used for the real-time-duration normalisation of the spike rate in
        :func:`rigctl.encoding.features.realtime_features`).

    Raises
    ------
    ValueError
        if the number of speed traces differs from the number of trials, or a trial has none or a non-finite one.
    """
    if len(speeds) != trains.n_trials:
        raise ValueError(f"{len(speeds)} speed traces for {trains.n_trials} trials")
    times = trains.spike_times.copy()
    starts = trains.row_starts.reshape(trains.shape)
    ends = trains.spike_times_index.reshape(trains.shape)
    edges_out = []
    for t in range(trains.n_trials):
        try:
            v = floor_speeds(speeds[t])
        except ValueError as exc:
            raise ValueError(f"trial {t}: {exc}") from None
        factor = v / reference_mm_s
        edges = scaled_edges(v, reference_mm_s, window_s)
        edges_out.append(edges)
        s0, s1 = starts[t, 0], ends[t, -1]
        if s1 == s0:
            continue
        x = times[s0:s1]
        w = np.clip(np.floor(x / window_s).astype(np.int64), 0, v.size - 1)
        times[s0:s1] = edges[w] + (x - w * window_s) * factor[w]
    return trains.with_times(times), edges_out
