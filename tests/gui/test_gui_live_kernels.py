"""The live view's compiled per-frame kernels (rigctl_gui.live_kernels) give exactly what the live view's numpy
reference functions give: the peak-decimated traces (every bin alignment, short and long windows, the unused tail)
with each taxel's min / max, and the coloured spike raster (counts and pixels); the live view's numpy stand-in while
the kernels compile in the background fills the same points; the kernels compile off the calling thread."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl_gui import live_kernels
from rigctl_gui.live_kernels import decimate_traces, decimated_length, fill_raster, raster_spans


@pytest.mark.parametrize("n, width, first", [(2000, 1000, 0), (2000, 1000, 13), (2001, 997, 123456), (500, 1000, 7),
                                             (10000, 640, 3), (2000, 1, 5), (1, 800, 0)])
def test_decimate_traces_is_peak_decimate(n, width, first):
    from rigctl_gui.live_view import _decimate_into, peak_decimate  # (pyqtgraph: not for the collection)

    rng = np.random.default_rng(n + width + first)
    t = (first + np.arange(n)) / 1000.0
    x = rng.integers(0, 1024, (n, 18)).astype(np.uint16)
    now = t[-1]
    ref_t, ref_x = peak_decimate(t - now, x, width, first_index=first)
    need = decimated_length(n, width, first)
    assert need == len(ref_t)
    points = np.full((18, need + 5, 2), np.nan)
    lo, hi = np.empty(18), np.empty(18)
    m = decimate_traces(t, x, now, width, first, points, lo, hi)
    assert m == len(ref_t)
    for c in range(18):
        np.testing.assert_array_equal(points[c, :m, 0], ref_t)
        np.testing.assert_array_equal(points[c, :m, 1], ref_x[:, c])
        assert (points[c, m:] == points[c, m - 1]).all()  # the tail repeats the last point
    np.testing.assert_array_equal(lo, x.min(axis=0))
    np.testing.assert_array_equal(hi, x.max(axis=0))
    with pytest.raises(ValueError):
        decimate_traces(t, x, now, width, first, np.zeros((18, max(need - 1, 0), 2)), lo, hi)
    # the numpy stand-in the live view draws with until the kernels are compiled: the same points, tail, min, max
    points2, lo2, hi2 = np.full_like(points, np.nan), np.empty(18), np.empty(18)
    assert _decimate_into(t, x, now, width, first, points2, lo2, hi2) == m
    np.testing.assert_array_equal(points2, points)
    np.testing.assert_array_equal(lo2, lo)
    np.testing.assert_array_equal(hi2, hi)


def test_the_kernels_compile_in_a_background_thread():
    thread = live_kernels.warm_up()
    assert thread.name == "live-kernels-compile" and live_kernels.warm_up() is thread  # once per process
    thread.join(120)
    assert live_kernels.ready()


@pytest.mark.parametrize("width, height, n_spikes", [(1000, 130, 1500), (333, 57, 20000), (50, 18, 0), (7, 200, 300)])
def test_fill_raster_is_raster_rows_coloured(width, height, n_spikes):
    from rigctl_gui.live_view import TICK_HEIGHT, raster_row_map, raster_rows  # (pyqtgraph: not for the collection)

    rng = np.random.default_rng(width * height + n_spikes)
    n_channels, window_s = 18, 2.0
    t = rng.uniform(-2.5, 0.2, n_spikes)
    t[: n_spikes // 10] = 0.0  # the newest spike goes into the last column
    t[n_spikes // 10: n_spikes // 5] = np.round(t[n_spikes // 10: n_spikes // 5], 2)  # on bin edges
    ch = rng.integers(-1, n_channels + 1, n_spikes).astype(np.int16)  # and trains outside the raster
    rows, row_of_pixel = raster_rows(t, ch, n_channels, window_s, width, height)
    assert row_of_pixel is raster_row_map(n_channels, height, TICK_HEIGHT)  # one map per plot height
    palette = np.array([0xFFFFFFFF, 0xFF1F77B4, 0xFF0F3B5A], np.uint32)
    counts = np.full((n_channels + 1, width), 9, np.uint8)
    pixels = np.zeros((height, width), np.uint32)
    fill_raster(t, ch, n_channels, window_s, raster_spans(row_of_pixel, n_channels), palette, counts, pixels)
    np.testing.assert_array_equal(counts, rows)
    np.testing.assert_array_equal(pixels, palette[rows][row_of_pixel[::-1]])
