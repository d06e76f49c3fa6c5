"""Status bar: link status of both boards (connected, frames/s, dropped frames, CRC errors), and the non-modal banner
that says when a board disconnects and when it is back."""

from __future__ import annotations

import time

from PySide6 import QtCore, QtWidgets

OK = "color: #080;"
BAD = "color: #fff; background: #c00; padding: 0 4px;"


class LinkStatus(QtWidgets.QWidget):
    """Two labels in the status bar, one per board; :meth:`update_from` reads the live objects (no blocking)."""

    #: emitted with (board, connected) whenever a board's link changes
    link_changed = QtCore.Signal(str, bool)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.drum = QtWidgets.QLabel("Drum: -")
        self.drum.setObjectName("drum_link")
        self.taxel = QtWidgets.QLabel("Taxels: -")
        self.taxel.setObjectName("taxel_link")
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.drum)
        lay.addSpacing(24)
        lay.addWidget(self.taxel)
        lay.addStretch(1)
        self._state = {"drum": None, "taxel": None}
        self._last = (time.monotonic(), 0)

    def update_from(self, poller, taxels) -> None:
        if poller is None:
            self.drum.setText("Drum: not connected")
            self.drum.setStyleSheet("")
        else:
            ok = poller.ok
            now = time.monotonic()
            dt = now - self._last[0]
            rate = (poller.reads - self._last[1]) / dt if dt > 0 else 0.0
            self._last = (now, poller.reads)
            text = f"Drum: {'connected' if ok else 'NO RESPONSE'}, {rate:.0f} polls/s, {poller.failures} failed"
            self.drum.setText(text)
            self.drum.setStyleSheet(OK if ok else BAD)
            self._set("drum", ok)
        if taxels is None:
            self.taxel.setText("Taxels: not connected")
            self.taxel.setStyleSheet("")
        else:
            s = taxels.stats
            ok = bool(s.connected)
            self.taxel.setText(
                f"Taxels: {'connected' if ok else 'DISCONNECTED'}, {s.frames_per_s:.0f} frames/s, "
                f"{s.frames} frames, {s.dropped} dropped, {s.crc_errors} CRC errors, {s.reconnects} reconnects"
            )
            self.taxel.setStyleSheet(OK if ok else BAD)
            self._set("taxel", ok)

    def _set(self, board: str, ok: bool) -> None:
        if self._state[board] is not None and self._state[board] != ok:
            self.link_changed.emit(board, ok)
        self._state[board] = ok


class Banner(QtWidgets.QFrame):
    """A non-modal message strip above the tabs: red while a board is away, green for a few seconds once back."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.label = QtWidgets.QLabel()
        self.label.setObjectName("banner_text")
        self.label.setWordWrap(True)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(8, 4, 8, 4)
        lay.addWidget(self.label, 1)
        close = QtWidgets.QPushButton("Dismiss")
        close.clicked.connect(self.hide)
        lay.addWidget(close)
        self._timer = QtCore.QTimer(self, singleShot=True)
        self._timer.timeout.connect(self.hide)
        self.hide()

    def show_message(self, text: str, *, error: bool, hide_after_s: float | None = None) -> None:
        self.label.setText(text)
        self.setStyleSheet(
            "QFrame { background: #fdd; border: 1px solid #c00; } QLabel { color: #900; font-weight: bold; }"
            if error
            else "QFrame { background: #dfd; border: 1px solid #080; } QLabel { color: #060; font-weight: bold; }"
        )
        self.show()
        if hide_after_s:
            self._timer.start(int(hide_after_s * 1000))
        else:
            self._timer.stop()

    def on_link_changed(self, board: str, connected: bool) -> None:
        name = {"drum": "Drum controller (Mega)", "taxel": "Taxel board (Uno)"}[board]
        if connected:
            self.show_message(f"{name} reconnected.", error=False, hide_after_s=5)
        else:
            self.show_message(
                f"{name} disconnected - trying to reconnect. Check the USB cable; data from the gap is lost "
                "and counted as dropped frames.",
                error=True,
            )
