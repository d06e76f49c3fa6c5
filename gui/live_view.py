"""Live view: the taxel traces (scrolling, last N seconds) and a heat map of the current readings, one of each per
layer of the sensor, and the live SA and RA spike rasters (one train per taxel each) from the streaming encoder.

Everything follows the stream's :class:`rigctl.core.sensor.SensorLayout` (``TaxelStream.layout``; default the paper's
3x3x2 at 1 kHz, 10-bit): the number of trace plots and heat maps (one per layer, each heat map the layer's rows x
cols grid), the raster rows (``layout.n_channels`` trains per population), the time axes (``sample_rate_hz``) and
the count ranges (``adc_max``).

Everything is drawn from fixed-size buffers filled from the taxel stream's ring buffer (never the file):
:class:`rigctl_gui.workers.TraceBuffer` (pulled in the GUI thread, so a frame reaches the screen without waiting for a
worker) and the spike rings of :class:`rigctl_gui.workers.LiveEncoder` (a worker thread), by :meth:`LiveView.refresh`,
called from the main window's QTimer at >= 30 Hz. Each
raster population is ONE curve with ``connect='pairs'`` (one short vertical tick per spike), so redrawing costs one
item per population however many spikes there are (pyqtgraph #1039/#1737/#2158).
"""

from __future__ import annotations

import time

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from rigctl_gui.workers import TraceBuffer
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout

#: most spikes drawn per population and refresh; beyond that the newest are kept (decimation)
MAX_DRAWN_SPIKES = 12_000
#: trace samples per second on screen (the stream is decimated to about this)
SCREEN_RATE_HZ = 200.0


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


def heatmap_aspect(rows: int, cols: int, *, max_elongation: float = 4.0) -> float:
    """The heat map's locked aspect ratio (pyqtgraph's ``xScale / yScale``): square taxels (1.0) unless the grid is
    longer than ``max_elongation`` : 1, whose taxels are stretched so the map is at most that elongated (a 1 x 16 row
    shows as a 4 : 1 strip instead of a 16 : 1 line)."""
    if cols > max_elongation * rows:
        return max_elongation * rows / cols
    if rows > max_elongation * cols:
        return rows / (max_elongation * cols)
    return 1.0


def raster_ticks(layout: SensorLayout) -> list[tuple[int, str]]:
    """Left-axis ticks of a raster: every 3rd taxel for the paper's 18 (about six ticks for any count); the channel
    names when the layout has its own and they fit (<= 20 channels)."""
    n = layout.n_channels
    if layout.channel_names is not None and n <= 20:
        return list(enumerate(layout.channel_names))
    step = max(1, int(round(n / 6)))
    return [(i, str(i)) for i in range(0, n, step)]


def raster_segments(t: np.ndarray, ch: np.ndarray, out: np.ndarray, *, height: float = 0.8) -> int:
    """Fill ``out[:2n]`` (``(2*cap, 2)`` float64, x/y) with one vertical segment per spike; returns ``2n``.

    Spike ``i`` at time ``t[i]`` (s) on train ``ch[i]`` becomes the pair ``(t, ch - h/2), (t, ch + h/2)``.
    """
    cap = len(out) // 2
    if len(t) > cap:  # decimate: keep the newest
        order = np.argsort(t)[-cap:]
        t, ch = t[order], ch[order]
    n = len(t)
    out[0 : 2 * n : 2, 0] = t
    out[1 : 2 * n : 2, 0] = t
    out[0 : 2 * n : 2, 1] = ch - height / 2
    out[1 : 2 * n : 2, 1] = ch + height / 2
    return 2 * n


class TimedGraphicsLayout(pg.GraphicsLayoutWidget):
    """A GraphicsLayoutWidget that records when each paint finished (for the frame-to-screen latency)."""

    painted = QtCore.Signal(float)

    def paintEvent(self, ev):  # noqa: N802 - Qt override
        super().paintEvent(ev)
        self.painted.emit(time.monotonic())


