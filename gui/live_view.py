"""Live view: the 18 taxel traces (scrolling, last N seconds), a 3x3 top/bottom heat map of the current readings,
and the live SA and RA spike rasters of all 36 spike trains from the streaming encoder.

Everything is drawn from fixed-size buffers filled from the taxel stream's ring buffer (never the file):
:class:`gui.workers.TraceBuffer` (pulled in the GUI thread, so a frame reaches the screen without waiting for a
worker) and the spike rings of :class:`gui.workers.LiveEncoder` (a worker thread), by :meth:`LiveView.refresh`,
called from the main window's QTimer at >= 30 Hz. Each
raster population is ONE curve with ``connect='pairs'`` (one short vertical tick per spike), so redrawing costs one
item per population however many spikes there are (pyqtgraph #1039/#1737/#2158).
"""

from __future__ import annotations

import time

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from gui.workers import TraceBuffer
from rigctl.devices.wire import ADC_MAX, N_TAXELS, N_TAXELS_PER_LAYER

#: most spikes drawn per population and refresh; beyond that the newest are kept (decimation)
MAX_DRAWN_SPIKES = 12_000


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
    """The live tab. Call :meth:`attach` with the taxel stream and a running :class:`gui.workers.LiveEncoder`."""

    def __init__(self, parent=None, *, window_s: float = 5.0, raster_s: float = 2.0):
        super().__init__(parent)
        self.encoder = None
        self.buffer = None
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
        bar = QtWidgets.QHBoxLayout()
        bar.addWidget(QtWidgets.QLabel("Trace window"))
        bar.addWidget(self.window_box)
        bar.addStretch(1)
        bar.addWidget(self.info)

        self.gl = TimedGraphicsLayout()
        self.gl.painted.connect(self._on_painted)
        self.gl.ci.layout.setSpacing(4)

        # traces: top layer and bottom layer
        self.trace_plots = []
        self.curves = []
        layers = ["Top layer (type I) taxels 0-8", "Bottom layer (type II) taxels 9-17"]
        for row, name in enumerate(layers):
            p = self.gl.addPlot(row=row, col=0, title=name)
            p.setLabel("left", "ADC counts")
            p.setYRange(0, ADC_MAX, padding=0.02)
            p.setXRange(-window_s, 0, padding=0)
            p.setMouseEnabled(x=False, y=True)
            p.hideButtons()
            p.disableAutoRange()
            for k in range(N_TAXELS_PER_LAYER):
                c = pg.PlotCurveItem(pen=pg.mkPen(pg.intColor(k, N_TAXELS_PER_LAYER), width=1), skipFiniteCheck=True)
                p.addItem(c)
                self.curves.append(c)
            self.trace_plots.append(p)
        # no setXLink: with PySide6 6.12 + pyqtgraph 0.14 a linked-view update crashes the interpreter
        # ("deallocating None" in ViewBox.linkedViewChanged); each plot's x range is set explicitly instead

        # heat maps
        hm = self.gl.addLayout(row=0, col=1, rowspan=2)
        self.images = []
        cmap = pg.colormap.get("viridis")
        for r, name in enumerate(["Top 3x3 (type I) now", "Bottom 3x3 (type II) now"]):
            hm.addLabel(name, row=2 * r, col=0, size="9pt")
            vb = hm.addViewBox(row=2 * r + 1, col=0, lockAspect=True, enableMouse=False, invertY=True)
            img = pg.ImageItem(np.zeros((3, 3)), axisOrder="row-major")
            img.setLookupTable(cmap.getLookupTable(nPts=256))
            img.setLevels((0, ADC_MAX))
            vb.addItem(img)
            self.images.append(img)
        hm.addLabel("colour: 0-1023 ADC counts (viridis)", row=4, col=0, size="8pt")
        hm.layout.setColumnFixedWidth(0, 170)

        # rasters
        self.raster_plots = {}
        self.raster_curves = {}
        for row, (key, title, colour) in enumerate(
            [("sa", "SA spike raster (18 trains)", "#1f77b4"), ("ra", "RA spike raster (18 trains)", "#d62728")],
            start=2,
        ):
            p = self.gl.addPlot(row=row, col=0, colspan=2, title=title)
            p.setYRange(-0.5, N_TAXELS - 0.5, padding=0)
            p.setXRange(-raster_s, 0, padding=0)
            p.setMouseEnabled(x=False, y=False)
            p.disableAutoRange()
            p.hideButtons()
            p.setLabel("left", "taxel")
            p.getAxis("left").setTicks([[(i, str(i)) for i in range(0, N_TAXELS, 3)]])
            c = pg.PlotCurveItem(pen=pg.mkPen(colour, width=1), connect="pairs", skipFiniteCheck=True)
            p.addItem(c)
            self.raster_plots[key] = p
            self.raster_curves[key] = c
        self.raster_plots["ra"].setLabel("bottom", "time before now (s)")
        self.trace_plots[1].setLabel("bottom", "time before now (s)")

        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(bar)
        lay.addWidget(self.gl, 1)

    def set_window(self, seconds: float) -> None:
        """Show the last ``seconds`` (1-10 s) of the taxel traces."""
        self.window_s = float(seconds)
        for p in self.trace_plots:
            p.setXRange(-self.window_s, 0, padding=0)

    def attach(self, taxels, encoder) -> None:
        """Show ``taxels`` (a :class:`rigctl.devices.taxel_stream.TaxelStream`) and ``encoder``'s spikes."""
        self.buffer = TraceBuffer(taxels.ring, seconds=10.0, decimate=5)  # 200 Hz on screen
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
        self.images[0].setImage(cur[:9].reshape(3, 3), autoLevels=False)
        self.images[1].setImage(cur[9:].reshape(3, 3), autoLevels=False)
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
