"""The main window's top strip: Connect..., the rig source and the drum's state, a protocol run's strip and STOP.

Its height is fixed (STOP's), never in a scroll area, so no message moves anything in it or below it. Where the
strip is too narrow for the source beside the drum's state (Qt's scale 1.5 on a 1024x700 screen: 683 px of Qt's
pixels), it is one line taller, set by the window's width alone: the source then wraps onto two lines, and a run's
state (STOPPED, its reason and what to do) keeps its three lines. The texts are
:class:`rigctl_gui.widgets.FittedText`: shown whole, wrapped, smaller where needed, never cut.
"""

from __future__ import annotations

from PySide6 import QtCore, QtGui, QtWidgets

from rigctl_gui.widgets import FittedText, StatusText

#: a usual source line: where it does not fit beside the drum's state on one line, the strip is narrow (a fixed text:
#: the strip's height follows the window's width, never a message such as a board not responding)
SOURCE_TEMPLATE = "Source: in-process simulated rig - connected"


class TopStrip(QtWidgets.QWidget):
    """The strip of ``connect`` (a button), ``source`` (the rig source), ``drum_state`` (the drum's state in its
    colour), ``run_strip`` (a protocol run's state and prompt, shown during a run) and ``stop`` (STOP, of fixed
    size)."""

    def __init__(self, connect: QtWidgets.QPushButton, source: FittedText, drum_state: StatusText,
                 run_strip: QtWidgets.QWidget, stop: QtWidgets.QPushButton, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("top_strip")
        self.connect_btn, self.source, self.drum_state, self.stop_btn = connect, source, drum_state, stop
        middle = QtWidgets.QVBoxLayout()
        middle.setContentsMargins(0, 0, 0, 0)
        middle.setSpacing(1)
        first = QtWidgets.QHBoxLayout()  # the source and the drum's state (turning, pressing, fault), on every tab
        first.addWidget(source, 1)
        first.addWidget(drum_state, 0, QtCore.Qt.AlignmentFlag.AlignTop)
        # the source takes the strip's height, or two fifths of it beside a run's strip (which takes the rest)
        middle.addLayout(first, 2)
        middle.addWidget(run_strip, 3)
        self._top = top = QtWidgets.QHBoxLayout(self)
        top.setContentsMargins(0, 0, 0, 0)
        top.addWidget(connect, 0, QtCore.Qt.AlignmentFlag.AlignTop)
        top.addLayout(middle, 1)
        top.addWidget(stop, 0, QtCore.Qt.AlignmentFlag.AlignTop)
        small = QtGui.QFont(source.label.font())
        small.setPixelSize(FittedText.MIN_PX)
        #: the height added where the strip is narrow (one line of the smallest text), px
        self.extra_px = QtGui.QFontMetrics(small).lineSpacing()
        self.fit_height()

    def narrow(self) -> bool:
        """Whether a usual source line (:data:`SOURCE_TEMPLATE`, in the source's own font) and the drum's state do
        not fit side by side."""
        top = self._top
        row = self.width() - self.connect_btn.sizeHint().width() - self.stop_btn.width() - 2 * top.spacing()
        font = QtGui.QFont(self.source.label.font())
        font.setPixelSize(self.source.base_px)
        need = QtGui.QFontMetrics(font).horizontalAdvance(SOURCE_TEMPLATE) + 8
        return row < need + self.drum_state.sizeHint().width() + top.spacing()

    def fit_height(self) -> None:
        """STOP's height (and a margin), plus :attr:`extra_px` where the strip is :meth:`narrow`: set by the
        window's width alone, never by a message."""
        height = self.stop_btn.height() + 4 + (self.extra_px if self.narrow() else 0)
        if self.height() != height or self.minimumHeight() != height:
            self.setFixedHeight(height)

    def resizeEvent(self, ev) -> None:  # noqa: N802 - Qt override
        super().resizeEvent(ev)
        self.fit_height()
