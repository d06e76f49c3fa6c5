"""The Live view's drawing items (:mod:`rigctl_gui.live_view`): all the traces of a plot in one item
(:class:`TracesItem`, issue 12: no per-curve bounds, signals and path building each frame), the flag that keeps Qt
from asking pure containers to paint (:func:`mark_containers`), the cached axes and titles
(:func:`cache_axes_and_title`, the control panel's plots too) and the layout widget that times its paints
(:class:`TimedGraphicsLayout`, for the frame-to-screen latency)."""

from __future__ import annotations

import time

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets


class TraceCurve:
    """One taxel's trace inside a :class:`TracesItem`: ``getData()`` (what is drawn: ``(t (n,) s, readings (n,))``),
    ``name()`` (the channel label) and ``opts["pen"]`` (the legend's colour), as pyqtgraph's curves have them."""

    def __init__(self, item: TracesItem, k: int, pen: QtGui.QPen, name: str):
        self._item, self._k, self._name = item, k, name
        self.opts = {"pen": pen, "name": name}

    def getData(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: N802 - pyqtgraph style
        return self._item.t, self._item.x[:, self._k]

    def name(self) -> str:
        return self._name


class TracesItem(pg.GraphicsObject):
    """All the traces of one plot (one layer's taxels) in one item: each a polyline of the (decimated) readings in
    its own 1-px cosmetic pen, no antialiasing. One item instead of a pyqtgraph curve per taxel: no per-curve data
    bounds, signals and path building each frame (issue 12); the bounding rect is the plot's view (the item is
    redrawn whole every frame anyway, since the traces scroll). ``curves``: a :class:`TraceCurve` per taxel."""

    def __init__(self, pens: list[QtGui.QPen], names: list[str]):
        super().__init__()
        self._pens = pens
        self.curves = [TraceCurve(self, k, pen, name) for k, (pen, name) in enumerate(zip(pens, names))]
        self._n = 0  # points drawn per taxel
        self._polys: list[QtGui.QPolygonF] = []  # one per taxel, reused from frame to frame
        self._points: list[np.ndarray] = []  # (capacity, 2) views of the polygons' points
        self._rect = QtCore.QRectF()
        self.segments: list[tuple[int, int]] = []

    @property
    def t(self) -> np.ndarray:
        """The times drawn (s), (n,)."""
        return self._points[0][:self._n, 0].copy() if self._points else np.zeros(0)

    @property
    def x(self) -> np.ndarray:
        """The readings drawn, (n, k)."""
        if not self._points:
            return np.zeros((0, len(self._pens)))
        return np.stack([pts[:self._n, 1] for pts in self._points], axis=1)

    def setData(self, t: np.ndarray, x: np.ndarray, breaks=()) -> None:  # noqa: N802 - pyqtgraph style
        """Draw ``t`` (n,) s against each column of ``x`` (n, k) readings; ``breaks``: indices where a new segment
        starts (an outage: no line is drawn across it)."""
        n = len(t)
        points = np.empty((x.shape[1], n, 2))
        points[:, :, 0] = t
        points[:, :, 1] = np.asarray(x).T
        self.set_points(points, n, breaks)

    def set_points(self, points: np.ndarray, n: int, breaks=()) -> None:
        """Draw the first ``n`` of ``points`` (k, capacity, 2): each taxel's ``(t (s), reading)``, the points past
        ``n`` repeating the last one (:func:`rigctl_gui.live_kernels.decimate_traces` writes them so); ``breaks``:
        indices where a new segment starts (an outage: no line is drawn across it)."""
        cuts = sorted({int(b) for b in breaks if 0 < int(b) < n}) if len(breaks) else []
        self.segments = list(zip([0, *cuts], [*cuts, n]))
        cap = points.shape[1]
        if not self._polys or len(self._points[0]) != cap:
            self._polys = [pg.functions.create_qpolygonf(cap) for _ in range(points.shape[0])]
            self._points = [pg.functions.ndarray_from_qpolygonf(poly) for poly in self._polys]
        for pts, src in zip(self._points, points):
            pts[:] = src
        self._n = n
        vb = self.getViewBox()
        rect = vb.viewRect() if vb is not None else QtCore.QRectF()
        if rect != self._rect:
            self.prepareGeometryChange()
            self._rect = rect
        self.update()

    def boundingRect(self) -> QtCore.QRectF:  # noqa: N802 - Qt override
        return QtCore.QRectF(self._rect)

    def paint(self, p, *args) -> None:
        if self._n == 0:
            return
        p.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing, False)
        if len(self.segments) <= 1:
            for pen, poly in zip(self._pens, self._polys):
                p.setPen(pen)
                p.drawPolyline(poly)
            return
        for pen, pts in zip(self._pens, self._points):  # an outage in the window: one polyline per segment
            p.setPen(pen)
            for a, b in self.segments:
                if b - a >= 2:
                    poly = pg.functions.create_qpolygonf(b - a)
                    pg.functions.ndarray_from_qpolygonf(poly)[:] = pts[a:b]
                    p.drawPolyline(poly)


def cache_axes_and_title(plot: pg.PlotItem) -> None:
    """Draw ``plot``'s left and bottom axes (their grid lines too) and its title once into pixmaps that are blitted
    while the data under them change (each repaint of the data area would otherwise replay their text); an axis or
    title is drawn again only when it changes (a new range, size or text)."""
    for name in ("left", "bottom"):
        plot.getAxis(name).setCacheMode(QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache)
    plot.titleLabel.item.setCacheMode(QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache)


def mark_containers(root: QtWidgets.QGraphicsItem) -> int:
    """Flag every pure container under ``root`` (layouts, plots, titles' boxes, view boxes without a border: they draw
    nothing themselves) ``ItemHasNoContents``, so Qt's paint of the scrolling data areas neither asks their Python
    ``boundingRect`` nor calls their Python ``paint`` each frame (pyqtgraph leaves the flag off). Their children draw
    as before. Returns how many were flagged."""
    flag = QtWidgets.QGraphicsItem.GraphicsItemFlag.ItemHasNoContents
    n, todo = 0, [root]
    while todo:
        item = todo.pop()
        todo.extend(item.childItems())
        if isinstance(item, (pg.GraphicsLayout, pg.PlotItem, pg.LabelItem)) or (
                isinstance(item, pg.ViewBox) and item.border is None):
            item.setFlag(flag, True)
            n += 1
    return n


class TimedGraphicsLayout(pg.GraphicsLayoutWidget):
    """A GraphicsLayoutWidget that records when each paint finished (for the frame-to-screen latency) and says when
    it was resized."""

    painted = QtCore.Signal(float)
    #: emitted after each resize (the Live view fits its titles and ticks to the new size)
    resized = QtCore.Signal()

    def resizeEvent(self, ev):  # noqa: N802 - Qt override
        super().resizeEvent(ev)
        self.resized.emit()

    def paintEvent(self, ev):  # noqa: N802 - Qt override
        super().paintEvent(ev)
        self.painted.emit(time.monotonic())