class LiveView(QtWidgets.QWidget):
    """The live tab. Call :meth:`attach` with the taxel stream and a running :class:`rigctl_gui.workers.LiveEncoder`; the
    plots are rebuilt for the stream's layout (``layout`` is the one shown before anything is attached)."""

    def __init__(self, parent=None, *, window_s: float = 5.0, raster_s: float = 2.0,
                 layout: SensorLayout = PAPER_SENSOR):
        super().__init__(parent)
        self.encoder = None
        self.buffer = None
        self.layout = None
        self.window_s = window_s
        self.raster_s = raster_s
        self._seg = {k: np.zeros((2 * MAX_DRAWN_SPIKES, 2)) for k in ("sa", "ra")}
        #: host receive time (time.monotonic) of the newest frame drawn in the last refresh, awaiting its paint
        self._pending_host_t = None
        self.latencies_s = np.full(4096, np.nan)  # frame-to-screen latency of recent paints (ring)
        self._lat_n = 0
        self.paint_times = np.full(512, np.nan)
        self._paint_n = 0

        self.window_box = QtWidgets.QDoubleSpinBox(suffix=" s", decimals=1, minimum=1.0, maximum=10.0, value=window_s)
        self.window_box.valueChanged.connect(self.set_window)
        self.info = QtWidgets.QLabel("")
        self.sensor_label = QtWidgets.QLabel("")
        bar = QtWidgets.QHBoxLayout()
        bar.addWidget(QtWidgets.QLabel("Trace window"))
        bar.addWidget(self.window_box)
        bar.addWidget(self.sensor_label)
        bar.addStretch(1)
        bar.addWidget(self.info)

        self.gl = TimedGraphicsLayout()
        self.gl.painted.connect(self._on_painted)
        self.gl.ci.layout.setSpacing(4)
        self.set_layout(layout)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(bar)
        lay.addWidget(self.gl, 1)

    def set_layout(self, layout: SensorLayout) -> None:
        """Build the plots for ``layout``: per layer a trace plot (one curve per taxel) and a rows x cols heat map,
        and an SA and an RA raster of ``layout.n_channels`` rows. Nothing is rebuilt when the layout is unchanged."""
        if layout == self.layout:
            return
        self.layout = layout
        self.gl.clear()
        self.sensor_label.setText(f"  sensor {layout.shape_text}, {layout.n_channels} taxels, "
                                  f"{layout.sample_rate_hz:g} Hz, {layout.adc_bits}-bit")
        self.sensor_label.setToolTip(layout.describe())
        n_layers, adc_max, labels = layout.n_layers, layout.adc_max, layout.channel_labels()

        # traces: one plot per layer
        self.trace_plots = []
        self.curves = []
        for i in range(n_layers):
            p = self.gl.addPlot(row=i, col=0, title=layer_titles(layout, i)[0])
            p.setLabel("left", "ADC counts")
            p.setYRange(0, adc_max, padding=0.02)
            p.setXRange(-self.window_s, 0, padding=0)
            p.setMouseEnabled(x=False, y=True)
            p.hideButtons()
            p.disableAutoRange()
            chans = layout.layer_channels(i)
            for k, ch in enumerate(chans):
                c = pg.PlotCurveItem(pen=pg.mkPen(pg.intColor(k, len(chans)), width=1), skipFiniteCheck=True,
                                     name=labels[ch])
                p.addItem(c)
                self.curves.append(c)
            self.trace_plots.append(p)
        # no setXLink: with PySide6 6.12 + pyqtgraph 0.14 a linked-view update crashes the interpreter
        # ("deallocating None" in ViewBox.linkedViewChanged); each plot's x range is set explicitly instead

        # heat maps: one per layer, its rows x cols grid
        self._layer_slices = [(layout.layer_channels(i).start, layout.layer_channels(i).stop, (la.rows, la.cols))
                              for i, la in enumerate(layout.layers)]
        hm = self.gl.addLayout(row=0, col=1, rowspan=n_layers)
        self.images = []
        cmap = pg.colormap.get("viridis")
        for i, la in enumerate(layout.layers):
            hm.addLabel(layer_titles(layout, i)[1], row=2 * i, col=0, size="9pt")
            vb = hm.addViewBox(row=2 * i + 1, col=0, lockAspect=True, enableMouse=False, invertY=True)
            vb.setAspectLocked(True, ratio=heatmap_aspect(la.rows, la.cols))
            img = pg.ImageItem(np.zeros((la.rows, la.cols)), axisOrder="row-major")
            img.setLookupTable(cmap.getLookupTable(nPts=256))
            img.setLevels((0, adc_max))
            ch0 = layout.layer_channels(i).start
            img.setToolTip("\n".join(  # which taxel is where: channel number and name, row by row
                "   ".join(f"{ch0 + r * la.cols + c}: {labels[ch0 + r * la.cols + c]}" for c in range(la.cols))
                for r in range(la.rows)))
            vb.addItem(img)
            self.images.append(img)
        hm.addLabel(f"colour: 0-{adc_max} ADC counts (viridis)", row=2 * n_layers, col=0, size="8pt")
        hm.layout.setColumnFixedWidth(0, 170)

        # rasters: one row per taxel
        n = layout.n_channels
        self.raster_plots = {}
        self.raster_curves = {}
        for row, (key, title, colour) in enumerate(
            [("sa", f"SA spike raster ({n} trains)", "#1f77b4"), ("ra", f"RA spike raster ({n} trains)", "#d62728")],
            start=n_layers,
        ):
            p = self.gl.addPlot(row=row, col=0, colspan=2, title=title)
            p.setYRange(-0.5, n - 0.5, padding=0)
            p.setXRange(-self.raster_s, 0, padding=0)
            p.setMouseEnabled(x=False, y=False)
            p.disableAutoRange()
            p.hideButtons()
            p.setLabel("left", "taxel")
            p.getAxis("left").setTicks([raster_ticks(layout)])
            c = pg.PlotCurveItem(pen=pg.mkPen(colour, width=1), connect="pairs", skipFiniteCheck=True)
            p.addItem(c)
            self.raster_plots[key] = p
            self.raster_curves[key] = c
        self.raster_plots["ra"].setLabel("bottom", "time before now (s)")
        self.trace_plots[-1].setLabel("bottom", "time before now (s)")
        # the traces get at least as much height as the two rasters (a single layer: twice a raster's)
        grid = self.gl.ci.layout
        for row in range(n_layers + 2):
            grid.setRowStretchFactor(row, 2 if n_layers == 1 and row == 0 else 1)

    def set_window(self, seconds: float) -> None:
        """Show the last ``seconds`` (1-10 s) of the taxel traces."""
        self.window_s = float(seconds)
        for p in self.trace_plots:
            p.setXRange(-self.window_s, 0, padding=0)

    def attach(self, taxels, encoder, layout: SensorLayout | None = None) -> None:
        """Show ``taxels`` (a :class:`rigctl.devices.taxel_stream.TaxelStream`) and ``encoder``'s spikes, with the
        plots built for ``layout`` (default the stream's ``layout``; the paper's sensor for a stream without one)."""
        layout = layout or getattr(taxels, "layout", None) or PAPER_SENSOR
        self.set_layout(layout)
        decimate = max(1, int(round(layout.sample_rate_hz / SCREEN_RATE_HZ)))  # 1 kHz: every 5th frame
        self.buffer = TraceBuffer(taxels.ring, seconds=10.0, decimate=decimate, layout=layout)
        self.encoder = encoder

    def detach(self) -> None:
        self.encoder = self.buffer = None

    # ------------------------------------------------------------------------------------------------------
    def refresh(self) -> bool:
        """Redraw from the encoder's buffers; returns True when new data was drawn."""
        enc, buf = self.encoder, self.buffer
        if buf is None or not self.isVisible():
            return False
        if buf.pull() == 0:
            return False
        t, x = buf.view()
        now = t[-1]
        keep = t >= now - self.window_s
        t, x = t[keep], x[keep]
        # x = time before now: the axes never change, so pyqtgraph reuses their drawing (the axis repaint with
        # moving ticks was 60 % of the paint time)
        t = t - now
        for k, c in enumerate(self.curves):
            c.setData(t, x[:, k], skipFiniteCheck=True)
        cur = buf.current.astype(float)
        for img, (start, stop, shape) in zip(self.images, self._layer_slices):
            img.setImage(cur[start:stop].reshape(shape), autoLevels=False)
        t0 = now - self.raster_s
        for key, ring in (("sa", enc.sa), ("ra", enc.ra)) if enc is not None else ():
            st, sc = ring.since(t0)
            n = raster_segments(st - now, sc.astype(float), self._seg[key])
            seg = self._seg[key][:n]
            self.raster_curves[key].setData(seg[:, 0], seg[:, 1], connect="pairs", skipFiniteCheck=True)
        if enc is not None:
            err = enc.encoder_error
            state = "" if enc.ready else " (encoder starting: compiling kernels)"
            self.info.setText(
                f"{buf.n_samples} frames shown, SA {enc.sa.total} / RA {enc.ra.total} spikes{state}"
                + (f" - encoder: {err}" if err else "")
            )
        self._pending_host_t = buf.newest_host_time_s
        return True

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
