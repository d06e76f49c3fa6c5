"""Small layout helpers shared by the panels."""

from __future__ import annotations

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
    area.setFrameShape(QtWidgets.QFrame.NoFrame)
    area.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarAlwaysOff)
    area.setFixedWidth(width)
    return area
