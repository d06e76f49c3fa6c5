"""Small layout helpers shared by the panels."""

from __future__ import annotations

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets


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


class FittedText(QtWidgets.QScrollArea):
    """A text shown whole, never cut with "...": wrapped to the widget's width, in the largest font from the app's
    down to :attr:`MIN_PX` whose lines fit the widget's height, and past that scrollable inside it. The text never
    sizes the widget (its layout does: a new text moves nothing); the tooltip has the whole text. ``bold``: in bold;
    ``align``: the text's alignment (top left by default). :attr:`label` is the QLabel showing it."""

    MIN_PX = 9

    def __init__(self, text: str = "", parent: QtWidgets.QWidget | None = None, *, bold: bool = False,
                 align: QtCore.Qt.AlignmentFlag = QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop):
        super().__init__(parent)
        self.label = QtWidgets.QLabel()
        self.label.setTextFormat(QtCore.Qt.TextFormat.PlainText)  # a '<' in an error is text, never markup
        self.label.setWordWrap(True)
        self.label.setAlignment(align)
        self.label.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        if bold:
            font = self.label.font()
            font.setBold(True)
            self.label.setFont(font)
        #: the text's own size (the app's font), px: :meth:`fit` goes down from it
        self.base_px = self.label.fontInfo().pixelSize()
        self.setWidget(self.label)
        self.setWidgetResizable(True)
        self.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        self.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Ignored)
        # see-through (the strip's own background shows), without a style sheet: a widget under one keeps the palette
        # it was polished with (black text after the desktop turned dark)
        self.viewport().setAutoFillBackground(False)
        self.label.setAutoFillBackground(False)
        self._text = ""
        self.setText(text)

    def text(self) -> str:
        """The whole text."""
        return self._text

    def setText(self, text: str) -> None:  # noqa: N802 - Qt style
        if text != self._text:
            self._text = text
            self.setToolTip(text)
            self.fit()

    def fit(self) -> None:
        """Show the whole text, wrapped, in the largest font (from the app's down to :attr:`MIN_PX`) whose lines fit
        the widget's height; a text that does not fit even then scrolls."""
        self.label.setText(self._text)
        width = max(self.viewport().width() - 4, 40)
        height = max(self.viewport().height(), 1)
        font = self.label.font()
        for px in range(max(self.base_px, self.MIN_PX), self.MIN_PX - 1, -1):
            font.setPixelSize(px)
            rect = QtGui.QFontMetrics(font).boundingRect(QtCore.QRect(0, 0, width, 100_000),
                                                         int(QtCore.Qt.TextFlag.TextWordWrap), self._text)
            if rect.height() <= height:
                break
        if font != self.label.font():
            self.label.setFont(font)

    def resizeEvent(self, ev) -> None:  # noqa: N802 - Qt override
        super().resizeEvent(ev)
        if self._text:
            self.fit()


class _PageLayout(QtWidgets.QVBoxLayout):
    """The margin-free layout of one page in :class:`PageTabs`: its height for a width is the page's *smallest*
    (its wrapped labels' lines counted), where a box layout gives the preferred one (the plots' preferred heights
    made a scroll area scroll a page that had room)."""

    def __init__(self, parent: QtWidgets.QWidget):
        super().__init__(parent)
        self.setContentsMargins(0, 0, 0, 0)

    def heightForWidth(self, width: int) -> int:  # noqa: N802 - Qt override
        item = self.itemAt(0)
        page = item.widget() if item is not None else None
        layout = page.layout() if page is not None else None
        if page is None or layout is None:
            return super().heightForWidth(width)
        smallest = page.minimumSizeHint().expandedTo(page.minimumSize()).height()
        return max(layout.totalMinimumHeightForWidth(width), smallest)


class PageTabs(QtWidgets.QTabWidget):
    """A tab widget whose every page lies in a scroll area of its own: a page that needs more room than the window
    gives it scrolls (both ways) instead of setting the window's smallest size (issue 38: at Qt's scale 1.5 a
    1024x700 screen is 683x466 of Qt's pixels), and where the room suffices the page is laid out exactly as without
    it. Pages are added, found and chosen as themselves: :meth:`widget`, :meth:`currentWidget`, :meth:`indexOf` and
    :meth:`setCurrentWidget` see the page, not its scroll area (:meth:`area` gives that)."""

    def add_page(self, page: QtWidgets.QWidget, label: str) -> int:
        """Add ``page`` as the tab ``label`` inside a frameless scroll area; returns its index."""
        # the page sits in a holder whose height for a width is the page's smallest (:class:`_PageLayout`)
        holder = QtWidgets.QWidget()
        _PageLayout(holder).addWidget(page)
        area = QtWidgets.QScrollArea()
        area.setObjectName(f"page_scroll_{self.count()}")
        area.setWidgetResizable(True)
        area.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        area.setWidget(holder)
        return self.addTab(area, label)

    def replace_page(self, index: int, page: QtWidgets.QWidget) -> None:
        """Put ``page`` in place of the page at ``index`` (a page built on first use); the old one is deleted."""
        area = self.area(index)
        holder = area.widget() if area is not None else None
        layout = holder.layout() if holder is not None else None
        old = self.widget(index)
        if area is None or layout is None or old is None:
            raise IndexError(f"no page at {index}")
        layout.removeWidget(old)
        old.hide()
        old.deleteLater()
        layout.addWidget(page)
        if area.isVisible():  # its tab is shown: shown now (not by a queued call); else it shows with its tab
            page.show()

    def area(self, index: int) -> QtWidgets.QScrollArea | None:
        """The scroll area of the page at ``index`` (None: no such tab)."""
        area = super().widget(index)
        return area if isinstance(area, QtWidgets.QScrollArea) and area.objectName().startswith("page_scroll") \
            else None

    def widget(self, index: int) -> QtWidgets.QWidget | None:
        area = self.area(index)
        holder = area.widget() if area is not None else None
        layout = holder.layout() if holder is not None else None
        if layout is None:
            return super().widget(index)
        item = layout.itemAt(0)
        return item.widget() if item is not None else None

    def currentWidget(self) -> QtWidgets.QWidget | None:  # type: ignore[override]  # noqa: N802 - Qt style
        return self.widget(self.currentIndex())

    def indexOf(self, page: QtWidgets.QWidget) -> int:  # noqa: N802 - Qt style
        return next((i for i in range(self.count()) if self.widget(i) is page), super().indexOf(page))

    def setCurrentWidget(self, page: QtWidgets.QWidget) -> None:  # noqa: N802 - Qt style
        index = self.indexOf(page)
        if index >= 0:
            self.setCurrentIndex(index)


def restyle(widget: QtWidgets.QWidget, style: str) -> None:
    """Set ``widget``'s style sheet to ``style`` unless it is that already (Qt re-polishes the widget at every
    ``setStyleSheet``, the same sheet too)."""
    if widget.styleSheet() != style:
        widget.setStyleSheet(style)


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
        self._template = template or text
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred, QtWidgets.QSizePolicy.Policy.Fixed)

    def sizeHint(self) -> QtCore.QSize:  # noqa: N802 - Qt override
        # in the font the text is drawn in (a style sheet's bold, set after this widget was made, included: measured
        # in the plain font, the drum's bold state lost its start at its template's length)
        fm = self.fontMetrics()  # 4 px of margins, 2 more for the text's fractional width
        return QtCore.QSize(fm.horizontalAdvance(self._template) + 6, fm.height() + 2)

    def minimumSizeHint(self) -> QtCore.QSize:  # noqa: N802 - Qt override
        return QtCore.QSize(0, self.sizeHint().height())

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
