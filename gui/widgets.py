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
    area.setFrameShape(QtWidgets.QFrame.NoFrame)
    area.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarAlwaysOff)
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
