"""Small layout helpers shared by the panels."""

from __future__ import annotations

import numpy as np
from PySide6 import QtCore, QtWidgets


def side_panel(layout: QtWidgets.QLayout, width: int) -> QtWidgets.QScrollArea:
    """A left-hand panel of fixed ``width`` (px) holding ``layout``: it never changes width as its texts wrap (so
    clicks never miss), and a short window gets a vertical scroll bar instead of clipped or squashed widgets."""
    layout.setContentsMargins(0, 0, 0, 0)
    inner = QtWidgets.QWidget()
    inner.setLayout(layout)
    area = QtWidgets.QScrollArea()
    area.setWidget(inner)
    area.setWidgetResizable(True)
    area.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
    area.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    area.setFixedWidth(width)
    return area


def keep_room(widget: QtWidgets.QWidget, *, lines: int | None = None) -> None:
    """Keep ``widget``'s room in its layout while it is hidden (and, with ``lines``, a fixed height of that many
    text lines), so the widgets around it never move when it shows or hides or its text grows."""
    sp = widget.sizePolicy()
    sp.setRetainSizeWhenHidden(True)
    widget.setSizePolicy(sp)
    if lines is not None:
        widget.setFixedHeight(lines * widget.fontMetrics().lineSpacing() + 4)


class StatusText(QtWidgets.QWidget):
    """A one-line text that changes often (rates, counters): :meth:`setText` repaints it and nothing else. A QLabel's
    new text asks its layout for room, and the request climbs every parent layout up to the main window (its docks
    animated anew each time) although nothing moves; this widget's size hint is fixed (``template``'s width, one line),
    it takes the width its layout gives it and elides what does not fit (the start of right-aligned text, else the
    end; the tooltip shows the whole text then).
    ``align``: the text's horizontal alignment."""

    def __init__(self, text: str = "", *, template: str = "", align=QtCore.Qt.AlignmentFlag.AlignLeft,
                 parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self._text = text
        self._align = align | QtCore.Qt.AlignmentFlag.AlignVCenter
        fm = self.fontMetrics()
        self._hint = QtCore.QSize(fm.horizontalAdvance(template or text) + 4, fm.height() + 2)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred, QtWidgets.QSizePolicy.Policy.Fixed)

    def sizeHint(self) -> QtCore.QSize:  # noqa: N802 - Qt override
        return QtCore.QSize(self._hint)

    def minimumSizeHint(self) -> QtCore.QSize:  # noqa: N802 - Qt override
        return QtCore.QSize(0, self._hint.height())

    def text(self) -> str:
        return self._text

    def setText(self, text: str) -> None:  # noqa: N802 - Qt style
        if text != self._text:
            self._text = text
            self.update()

    def _shown(self) -> str:
        # right-aligned text loses its start (its end, e.g. the newest counter, stays in view), other text its end
        mode = (QtCore.Qt.TextElideMode.ElideLeft if self._align & QtCore.Qt.AlignmentFlag.AlignRight
                else QtCore.Qt.TextElideMode.ElideRight)
        return self.fontMetrics().elidedText(self._text, mode, max(self.width() - 4, 0))

    def paintEvent(self, ev) -> None:  # noqa: N802 - Qt override
        from PySide6 import QtGui

        p = QtGui.QPainter(self)
        p.setPen(self.palette().color(QtGui.QPalette.ColorRole.WindowText))
        p.drawText(self.rect().adjusted(2, 0, -2, 0), self._align, self._shown())
        p.end()

    def event(self, ev) -> bool:
        if ev.type() == QtCore.QEvent.Type.ToolTip and not self.toolTip() and self._shown() != self._text:
            QtWidgets.QToolTip.showText(ev.globalPos(), self._text, self)
            return True
        return super().event(ev)


def gap_breaks(rows: np.ndarray, *, max_dt: float, time_col: int = 0) -> np.ndarray:
    """``rows`` (n, k) in time order with a NaN row inserted wherever the time (column ``time_col``, s) jumps by
    more than ``max_dt``: a curve drawn with ``connect="finite"`` shows the outage as a gap, not as a straight line
    across it. The NaN row's time is the midpoint of the jump (so the x range still spans the data)."""
    if len(rows) < 2:
        return rows
    t = rows[:, time_col]
    jumps = np.flatnonzero(np.diff(t) > max_dt)
    if not jumps.size:
        return rows
    filler = np.full((len(jumps), rows.shape[1]), np.nan)
    filler[:, time_col] = (t[jumps] + t[jumps + 1]) / 2
    return np.insert(rows, jumps + 1, filler, axis=0)


def add_taxel_numbers(view, rows: int, cols: int, first: int, *, point_size: int = 7) -> list:
    """Write each taxel's channel number (``first`` + row * ``cols`` + col) in the top left corner of its cell of a
    ``rows`` x ``cols`` heat map drawn in ``view`` (a pyqtgraph ViewBox or PlotItem, one unit per cell), on a pale box
    so it reads over any colour. Returns the text items (to show or hide them)."""
    import pyqtgraph as pg
    from PySide6 import QtGui

    font = QtGui.QFont()
    font.setPointSize(point_size)
    items = []
    for r in range(rows):
        for c in range(cols):
            t = pg.TextItem(str(first + r * cols + c), color="k", fill=pg.mkBrush(255, 255, 255, 190), anchor=(0, 0))
            t.setFont(font)
            t.textItem.setCacheMode(QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache)  # drawn once
            t.setPos(c + 0.03, r + 0.03)
            view.addItem(t)
            items.append(t)
    return items
