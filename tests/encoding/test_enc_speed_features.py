"""Speed invariance (eq. 2, incremental 100 ms batches), features (720 / 2160 / 180), NWB-style spike trains."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.encoding.features import realtime_features, realtime_features_unscaled, spike_features
from rigctl.encoding.izhikevich import encode_ra, encode_sa
from rigctl.encoding.speed import incremental_scale, scale_spike_times, speed_coefficient, window_speeds
from rigctl.encoding.spikes import SpikeTrains


def spatial_signal(position_mm: np.ndarray, n_ch: int = 18) -> np.ndarray:
    """A texture-like reading as a function of drum position (same for every speed)."""
    ch = np.arange(n_ch)[None, :]
    p = position_mm[:, None]
    return 0.45 + 0.3 * np.sin(2 * np.pi * (p + 3 * ch) / 40.0) * (0.6 + 0.4 * np.cos(2 * np.pi * p / 97.0))


def render(speed_mm_s: float, travel_mm: float = 240.0) -> np.ndarray:
    n = int(round(travel_mm / speed_mm_s * 1000))
    return spatial_signal(np.arange(n) * speed_mm_s / 1000.0)


def test_feature_shapes_720_and_2160():
    trials = [render(v) for v in (40, 60, 80, 100, 120)]
    sa, ra = encode_sa(trials), encode_ra(trials)
    speeds = np.array([40, 60, 80, 100, 120.0])
    unscaled = spike_features(sa, ra, n_windows=60)
    assert unscaled.shape == (5, 2160) and unscaled.dtype == np.float32
    coef = speed_coefficient(speeds)
    scaled = spike_features(scale_spike_times(sa, speeds), scale_spike_times(ra, speeds), n_windows=20,
                            sr_factor=coef)
    assert scaled.shape == (5, 720)
    # unscaled: the 2 s trial (120 mm/s) is zero-padded after window 20; the 6 s trial fills all 60
    w = unscaled.reshape(5, 36, 60)
    assert np.all(w[4, :, 20:] == 0) and w[4, :18, :20].sum() > 0
    assert w[0, :18, 55:].sum() > 0


def test_time_stretched_copies_give_the_same_speed_scaled_features():
    slow, fast = render(40), render(120)  # the same spatial signal: 6 s vs 2 s
    sa = encode_sa([slow, fast])
    speeds = np.array([40.0, 120.0])
    f = spike_features(scale_spike_times(sa, speeds), None, n_windows=20, sr_factor=speed_coefficient(speeds))
    # window 0 holds the neurons' onset transient (u adapting), which lasts longer in scaled time when fast
    a, b = f[0].reshape(18, 20)[:, 1:].ravel(), f[1].reshape(18, 20)[:, 1:].ravel()
    assert a.mean() > 20  # spikes/s: a real signal
    # tolerance: about 10 spikes per 100 ms window at 120 mm/s, so whole-spike rounding alone is ~10 %
    rel = np.linalg.norm(a - b) / np.linalg.norm(b)
    assert rel < 0.2, rel
    assert np.corrcoef(a, b)[0, 1] > 0.85
    # without speed scaling the two trials look different
    g = spike_features(sa, None, n_windows=20).reshape(2, 18, 20)[:, :, 1:].reshape(2, -1)
    assert np.linalg.norm(g[0] - g[1]) / np.linalg.norm(g[1]) > 2 * rel


def test_eq2_scales_times_by_speed_over_reference():
    st = SpikeTrains.from_lists([[[0.5, 3.0], [1.2]], [[0.6], []]])
    out = scale_spike_times(st, [40, 120])
    np.testing.assert_allclose(out.train(0, 0), [0.5 / 3, 1.0])
    np.testing.assert_allclose(out.train(1, 0), [0.6])
    with pytest.raises(ValueError):
        speed_coefficient([0.0])


def test_incremental_scale_constant_speed_equals_eq2_and_ramp_is_piecewise():
    st = SpikeTrains.from_lists([[[0.05, 0.15, 0.95]]])
    const, _ = incremental_scale(st, [np.full(10, 50.0)], reference_mm_s=100.0)
    np.testing.assert_allclose(const.spike_times, st.spike_times * 0.5)
    ramp, edges = incremental_scale(st, [np.array([100.0, 200.0] + [100.0] * 8)], reference_mm_s=100.0)
    # window 0 unscaled, window 1 doubled, then the offset of window 1 carries on
    np.testing.assert_allclose(ramp.spike_times, [0.05, 0.1 + 0.05 * 2, 0.1 + 0.2 + 0.7 + 0.05])
    np.testing.assert_allclose(edges[0][:3], [0, 0.1, 0.3])


def test_realtime_features_constant_speed_matches_offline_rates():
    x = render(50, travel_mm=200)  # 4 s
    sa = encode_sa(x).select_trains(np.arange(9))
    scaled, edges = incremental_scale(sa, [np.full(40, 50.0)], reference_mm_s=100.0)
    rt = realtime_features(scaled, edges)
    assert rt.shape == (1, 180)
    offline = spike_features(sa.scale_times(0.5), None, n_windows=20, sr_factor=0.5)
    np.testing.assert_allclose(rt, offline, rtol=1e-6)
    un = realtime_features_unscaled(sa, 4.0)
    assert un.shape == (1, 180)
    # the last 20 real windows (2-4 s) of the trial
    last = spike_features(sa.scale_times(1.0).with_times(sa.spike_times - 2.0), None, n_windows=20)
    np.testing.assert_allclose(un, last)


def test_window_speeds_from_a_drum_trace():
    t = np.linspace(0, 2.5, 60)
    v = 40 + 32 * t  # ramp 40 -> 120 mm/s
    w = window_speeds(t, v, 2.5)
    assert w.shape == (25,)
    np.testing.assert_allclose(w, 40 + 32 * (np.arange(25) * 0.1 + 0.05), rtol=1e-6)


def test_spike_trains_encoded_file_round_trip_and_layout(tmp_path):
    from rigctl.core.sensor import SensorLayout
    from rigctl.core.textures import texture_set_from_labels
    from rigctl.storage.encoded import EncodedWriter, open_encoded

    st = SpikeTrains.from_lists([[[0.1, 0.2], [], [0.3]], [[0.4], [0.5, 0.6, 0.7], []]])
    assert st.shape == (2, 3)
    np.testing.assert_array_equal(st.spike_times_index, [2, 2, 3, 4, 7, 7])  # NWB row ends
    with EncodedWriter(tmp_path / "s.h5", layout=SensorLayout.grid(1, 3), textures=texture_set_from_labels("A"),
                       trials={"trial_id": [0, 1], "texture": ["A", "A"]}) as w:
        w.add_spikes("original", 3)
        w.append_spikes("original", st.select_trials([0]))
        w.append_spikes("original", st.select_trials([1]))
        w.write_features("original", 0, np.zeros((2, 1)))
    with open_encoded(tmp_path / "s.h5") as f:
        assert SpikeTrains(*f.spikes("original")) == st
    both = SpikeTrains.hstack([st, st.select_trains([2])])
    assert both.shape == (2, 4)
    np.testing.assert_array_equal(both.train(1, 1), [0.5, 0.6, 0.7])
    np.testing.assert_array_equal(both.train(0, 3), [0.3])
    assert SpikeTrains.concatenate([st, st]).shape == (4, 3)
    np.testing.assert_array_equal(st.select_trials([1]).train(0, 1), [0.5, 0.6, 0.7])
    with pytest.raises(ValueError):
        SpikeTrains(np.zeros(3), np.array([1, 2]), 1)


def test_window_counts_bin_each_spike_by_its_window():
    """The compiled binning against a per-spike loop: times k * window_s (computed, with float error) land in window
    k, times before 0 or past the last window are ignored, empty rows give zeros."""
    rng = np.random.default_rng(11)
    window_s, n_windows = 0.1, 30
    lists = []
    for _ in range(40):
        row = []
        for _ in range(6):
            k = rng.integers(-3, 40, rng.integers(0, 25))
            t = np.concatenate([k * window_s, k * 0.001 * rng.choice([1.0, 0.5, 1 / 3]), [3 * 0.1]])
            row.append(np.sort(t) if rng.random() > 0.1 else np.zeros(0))
        lists.append(row)
    st = SpikeTrains.from_lists(lists)
    got = st.window_counts(window_s, n_windows)
    want = np.zeros((40, 6, n_windows))
    for i, row in enumerate(lists):
        for j, times in enumerate(row):
            for t in times:
                w = int(np.floor(round(t / window_s, 9)))
                if 0 <= w < n_windows:
                    want[i, j, w] += 1
    np.testing.assert_array_equal(got, want)
    assert got[:, :, 3].sum() >= sum(1 for row in lists for times in row if times.size)  # 0.3 s: window 3, not 2
    # a time scale counts the times scale_times makes (eq. 2, per trial), without making them
    coef = rng.choice([0.5, 1 / 3, 2 / 3, 1.25], 40)
    np.testing.assert_array_equal(st.window_counts(window_s, n_windows, coef),
                                  st.scale_times(coef).window_counts(window_s, n_windows))
    np.testing.assert_array_equal(st.window_counts(window_s, n_windows, 1.0), got)
