"""The live view's per-frame numbers in one compiled pass each (numba), so a frame's refresh costs a few kernel calls
instead of dozens of small numpy operations (issue 26: < 20 % of a core at 30 frames/s).

- :func:`decimate_traces`: :func:`rigctl_gui.live_view.peak_decimate` of every taxel's window written straight into
  the polyline points of the trace items, with each taxel's minimum and maximum in the window (the auto-ranged y
  axes);
- :func:`fill_raster`: a spike raster coloured at the data area's pixel size
  (:func:`rigctl_gui.live_view.raster_rows` then the palette: the same pixels), written into the image the raster item
  blits.

Both give exactly what the numpy functions of :mod:`rigctl_gui.live_view` give (tests/gui/test_gui_live_kernels.py);
those stay the reference. Compiled (or loaded from numba's cache on disk, as the encoder's kernels are) by
:func:`warm_up` in a background thread, never on the GUI thread: a first compile costs ~2.4 s of CPU and a load from
the cache ~1.2 s, which on the GUI thread froze the window for seconds on a loaded machine (the drum turning, long
enough for the dead man's switch to stop it). Until :func:`ready`, the live view draws with the numpy reference.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numba
import numpy as np

from rigctl.core.caches import configure_numba_cache
from rigctl_gui.once import StartOnce

configure_numba_cache()  # numba's kernel cache in the user's cache folder (before the kernels below are defined)


def decimated_length(n: int, width_px: int, first_index: int) -> int:
    """How many points :func:`rigctl_gui.live_view.peak_decimate` makes of ``n`` samples for a plot ``width_px``
    wide, the first sample's absolute number being ``first_index`` (at most ``width_px`` plus the two partial bins)."""
    if n <= width_px:
        return n
    step = -(-n // max(int(width_px) // 2, 1))
    if step < 2:
        return n
    skip = (-int(first_index)) % step
    m = (n - skip) // step
    return n - m * step + 2 * m


@numba.njit(cache=True, nogil=True)
def _copy_samples(t: Any, x: Any, now: float, start: int, stop: int, points: Any, lo: Any, hi: Any,
                  j: int) -> int:  # pragma: no cover - compiled
    """Samples ``start:stop`` as they are into ``points[:, j:]`` (their times from ``now``), widening ``lo``/``hi``;
    the next free point index."""
    for i in range(start, stop):
        ti = t[i] - now
        for c in range(x.shape[1]):
            v = x[i, c]
            points[c, j, 0] = ti
            points[c, j, 1] = v
            lo[c] = min(lo[c], v)
            hi[c] = max(hi[c], v)
        j += 1
    return j


@numba.njit(cache=True, nogil=True)
def _decimate_traces(t: Any, x: Any, now: float, width_px: int, first_index: int, points: Any, lo: Any,
                     hi: Any) -> int:  # pragma: no cover - compiled
    n, k = x.shape
    cap = points.shape[1]
    for c in range(k):
        lo[c] = np.inf
        hi[c] = -np.inf
    step = 1
    if n > width_px:
        step = -(-n // max(width_px // 2, 1))
    if step < 2:  # every sample as it is
        m_out = _copy_samples(t, x, now, 0, n, points, lo, hi, 0)
    else:
        skip = (-first_index) % step
        m = (n - skip) // step
        end = skip + m * step
        j = _copy_samples(t, x, now, 0, skip, points, lo, hi, 0)  # the oldest partial bin as it is
        for b in range(m):  # each full bin: its minimum at its first time, its maximum at its last
            a = skip + b * step
            t0 = t[a] - now
            t1 = t[a + step - 1] - now
            for c in range(k):
                bmin = x[a, c]
                bmax = bmin
                for i in range(a + 1, a + step):
                    v = x[i, c]
                    if v < bmin:
                        bmin = v
                    elif v > bmax:
                        bmax = v
                points[c, j, 0] = t0
                points[c, j, 1] = bmin
                points[c, j + 1, 0] = t1
                points[c, j + 1, 1] = bmax
                lo[c] = min(lo[c], bmin)
                hi[c] = max(hi[c], bmax)
            j += 2
        m_out = _copy_samples(t, x, now, end, n, points, lo, hi, j)  # the newest partial bin as it is
    for c in range(k):  # the unused tail repeats the last point: a fixed-length polyline draws nothing more
        for i in range(m_out, cap):
            points[c, i, 0] = points[c, m_out - 1, 0] if m_out else 0.0
            points[c, i, 1] = points[c, m_out - 1, 1] if m_out else 0.0
    return m_out


def decimate_traces(t: np.ndarray, x: np.ndarray, now: float, width_px: int, first_index: int, points: np.ndarray,
                    lo: np.ndarray, hi: np.ndarray) -> int:
    """Peak-decimate ``x`` (n, k) readings at times ``t`` (n,) s for a plot ``width_px`` wide into ``points`` (k, cap,
    2) float64: ``points[c, i] = (time before now (s) = t - now, reading)`` of taxel ``c``'s ``i``-th point, exactly
    :func:`rigctl_gui.live_view.peak_decimate`'s ``(t - now, x)`` (bins aligned to the absolute sample number
    ``first_index`` of ``t[0]``); points past the returned count repeat the last one. ``lo`` / ``hi`` (k,) float64
    get each taxel's minimum / maximum reading in the window. Returns the number of points; raises ValueError when
    ``points`` is too short (:func:`decimated_length`)."""
    need = decimated_length(len(t), width_px, first_index)
    if points.shape[0] != x.shape[1] or points.shape[1] < max(need, 1) or points.shape[2] != 2:
        raise ValueError(f"points must be ({x.shape[1]}, >= {max(need, 1)}, 2), got {points.shape}")
    return int(_decimate_traces(t, x, float(now), int(width_px), int(first_index), points, lo, hi))


@numba.njit(cache=True, nogil=True)
def _fill_raster(t: Any, ch: Any, n_channels: int, window_s: float, row_start: Any, row_stop: Any, palette: Any,
                 counts: Any, pixels: Any) -> None:  # pragma: no cover - compiled
    w = counts.shape[1]
    counts[:, :] = 0
    scale = w / window_s
    for i in range(len(t)):
        if t[i] == 0:
            col = w - 1
        else:
            col = int(math.floor((t[i] + window_s) * scale))
        c = ch[i]
        if 0 <= col < w and 0 <= c < n_channels and counts[c, col] < 2:
            counts[c, col] += 1
    pixels[:, :] = palette[0]
    for c in range(n_channels):
        for j in range(w):
            v = counts[c, j]
            if v:
                colour = palette[min(v, len(palette) - 1)]
                for r in range(row_start[c], row_stop[c]):
                    pixels[r, j] = colour


def raster_spans(row_of_pixel: np.ndarray, n_channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Each taxel's rows of the raster image in screen order (top row first): ``(start, stop)`` (n_channels,) int64,
    from :func:`rigctl_gui.live_view.raster_row_map`'s ``row_of_pixel`` (bottom row first). A taxel with no row
    gets an empty span. Raises ValueError if a taxel's rows are not contiguous."""
    screen = np.asarray(row_of_pixel)[::-1]
    start = np.zeros(n_channels, np.int64)
    stop = np.zeros(n_channels, np.int64)
    for c in range(n_channels):
        rows = np.flatnonzero(screen == c)
        if rows.size:
            if rows[-1] - rows[0] + 1 != rows.size:
                raise ValueError(f"taxel {c}'s raster rows are not contiguous")
            start[c], stop[c] = rows[0], rows[-1] + 1
    return start, stop


def fill_raster(t: np.ndarray, ch: np.ndarray, n_channels: int, window_s: float, spans: tuple[np.ndarray, np.ndarray],
                palette: np.ndarray, counts: np.ndarray, pixels: np.ndarray) -> None:
    """Bin spikes ``t`` (s before now) of trains ``ch`` into ``counts`` (n_channels + 1, width) uint8 (clipped to 2:
    :func:`rigctl_gui.live_view.raster_rows`' ``rows``) and colour ``pixels`` (height, width) uint32 (screen order)
    with ``palette`` (uint32: empty, one spike, more): each taxel's ``spans`` (:func:`raster_spans`) in its
    column's colour, everything else ``palette[0]``."""
    _fill_raster(np.ascontiguousarray(t, np.float64), np.ascontiguousarray(ch, np.int64), int(n_channels),
                 float(window_s), spans[0], spans[1], palette, counts, pixels)


_ready = threading.Event()


def _compile_both() -> None:
    points, lo, hi = np.zeros((1, 2, 2)), np.zeros(1), np.zeros(1)
    decimate_traces(np.zeros(1), np.zeros((1, 1), np.uint16), 0.0, 1, 0, points, lo, hi)
    spans = raster_spans(np.zeros(1, np.int64), 1)
    fill_raster(np.zeros(0), np.zeros(0, np.int64), 1, 1.0, spans, np.zeros(3, np.uint32), np.zeros((2, 1), np.uint8),
                np.zeros((1, 1), np.uint32))
    _ready.set()


_warming = StartOnce(_compile_both, "live-kernels-compile")


def warm_up() -> threading.Thread:
    """Compile both kernels (or load them from numba's cache) in a background thread, once per process; returns the
    thread. :func:`ready` is True once they can be called without compiling."""
    return _warming.start()


def ready() -> bool:
    """True once :func:`warm_up` has compiled both kernels: a call then costs microseconds, not seconds."""
    return _ready.is_set()


__all__ = ["decimate_traces", "decimated_length", "fill_raster", "raster_spans", "ready", "warm_up"]
