"""Live view: the taxel traces of the last N seconds, one plot per layer of the sensor, with the live SA and RA spike
rasters (one train per taxel each) from the streaming encoder on the SAME time axis below them, and a heat map of the
current readings per layer beside them.

Everything follows the stream's :class:`rigctl.core.sensor.SensorLayout` (``TaxelStream.layout``; default the paper's
3x3x2 at 1 kHz, 10-bit): the number of trace plots and heat maps (one per layer, each heat map the layer's rows x
cols grid with its taxel numbers), the raster rows (``layout.n_channels`` trains per population), the time axes
(``sample_rate_hz``) and the count ranges (``adc_max``).

One time axis: the trace plots and both rasters are stacked in one column of one layout, with left axes of one fixed
width, so their data areas have the same pixel geometry; one window (``Time window``, 0.5-10 s) sets all their x
ranges to ``(-window, 0)`` s before now (they are linked by this one setter: the mouse never pans them). A spike
sits exactly above or below the trace sample it came from.

Drawing costs do not grow with the data (issue 12): each trace is decimated to the data area's pixel width (min and
max per pixel column, so peaks survive, :func:`peak_decimate`); each raster population is ONE image at the data
area's pixel size (:func:`raster_image`: spikes binned per pixel column and taxel row), so every spike in the
window is drawn whatever the rate (no spike budget) at the cost of one small image; each layer's traces are ONE item
(:class:`rigctl_gui.live_items.TracesItem`: a polyline per taxel, no per-curve bounds or signals), only the window is copied out of the
trace buffer, and the axes and titles are cached pixmaps (the data areas under them scroll every frame).

Everything is drawn from fixed-size buffers filled from the taxel stream's ring buffer (never the file):
:class:`rigctl_gui.workers.TraceBuffer` (pulled in the GUI thread, so a frame reaches the screen without waiting for a
worker) and the spike rings of :class:`rigctl_gui.workers.LiveEncoder` (a worker thread), by :meth:`LiveView.refresh`,
called from the main window's QTimer at >= 30 Hz.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl_gui import live_kernels
from rigctl_gui.live_items import TimedGraphicsLayout, TracesItem, cache_axes_and_title, mark_containers
from rigctl_gui.live_kernels import fill_raster
from rigctl_gui.staged import StagedBuild, StagedWidget
from rigctl_gui.widgets import StatusText, add_taxel_numbers
from rigctl_gui.workers import LIVE_WINDOW_MAX_S, TraceBuffer

#: the time window's range (s): traces and rasters show the last WINDOW_RANGE_S seconds
WINDOW_RANGE_S = (0.5, LIVE_WINDOW_MAX_S)
#: width of every time plot's left axis (px): the same for all, so their data areas line up
AXIS_WIDTH_PX = 62
#: raster colours per population (matplotlib's C0 / C3)
RASTER_COLOURS = {"sa": "#1f77b4", "ra": "#d62728"}
#: fraction of a raster row a spike tick covers (the rest is the gap to the next taxel)
TICK_HEIGHT = 0.8
#: auto-ranged y axes never span fewer ADC counts than this fraction of full scale (noise is not blown up)
MIN_AUTO_SPAN = 0.02
#: the info line is updated every this many refreshes (a label's text change costs a relayout)
INFO_EVERY = 10
#: taxel numbers are written in the heat-map cells only when a cell is at least this wide on screen (px); smaller
#: cells keep their colour visible (the map's tooltip still maps positions to taxels)
MIN_LABELLED_CELL_PX = 22
#: outages marked at once in each time plot (a dashed line each)
GAP_MARKS = 4
#: the heat maps are updated every this many refreshes (~8 Hz at the app's default 30 frames/s: a "now" map needs no more, and
#: each update repaints the maps and their taxel numbers)
HEATMAP_EVERY = 4
#: the smallest data areas (px): traces, rasters; a view shorter than their sum (a short window, a 1.5x scale)
#: scrolls instead of squeezing them (issue 38: 15-px traces at 1.5x on 1280x800)
MIN_TRACE_PX, MIN_RASTER_PX = 56, 36
#: title font sizes tried, largest first, until a title fits its plot's width (it never widens the column)
TITLE_SIZES_PT = (10, 9, 8)


def layer_titles(layout: SensorLayout, i: int) -> tuple[str, str]:
    """``(trace title, heat-map title)`` of layer ``i``, e.g. ``("Top layer (type I) taxels 0-8",
    "Top 3x3 (type I) now")`` for the paper's sensor, ``("Taxels 0-8 (type I)", "3x3 taxels (type I) now")`` for a
    single unnamed layer."""
    la = layout.layers[i]
    ch = layout.layer_channels(i)
    span = f"{ch.start}-{ch.stop - 1}" if len(ch) > 1 else f"{ch.start}"
    rec = f" ({la.receptor})" if la.receptor else ""
    grid = f"{la.rows}x{la.cols}"
    if la.name in ("", "taxels"):
        return f"Taxels {span}{rec}", f"{grid} taxels{rec} now"
    name = la.name[:1].upper() + la.name[1:]
    return f"{name} layer{rec} taxels {span}", f"{name} {grid}{rec} now"


def trace_colours(n: int) -> list[QtGui.QColor]:
    """The pen colour of each of a layer's ``n`` traces (the legend uses the same)."""
    return [pg.intColor(k, max(n, 2), maxValue=210) for k in range(n)]


def legend_html(layout: SensorLayout, i: int, max_entries: int = 24) -> str:
    """The colour legend of layer ``i``'s traces: each taxel number in its trace's colour (the heat map shows where
    each number sits); a layer of more than ``max_entries`` taxels gets the first and last only."""
    ch = layout.layer_channels(i)
    cols = trace_colours(len(ch))
    entries = [f"<span style='color:{c.name()}'>&#9632;{k}</span>" for k, c in zip(ch, cols)]
    if len(entries) > max_entries:
        entries = entries[:2] + ["..."] + entries[-2:]
    return "&nbsp;".join(entries)


def heatmap_aspect(rows: int, cols: int, *, max_elongation: float = 4.0) -> float:
    """The heat map's locked aspect ratio (pyqtgraph's ``xScale / yScale``): square taxels (1.0) unless the grid is
    longer than ``max_elongation`` : 1, whose taxels are stretched so the map is at most that elongated (a 1 x 16 row
    shows as a 4 : 1 strip instead of a 16 : 1 line)."""
    if cols > max_elongation * rows:
        return max_elongation * rows / cols
    if rows > max_elongation * cols:
        return rows / (max_elongation * cols)
    return 1.0


def raster_ticks(layout: SensorLayout, max_ticks: int = 6) -> list[tuple[int, str]]:
    """Left-axis ticks of a raster: at most ``max_ticks`` (every 3rd taxel for the paper's 18 at the default 6, so
    a short plot gets fewer and its labels never overlap); the channel names when the layout has its own and each
    gets a tick (<= 20 channels, <= ``max_ticks``)."""
    n, max_ticks = layout.n_channels, max(int(max_ticks), 1)
    if layout.channel_names is not None and n <= min(20, max_ticks):
        return list(enumerate(layout.channel_names))
    step = max(1, -(-n // max_ticks))
    return [(i, str(i)) for i in range(0, n, step)]


def peak_decimate(t: np.ndarray, x: np.ndarray, width_px: int, first_index: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Traces decimated to a plot's pixel width, peaks kept.

    ``t`` (n,) s and ``x`` (n, k) readings; ``first_index`` is the absolute sample number of ``t[0]`` (bins are
    aligned to it, so a scrolling trace does not shimmer). With at most ``width_px`` samples nothing changes;
    otherwise samples are binned ``step = ceil(n / (width_px / 2))`` at a time (a bin per two pixel columns) and
    each bin becomes two points (its minimum at the bin's first time and its maximum at its last time, so the newest
    sample's time is always the last point's): at most ``width_px`` points, plus the oldest and the newest partial
    bins as they are. Returns ``(t, x)`` (x of ``x``'s dtype).
    """
    n = len(t)
    if n <= width_px:
        return t, x
    step = -(-n // max(int(width_px) // 2, 1))
    if step < 2:
        return t, x
    skip = (-int(first_index)) % step
    m = (n - skip) // step
    end = skip + m * step
    blocks = x[skip:end].reshape(m, step, x.shape[1])
    out_x = np.empty((2 * m + skip + n - end, x.shape[1]), x.dtype)
    out_t = np.empty(len(out_x))
    out_x[:skip], out_t[:skip] = x[:skip], t[:skip]
    mid = slice(skip, skip + 2 * m)
    out_x[mid][0::2] = blocks.min(axis=1)
    out_x[mid][1::2] = blocks.max(axis=1)
    out_t[mid][0::2] = t[skip:end:step]
    out_t[mid][1::2] = t[skip + step - 1:end:step]
    out_x[skip + 2 * m:], out_t[skip + 2 * m:] = x[end:], t[end:]
    return out_t, out_x


def _decimate_into(t: np.ndarray, x: np.ndarray, now: float, width_px: int, first_index: int, points: np.ndarray,
                   lo: np.ndarray, hi: np.ndarray) -> int:
    """:func:`rigctl_gui.live_kernels.decimate_traces` done with :func:`peak_decimate` (while the kernel compiles):
    the same points, minima and maxima written into ``points``, ``lo`` and ``hi``; returns the number of points."""
    dt, dx = peak_decimate(t, x, width_px, first_index)
    n = len(dt)
    lo[:], hi[:] = (x.min(axis=0), x.max(axis=0)) if len(x) else (np.inf, -np.inf)
    if n:
        points[:, :n, 0] = dt - now
        points[:, :n, 1] = dx.T
        points[:, n:] = points[:, n - 1:n]
    return n


def raster_rows(t: np.ndarray, ch: np.ndarray, n_channels: int, window_s: float, width_px: int,
                height_px: int, *, tick: float = TICK_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """A spike raster at the data area's pixel size as ``(rows, row_of_pixel)``: the ``(height_px, width_px)`` uint8
    image is ``rows[row_of_pixel]`` (:func:`raster_image`), kept apart so colouring costs one row per taxel.

    ``t`` (s, times before now: ``-window_s <= t <= 0``) and ``ch`` (train number 0 .. n_channels - 1) are the
    spikes; column ``j`` is the time bin ``[-window_s + j w, -window_s + (j + 1) w)`` with ``w = window_s /
    width_px`` (the newest spike, t = 0, goes into the last column). ``rows`` is ``(n_channels + 1, width_px)``: the
    spikes per bin of each taxel (clipped to 2: one spike, more than one), then a blank row (the gap between
    taxels); ``row_of_pixel`` (height_px,) maps image row ``r`` (row 0 = bottom = y -0.5) to taxel ``round(y_r)``
    where ``y_r`` is the row's centre, or to the blank row when ``|y_r - taxel| > tick / 2`` (:func:`raster_row_map`,
    read-only). Spikes outside the window are ignored.
    """
    w = max(int(width_px), 1)
    t = np.asarray(t, float)
    ch = np.asarray(ch, np.int64)
    col = np.floor((t + window_s) * (w / window_s)).astype(np.int64)
    col[t == 0] = w - 1
    ok = (col >= 0) & (col < w) & (ch >= 0) & (ch < n_channels)
    counts = np.bincount(ch[ok] * w + col[ok], minlength=(n_channels + 1) * w).reshape(n_channels + 1, w)
    rows = np.minimum(counts, 2).astype(np.uint8)  # the last row (no channel n_channels): the blank gap
    return rows, raster_row_map(n_channels, max(int(height_px), 1), float(tick))


@functools.lru_cache(maxsize=16)
def raster_row_map(n_channels: int, height_px: int, tick: float = TICK_HEIGHT) -> np.ndarray:
    """The ``(height_px,)`` row map of a raster of ``n_channels`` trains (:func:`raster_rows`; row 0 at the bottom;
    ``n_channels`` = the blank gap between taxels). The same for every frame of a plot of that height: computed once
    (a read-only array)."""
    y = -0.5 + (np.arange(height_px) + 0.5) * (n_channels / height_px)  # centre of each pixel row, in taxel units
    row_ch = np.clip(np.rint(y), 0, n_channels - 1).astype(np.int64)
    row_ch[np.abs(y - row_ch) > tick / 2] = n_channels
    row_ch.flags.writeable = False
    return row_ch


def raster_image(t: np.ndarray, ch: np.ndarray, n_channels: int, window_s: float, width_px: int,
                 height_px: int, *, tick: float = TICK_HEIGHT) -> np.ndarray:
    """A spike raster as a ``(height_px, width_px)`` uint8 image at the data area's pixel size (pixel value: spikes
    in that time bin and taxel row, clipped to 2; 0 between taxels): :func:`raster_rows` expanded."""
    rows, row_ch = raster_rows(t, ch, n_channels, window_s, width_px, height_px, tick=tick)
    return rows[row_ch]


def auto_y_range(lo: float, hi: float, current: tuple[float, float] | None, adc_max: float,
                 *, min_span: float = MIN_AUTO_SPAN) -> tuple[float, float] | None:
    """The auto-ranged y range of a trace plot whose visible data span ``lo``-``hi`` ADC counts, or None to keep
    ``current``: a new range (10 % margin, at least ``min_span * adc_max`` wide, inside 0-``adc_max``, rounded
    outward to 1/100 of full scale) only when the data leave the current range or fill less than a third of it, so
    the axis does not twitch with every frame."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return None
    if current is not None:
        c0, c1 = current
        if lo >= c0 and hi <= c1 and (hi - lo) >= (c1 - c0) / 3:
            return None
    span = max(hi - lo, min_span * adc_max)
    mid = (lo + hi) / 2
    a, b = mid - 0.6 * span, mid + 0.6 * span
    q = max(adc_max / 100.0, 1.0)
    a, b = max(0.0, np.floor(a / q) * q), min(float(adc_max), np.ceil(b / q) * q)
    return (a, b) if b > a else (0.0, float(adc_max))


class RasterItem(pg.GraphicsObject):
    """A spike raster image (:func:`raster_image`) drawn into a rectangle of its plot: an opaque 32-bit image from a
    small palette (Qt blits that several times faster than pyqtgraph's ImageItem's 24-bit or alpha images), row 0
    at the rectangle's top in data coordinates (y = -0.5: the bottom taxel). The pixels live in one array (and one
    QImage on it) reused while the size holds: a new half-megabyte image each frame cost its page faults.
    ``image``: the last counts shown, as the ``(height, width)`` array."""

    def __init__(self, palette: list[QtGui.QColor]):
        super().__init__()
        self._palette = np.array([c.rgb() for c in palette], np.uint32)  # 0xffRRGGBB
        self._rect = QtCore.QRectF(0, 0, 1, 1)
        self._qimage: QtGui.QImage | None = None
        self._pixels: np.ndarray | None = None
        self._rows: np.ndarray | None = None
        self._row_of_pixel: np.ndarray | None = None
        self._spans: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros(0, np.int64))

    @property
    def image(self) -> np.ndarray | None:
        """The counts shown (``(height, width)`` uint8, row 0 = the bottom row), or None before :meth:`setImage`."""
        if self._rows is None or self._row_of_pixel is None:
            return None
        return self._rows.take(self._row_of_pixel, axis=0)

    def setRect(self, rect: QtCore.QRectF) -> None:  # noqa: N802 - Qt style
        if rect != self._rect:
            self.prepareGeometryChange()
            self._rect = QtCore.QRectF(rect)
            self.update()

    def setImage(self, counts: np.ndarray, row_of_pixel: np.ndarray | None = None) -> None:  # noqa: N802 - Qt style
        """Show ``(height, width)`` uint8 spike counts (0, 1, 2+ -> the palette's colours), or, with
        ``row_of_pixel``, the image ``counts[row_of_pixel]`` (:func:`raster_rows`: coloured per row, then expanded)."""
        if row_of_pixel is None:
            row_of_pixel = np.arange(len(counts))
        colours = self._palette.take(counts, mode="clip")  # counts past the palette get its last colour
        h, w = len(row_of_pixel), counts.shape[1]
        if self._pixels is None or self._pixels.shape != (h, w):
            self._pixels = np.empty((h, w), np.uint32)  # top row first (screen order): blitted as it is
            self._qimage = QtGui.QImage(self._pixels.data, w, h, 4 * w, QtGui.QImage.Format.Format_RGB32)
        np.take(colours, row_of_pixel[::-1], axis=0, out=self._pixels)
        self._rows, self._row_of_pixel = counts, row_of_pixel
        self.update()

    def draw_spikes(self, t: np.ndarray, ch: np.ndarray, n_channels: int, window_s: float, width_px: int,
                    height_px: int) -> None:
        """Show the spikes ``t`` (s before now) of trains ``ch`` binned at ``width_px`` x ``height_px``: the image of
        :func:`raster_rows` and :meth:`setImage`, binned and coloured in one compiled pass
        (:func:`rigctl_gui.live_kernels.fill_raster`) into the reused counts and pixels."""
        w, h = max(int(width_px), 1), max(int(height_px), 1)
        row_of_pixel = raster_row_map(n_channels, h, TICK_HEIGHT)
        if self._pixels is None or self._pixels.shape != (h, w) or self._rows is None \
                or self._rows.shape != (n_channels + 1, w) or self._row_of_pixel is not row_of_pixel:
            self._pixels = np.empty((h, w), np.uint32)
            self._qimage = QtGui.QImage(self._pixels.data, w, h, 4 * w, QtGui.QImage.Format.Format_RGB32)
            self._rows = np.zeros((n_channels + 1, w), np.uint8)
            self._spans = live_kernels.raster_spans(row_of_pixel, n_channels)
        if not live_kernels.ready():  # the kernel still compiling in the background: the numpy reference
            self.setImage(raster_rows(t, ch, n_channels, window_s, w, h)[0], row_of_pixel)
            return
        fill_raster(t, ch, n_channels, window_s, self._spans, self._palette, self._rows, self._pixels)
        self._row_of_pixel = row_of_pixel
        self.update()

    def boundingRect(self) -> QtCore.QRectF:  # noqa: N802 - Qt override
        return QtCore.QRectF(self._rect)

    def paint(self, p, *args) -> None:
        img = self._qimage
        if img is None:
            return
        tr = p.transform()
        dev = tr.mapRect(self._rect)
        if (tr.type().value <= QtGui.QTransform.TransformationType.TxScale.value and abs(dev.width() - img.width()) < 1
                and abs(dev.height() - img.height()) < 1):
            # the image is at the data area's pixel size: blit it unscaled (a scaled draw costs several times more)
            p.save()
            p.resetTransform()
            p.drawImage(QtCore.QPointF(round(dev.left()), round(dev.top())), img)
            p.restore()
            return
        # any other size (an export, a resize before the next refresh): scaled, flipped to data y (row 0 = y -0.5)
        p.save()
        r = self._rect
        p.translate(0, r.top() + r.bottom())
        p.scale(1, -1)
        p.drawImage(r, img)
        p.restore()


def _title_min(label: pg.LabelItem) -> None:
    """A plot title's minimum size: its text's height, no width (a title never widens its column: the Live view
    fits its text to the width, :meth:`LiveView.fit_plots`)."""
    h = label.itemRect().height()
    label.setMinimumWidth(0)
    label.setMinimumHeight(h)
    label._sizeHint = {QtCore.Qt.SizeHint.MinimumSize: (0, h), QtCore.Qt.SizeHint.PreferredSize: (0, h),
                       QtCore.Qt.SizeHint.MaximumSize: (-1, -1), QtCore.Qt.SizeHint.MinimumDescent: (0, 0)}
    label.updateGeometry()


class LiveView(StagedWidget, QtWidgets.QWidget):
    """The live tab. Call :meth:`attach` with the taxel stream and a running :class:`rigctl_gui.workers.LiveEncoder`; the
    plots are rebuilt for the stream's layout (``layout`` is the one shown before anything is attached).

    ``window_s``: the time window of the traces and the rasters (s); ``auto_range``: y axes of the traces follow the
    data (else 0-``adc_max``)."""

    #: a staged build (``staged=True``) has finished: every plot exists (GUI thread)
    built = QtCore.Signal()

    def __init__(self, parent=None, *, window_s: float = 2.0, auto_range: bool = True,
                 layout: SensorLayout = PAPER_SENSOR, staged: bool = False):
        super().__init__(parent)
        self._staged: StagedBuild | None = None  # the staged build (``staged=True``)
        self._complete = False  # every plot of the layout exists (fit_plots has something to fit)
        self.encoder = None
        self.buffer: TraceBuffer | None = None
        self.sensor_layout: SensorLayout | None = None
        self.window_s = float(window_s)
        #: the spikes drawn by the last refresh per population: ``(t (s before now), taxel)`` (tests, tooltips)
        self.drawn: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        #: host receive time (time.monotonic) of the newest frame drawn in the last refresh, awaiting its paint
        self._pending_host_t: float | None = None
        self.latencies_s = np.full(4096, np.nan)  # frame-to-screen latency of recent paints (ring)
        self._lat_n = 0
        self.paint_times = np.full(512, np.nan)
        self._paint_n = 0
        self._refresh_n = 0
        #: the readings (one frame, ADC counts) the heat maps show
        self.heatmap_frame: np.ndarray | None = None
        # each taxel's decimated trace points (taxels, capacity, 2) and its min / max in the window, reused
        self._trace_points: np.ndarray | None = None
        self._trace_lo = self._trace_hi = np.zeros(0)

        self.window_box = QtWidgets.QDoubleSpinBox(suffix=" s", decimals=1, minimum=WINDOW_RANGE_S[0],
                                                   maximum=WINDOW_RANGE_S[1], singleStep=0.5, value=self.window_s)
        self.window_box.setToolTip("The last this many seconds, for the traces and the spike rasters alike")
        self.window_box.valueChanged.connect(self.set_window)
        self.auto_box = QtWidgets.QCheckBox("Auto-range y")
        self.auto_box.setToolTip("Trace y axes follow the readings in the window (else the full ADC range)")
        self.auto_box.setChecked(auto_range)
        self.auto_box.toggled.connect(self.set_auto_range)
        # the info line and the rates change several times a second: StatusText repaints them without relayouting
        # the window (issue 26); the info line takes the room left and never widens the window (an encoder error can
        # be long: elided, whole in its tooltip)
        self.info = StatusText("", template="888888 frames shown, SA 88888 / RA 88888 spikes",
                               align=QtCore.Qt.AlignmentFlag.AlignRight)
        self.info.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Fixed)
        self.sensor_label = QtWidgets.QLabel("")
        #: the frame-rate readout: the display's paints per second and the taxel frames arriving per second
        self.rate_label = StatusText("", template="  display 888/s, taxels 88888 frames/s")
        self.rate_label.setSizePolicy(QtWidgets.QSizePolicy.Policy.Fixed, QtWidgets.QSizePolicy.Policy.Fixed)
        self.rate_label.setObjectName("live_rates")
        self.rate_label.setToolTip("display: paints of these plots per second; taxels: frames arriving per second")
        # one row of controls and readouts where the tab is wide enough, else the rates and the sensor on a second
        # row (:meth:`_arrange_bar`): the bar never sets the window's smallest width
        self._bar = bar = QtWidgets.QHBoxLayout()
        self._bar_first: list[QtWidgets.QWidget] = [QtWidgets.QLabel("Time window"), self.window_box, self.auto_box]
        for w in self._bar_first:
            bar.addWidget(w)
        bar.addWidget(self.rate_label)
        bar.addWidget(self.sensor_label)
        bar.addWidget(self.info, 1)
        self._bar2 = QtWidgets.QHBoxLayout()
        self._bar2.addStretch(1)

        self.gl = TimedGraphicsLayout()
        self.gl.painted.connect(self._on_painted)
        # the text is fitted to the plots once their layout has settled, after any change of their size: the tab's,
        # the plots' widget's alone (the scroll bar comes or goes), or a rebuild for a layout (a reconnected board)
        self._fit_timer = QtCore.QTimer(self, singleShot=True, interval=0)
        self._fit_timer.timeout.connect(self.fit_plots)
        self.gl.resized.connect(self._fit_timer.start)
        self.gl.ci.layout.setSpacing(4)
        if staged:  # one plot per pass of the event loop (each ~20-60 ms), never the whole ~0.5 s at once
            self._staged = StagedBuild(self._layout_steps(layout), self)
            self._staged.done.connect(self.built)
        else:
            self.set_layout(layout)

        # the plots keep readable heights (MIN_TRACE_PX, MIN_RASTER_PX): a shorter tab scrolls them
        self.plot_scroll = QtWidgets.QScrollArea(widgetResizable=True)
        self.plot_scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        self.plot_scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.plot_scroll.setWidget(self.gl)
        self._vbox = lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(bar)
        lay.addLayout(self._bar2)
        lay.addWidget(self.plot_scroll, 1)
        if staged:  # shown whole once built: no paint of a half-built grid between the steps
            self.plot_scroll.hide()
            self._building_label: QtWidgets.QLabel | None = QtWidgets.QLabel("building the live plots...")
            self._building_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            lay.addWidget(self._building_label, 1)
            self.built.connect(self._show_built)

    def _show_built(self) -> None:
        label = getattr(self, "_building_label", None)
        if label is not None:
            label.hide()
            label.deleteLater()
            self._building_label = None
        self.plot_scroll.show()
        self._arrange_bar()  # (the bar's rows for the tab's width: no resize may come once it is built)

    def _bar_widths(self) -> tuple[int, int]:
        """The width (px) the bar needs on one row, and on two rows (the rates and the sensor on the second)."""
        space = self._bar.spacing()
        m = self._vbox.contentsMargins()
        first = self._bar_first  # Time window, its box, Auto-range y
        second: list[QtWidgets.QWidget] = [self.rate_label, self.sensor_label]
        one = sum(w.sizeHint().width() for w in first + second) + space * len(first + second)
        two = max(sum(w.sizeHint().width() for w in first) + space * (len(first) - 1),
                  sum(w.sizeHint().width() for w in second) + space)
        return one + m.left() + m.right(), two + m.left() + m.right()

    def _arrange_bar(self) -> None:
        """The bar on one row when the tab is wide enough for it, else on two: the rates and the sensor move to the
        second row (issue 38: 683 px of Qt's pixels at 1.5x on a 1024x700 screen), nothing is cut."""
        two_rows = self.width() < self._bar_widths()[0]
        if two_rows == (self._bar2.indexOf(self.sensor_label) >= 0):
            return
        for i, w in enumerate((self.rate_label, self.sensor_label)):
            (self._bar if two_rows else self._bar2).removeWidget(w)
            if two_rows:
                self._bar2.insertWidget(i, w)
            else:
                self._bar.insertWidget(3 + i, w)

    def resizeEvent(self, ev) -> None:  # noqa: N802 - Qt override
        self._arrange_bar()
        super().resizeEvent(ev)

    def minimumSizeHint(self) -> QtCore.QSize:  # noqa: N802 - Qt override
        """As the layout's, but as wide only as the bar on two rows needs (it takes two rows when narrower)."""
        hint = super().minimumSizeHint()
        m = self._vbox.contentsMargins()
        hint.setWidth(max(self._bar_widths()[1], self.plot_scroll.minimumSizeHint().width() + m.left() + m.right()))
        return hint

    @property
    def raster_s(self) -> float:
        """The rasters' window (s): the same as the traces' (one time axis)."""
        return self.window_s

    @property
    def time_plots(self) -> list:
        """Every plot on the shared time axis: the trace plots, then the SA and RA rasters."""
        return [*self.trace_plots, *self.raster_plots.values()]

    def set_layout(self, layout: SensorLayout) -> None:
        """Build the plots for ``layout``: per layer a trace plot (one curve per taxel, a colour legend) and a rows
        x cols heat map (taxel numbers, one colour bar), and an SA and an RA raster of ``layout.n_channels`` rows.
        Nothing is rebuilt when the layout is unchanged."""
        self.finish_build()
        for _ in self._layout_steps(layout):
            pass

    def _layout_steps(self, layout: SensorLayout) -> Iterator[None]:
        """:meth:`set_layout` in steps: it yields after each plot (the staged build runs one step per pass of the
        event loop)."""
        if layout == self.sensor_layout:
            return
        self._complete = False
        self.sensor_layout = layout
        self.gl.clear()
        self.sensor_label.setText(f"  sensor {layout.shape_text}, {layout.n_channels} taxels, "
                                  f"{layout.sample_rate_hz:g} Hz, {layout.adc_bits}-bit")
        self.sensor_label.setToolTip(layout.describe())
        n_layers, adc_max, labels = layout.n_layers, layout.adc_max, layout.channel_labels()
        self._y_ranges: list[tuple[float, float] | None] = [None] * n_layers
        self.gap_marks: list[list[pg.InfiniteLine]] = []
        #: each time plot's title texts, the first that fits its width in :data:`TITLE_SIZES_PT` is shown
        self._titles: dict[pg.PlotItem, list[str]] = {}

        def time_plot(row: int, title: str):
            p = self.gl.addPlot(row=row, col=0, enableMenu=False)  # no context menus (never built)
            self._titles[p] = [title]
            p.setMouseEnabled(x=False, y=False)
            p.hideButtons()
            p.disableAutoRange()
            p.setXRange(-self.window_s, 0, padding=0)
            p.getAxis("left").setWidth(AXIS_WIDTH_PX)
            # axes and titles are drawn once into pixmaps and blitted while the data under them scroll (their ticks
            # reach into the data area, so each frame's repaint of it would otherwise redraw their text)
            cache_axes_and_title(p)
            # where frames stopped coming (an outage): a dashed red line per gap in the window
            marks = [pg.InfiniteLine(angle=90, movable=False, pen=pg.mkPen("#c00", width=2, style=QtCore.Qt.PenStyle.DashLine))
                     for _ in range(GAP_MARKS)]
            for m in marks:
                m.hide()
                p.addItem(m, ignoreBounds=True)
            self.gap_marks.append(marks)
            return p

        # traces: one plot per layer, a colour legend of its taxels in the title
        self.trace_plots = []
        self.trace_items = []
        self.curves = []
        self._layer_channels = [layout.layer_channels(i) for i in range(n_layers)]
        for i, chans in enumerate(self._layer_channels):
            p = time_plot(i, f"{layer_titles(layout, i)[0]}&nbsp;&nbsp;&nbsp;{legend_html(layout, i)}")
            self._titles[p].append(legend_html(layout, i))  # a narrow plot: the legend alone (it names the taxels)
            p.setLabel("left", "ADC counts")
            p.vb.setMinimumHeight(MIN_TRACE_PX)
            p.setYRange(0, adc_max, padding=0)
            item = TracesItem([pg.mkPen(colour, width=1) for colour in trace_colours(len(chans))],
                              [labels[ch] for ch in chans])
            p.addItem(item)
            self.trace_items.append(item)
            self.curves.extend(item.curves)
            self.trace_plots.append(p)
            yield

        # rasters: one row per taxel, one image per population, on the traces' time axis
        n = layout.n_channels
        self.raster_plots = {}
        self.raster_images = {}
        for row, (key, title) in enumerate(
            [("sa", f"SA spike raster ({n} trains)"), ("ra", f"RA spike raster ({n} trains)")], start=n_layers,
        ):
            p = time_plot(row, title)
            p.setYRange(-0.5, n - 0.5, padding=0)
            p.setLabel("left", "taxel")
            p.getAxis("left").setTicks([raster_ticks(layout)])
            p.vb.setMinimumHeight(MIN_RASTER_PX)
            colour = QtGui.QColor(RASTER_COLOURS[key])
            img = RasterItem([QtGui.QColor("white"), colour, colour.darker(170)])
            img.setRect(QtCore.QRectF(-self.window_s, -0.5, self.window_s, n))
            p.addItem(img)
            self.raster_plots[key] = p
            self.raster_images[key] = img
            self.drawn[key] = (np.zeros(0), np.zeros(0, np.int16))
            yield
        self.raster_plots["ra"].setLabel("bottom", "time before now (s)")
        for p in self.time_plots[:-1]:  # one time axis: its values under the lowest plot only (the others' ticks stay)
            p.getAxis("bottom").setStyle(showValues=False)

        # heat maps: one per layer beside its traces (its rows x cols grid, taxel numbers in the cells), one colour
        # bar for all
        self.images = []
        self.taxel_labels = []
        cmap = pg.colormap.get("viridis")
        lut = cmap.getLookupTable(nPts=256)
        for i, la in enumerate(layout.layers):
            cell = self.gl.addLayout(row=i, col=1)
            cell.addLabel(layer_titles(layout, i)[1], row=0, col=0, size="9pt")
            cell.layout.setRowFixedHeight(0, 20)
            vb = cell.addViewBox(row=1, col=0, lockAspect=True, enableMouse=False, invertY=True, enableMenu=False)
            vb.setAspectLocked(True, ratio=heatmap_aspect(la.rows, la.cols))
            img = pg.ImageItem(np.zeros((la.rows, la.cols)), axisOrder="row-major")
            img.setLookupTable(lut)
            img.setLevels((0, adc_max))
            ch0 = self._layer_channels[i].start
            img.setToolTip("\n".join(  # which taxel is where: channel number and name, row by row
                "   ".join(f"{ch0 + r * la.cols + c}: {labels[ch0 + r * la.cols + c]}" for c in range(la.cols))
                for r in range(la.rows)))
            vb.addItem(img)
            # a fixed range: no auto-range pass (and relayout of the numbers) each time the image changes
            vb.disableAutoRange()
            vb.setRange(xRange=(0, la.cols), yRange=(0, la.rows), padding=0)
            if la.n_channels <= 64:  # the taxel numbers, top left in each cell, on a pale box (any colour under it)
                self.taxel_labels.extend(add_taxel_numbers(vb, la.rows, la.cols, ch0))
            self.images.append(img)
            yield
        bar = pg.ColorBarItem(values=(0, adc_max), colorMap=cmap, interactive=False, colorMapMenu=False, width=12,
                              label="ADC counts")
        self.gl.addItem(bar, row=0, col=2, rowspan=n_layers)
        self.colour_bar = bar
        grid = self.gl.ci.layout
        grid.setColumnFixedWidth(1, 150)
        grid.setColumnFixedWidth(2, 75)
        # the traces get at least as much height as the two rasters (a single layer: twice a raster's)
        for row in range(n_layers + 2):
            grid.setRowStretchFactor(row, 2 if n_layers == 1 and row == 0 else 1)
        mark_containers(self.gl.ci)
        for vb in [p.vb for p in self.time_plots] + [img.getViewBox() for img in self.images]:
            vb.sigResized.connect(self._fit_timer.start)
        self._complete = True
        self.fit_plots()
        self._fit_timer.start()

    def fit_plots(self) -> None:
        """Fit the plots' text to their size: each time plot's title in the largest of :data:`TITLE_SIZES_PT` that
        fits its width (else its shorter text; a title never widens the column, so the heat maps and the colour bar
        keep their room), its title row as tall as that text, as many raster ticks as fit without overlapping, the
        plots' minimum height (the tab scrolls below it), and the taxel numbers (:meth:`fit_taxel_labels`)."""
        if not self._complete:  # (a staged build: fitted once its last plot exists)
            return
        for p, texts in self._titles.items():
            label, width = p.titleLabel, p.vb.width() or self.gl.width()  # the title spans the data area
            for text, size in [(t, s) for t in texts for s in TITLE_SIZES_PT]:
                if label.text != text or label.opts.get("size") != f"{size}pt":
                    p.setTitle(text, size=f"{size}pt")
                if label.item.boundingRect().width() <= width:
                    break
            h = int(np.ceil(label.item.boundingRect().height()))
            label.updateMin = functools.partial(_title_min, label)  # pyqtgraph's sets the text's width at each resize
            label.updateMin()
            label.setMaximumHeight(h)
            p.layout.setRowFixedHeight(0, h)
        if self.raster_plots:  # a tick label per 1.5 lines of the axis' font at most
            fit = int(self.raster_plots["sa"].vb.height() // (1.5 * QtGui.QFontMetrics(self.gl.font()).height()))
            ticks = [raster_ticks(self._layout(), min(6, max(2, fit)))]
            for p in self.raster_plots.values():
                if p.getAxis("left")._tickLevels != ticks:
                    p.getAxis("left").setTicks(ticks)
        need = self.gl.ci.effectiveSizeHint(QtCore.Qt.SizeHint.MinimumSize).height()
        self.gl.setMinimumHeight(int(np.ceil(need)) + 2 * self.gl.frameWidth())
        self.fit_taxel_labels()

    def fit_taxel_labels(self) -> None:
        """Show the taxel numbers in the heat maps when the cells are large enough to keep their colour visible
        (:data:`MIN_LABELLED_CELL_PX`)."""
        if not self.images:
            return
        cells = []
        for img in self.images:
            r = img.mapRectToScene(img.boundingRect())
            rows, cols = img.image.shape[:2]
            cells.append(min(r.width() / cols, r.height() / rows))
        show = min(cells) >= MIN_LABELLED_CELL_PX
        for t in self.taxel_labels:
            t.setVisible(show)

    def _layout(self) -> SensorLayout:
        """The sensor the plots are built for. Raises RuntimeError before :meth:`set_layout`."""
        if self.sensor_layout is None:
            raise RuntimeError("the live view has no sensor layout yet (set_layout)")
        return self.sensor_layout

    def set_window(self, seconds: float) -> None:
        """Show the last ``seconds`` (0.5-10 s) in the traces and the rasters alike (one time axis)."""
        self.finish_build()
        self.window_s = float(np.clip(seconds, *WINDOW_RANGE_S))
        for p in self.time_plots:
            p.setXRange(-self.window_s, 0, padding=0)
        for img in self.raster_images.values():
            img.setRect(QtCore.QRectF(-self.window_s, -0.5, self.window_s, self._layout().n_channels))
        if self.window_box.value() != self.window_s:
            self.window_box.setValue(self.window_s)

    def set_auto_range(self, on: bool) -> None:
        """Trace y axes follow the data in the window (``on``) or show the full ADC range."""
        self.finish_build()
        if self.auto_box.isChecked() != bool(on):
            self.auto_box.setChecked(bool(on))
        self._y_ranges = [None] * len(self.trace_plots)
        if not on:
            for p in self.trace_plots:
                p.setYRange(0, self._layout().adc_max, padding=0)

    def attach(self, taxels, encoder, layout: SensorLayout | None = None, since: int | None = None) -> None:
        """Show ``taxels`` (a :class:`rigctl.devices.taxel_stream.TaxelStream`) and ``encoder``'s spikes, with the
        plots built for ``layout`` (default the stream's ``layout``; the paper's sensor for a stream without one);
        ``since``: the stream's frame count the traces start from (default now; :class:`rigctl_gui.workers.TraceBuffer`)."""
        layout = layout or getattr(taxels, "layout", None) or PAPER_SENSOR
        self.set_layout(layout)
        # every frame of the longest window is kept; drawing decimates to the pixel width
        self.buffer = TraceBuffer(taxels.ring, seconds=WINDOW_RANGE_S[1], decimate=1, layout=layout, since=since)
        self.encoder = encoder
        self._refresh_n = 0  # the first refresh draws everything

    def detach(self) -> None:
        self.encoder = self.buffer = None

    def data_width_px(self) -> int:
        """Pixel width of the time plots' data area (the same for all of them)."""
        return max(int(round(self.trace_plots[0].vb.width())), 1)

    # ------------------------------------------------------------------------------------------------------
    def refresh(self) -> bool:
        """Redraw from the encoder's buffers; returns True when new data was drawn."""
        enc, buf = self.encoder, self.buffer
        if buf is None or not self.isVisible() or self.building:
            return False
        if buf.pull() == 0:
            return False
        # only the window (and one sample before it) is copied out of the buffer
        stream_t, x = buf.view(last=int(np.ceil(self.window_s * buf.rate_hz)) + 2)
        t = buf.display_time(stream_t)  # an outage takes its real width on the time axis (a gap, not a seam)
        stream_now, now = float(stream_t[-1]), float(t[-1])
        first = int(np.searchsorted(t, now - self.window_s - 1e-9))
        t, x, stream_t = t[first:], x[first:], stream_t[first:]
        width = self.data_width_px()
        # x = time before now: the axes never change, so pyqtgraph reuses their drawing; every taxel peak-decimated
        # to the pixel width in one compiled pass, straight into the polyline points (live_kernels)
        first_index = int(round(stream_t[0] * buf.rate_hz))  # the absolute sample number (bins stay put)
        need = live_kernels.decimated_length(len(t), width, first_index)
        pts = self._trace_points
        if pts is None or pts.shape[0] != x.shape[1] or pts.shape[1] < need:  # room for a few more points
            pts = self._trace_points = np.zeros((x.shape[1], need + 64, 2))
            self._trace_lo, self._trace_hi = np.empty(x.shape[1]), np.empty(x.shape[1])
        lo, hi = self._trace_lo, self._trace_hi
        if live_kernels.ready():
            n_points = live_kernels.decimate_traces(t, x, now, width, first_index, pts, lo, hi)
        else:  # the kernels compile in the background (seconds, never here): the numpy reference, the same points
            live_kernels.warm_up()
            n_points = _decimate_into(t, x, now, width, first_index, pts, lo, hi)
        at = buf.display_time(np.array([g for g, _ in buf.gaps])) if buf.gaps else ()
        gaps = [(float(g) - now, d) for g, (_, d) in zip(at, buf.gaps) if g - now > -self.window_s]
        breaks = np.searchsorted(pts[0, :n_points, 0], [g - 1e-9 for g, _ in gaps]) if gaps else ()
        self.shown_gaps = gaps
        self._show_gap_marks(gaps)
        auto = self.auto_box.isChecked()
        for i, (p, item, chans) in enumerate(zip(self.trace_plots, self.trace_items, self._layer_channels)):
            if auto:  # the y range first, so the traces are drawn in the view they will be shown in
                r = auto_y_range(float(lo[chans.start:chans.stop].min()), float(hi[chans.start:chans.stop].max()),
                                 self._y_ranges[i], self._layout().adc_max)
                if r is not None:
                    self._y_ranges[i] = r
                    p.setYRange(*r, padding=0)
            item.set_points(pts[chans.start:chans.stop], n_points, breaks)
        if self._refresh_n % HEATMAP_EVERY == 0:
            self.heatmap_frame = cur = buf.current.copy()
            for img, chans, la in zip(self.images, self._layer_channels, self._layout().layers):
                img.setImage(cur[chans.start:chans.stop].reshape(la.rows, la.cols).astype(float), autoLevels=False)
        if enc is not None:
            n = self._layout().n_channels
            height = max(int(round(self.raster_plots["sa"].vb.height())), 1)
            for key, ring in (("sa", enc.sa), ("ra", enc.ra)):
                st, sc = ring.since(stream_now - self.window_s)  # stream time, as the encoder counts it
                st = buf.display_time(st) - now
                keep = st >= -self.window_s  # an outage in the window pushes the spikes before it further back
                st, sc = st[keep], sc[keep]
                self.drawn[key] = (st, sc)
                self.raster_images[key].draw_spikes(st, sc, n, self.window_s, width, height)
            if self._refresh_n % INFO_EVERY == 0:
                err = enc.encoder_error
                state = "" if enc.ready else " (encoder starting: compiling kernels)"
                self.rate_label.setText(f"  display {self.display_rate_hz():.0f}/s, taxels "
                                        f"{self.stream_rate_hz(buf):.0f} frames/s")
                self.info.setText(
                    f"{buf.n_samples} frames shown, SA {enc.sa.total} / RA {enc.ra.total} spikes{state}"
                    + (f" - encoder: {err}" if err else "")
                )
        self._refresh_n += 1
        self._pending_host_t = buf.newest_host_time_s
        return True

    def _show_gap_marks(self, gaps: list[tuple[float, float]]) -> None:
        """Place the gap lines of every time plot at ``gaps`` ((time before now, s; outage length, s))."""
        for marks in self.gap_marks:
            for i, m in enumerate(marks):
                if i < len(gaps):
                    m.setPos(gaps[i][0])
                    m.setToolTip(f"no taxel frame for {gaps[i][1]:.1f} s")
                    m.show()
                elif m.isVisible():
                    m.hide()

    def display_rate_hz(self) -> float:
        """Paints of the live view per second over the last 2 s (the frame-rate readout)."""
        t = self.paint_times[np.isfinite(self.paint_times)]
        if t.size < 2:
            return 0.0
        t = t[t >= t.max() - 2.0]
        return (t.size - 1) / (t.max() - t.min()) if t.size > 1 and t.max() > t.min() else 0.0

    def stream_rate_hz(self, buf) -> float:
        """Taxel frames per second arriving (the frames pulled over the last ~second)."""
        now = time.monotonic()
        last = getattr(self, "_rate_mark", None)
        if last is None or now - last[0] >= 1.0:
            if last is not None:
                self._stream_rate = (buf.n_samples - last[1]) / (now - last[0])
            self._rate_mark = (now, buf.n_samples)
        return getattr(self, "_stream_rate", 0.0)

    def _on_painted(self, t_paint: float) -> None:
        self.paint_times[self._paint_n % len(self.paint_times)] = t_paint
        self._paint_n += 1
        if self._pending_host_t is not None and np.isfinite(self._pending_host_t):
            self.latencies_s[self._lat_n % len(self.latencies_s)] = t_paint - self._pending_host_t
            self._lat_n += 1
        self._pending_host_t = None

    @property
    def paints(self) -> int:
        return self._paint_n
