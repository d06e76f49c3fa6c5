"""Status bar and banners: the link status of both boards (connected, polls/s, frames/s, dropped frames, CRC
errors, reconnects), and the non-modal banners above the tabs: one per board (red while it is away, green for a few
seconds once it is back), one for a latched controller fault, one for the app's own errors."""

from __future__ import annotations

import time

from PySide6 import QtCore, QtWidgets

OK = "color: #080;"
BAD = "color: #fff; background: #c00; padding: 0 4px;"

#: the boards by the names the banners and the status bar use
BOARD_NAMES = {"drum": "Drum controller (Mega)", "taxel": "Taxel board (Uno)"}


class LinkStatus(QtWidgets.QWidget):
    """Two labels in the status bar, one per board; :meth:`update_from` reads the live objects (no blocking).

    Each label is short (it shares the bar with the temporary messages); its tooltip has the full counters."""

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
        lay.addSpacing(16)
        lay.addWidget(self.taxel)
        self.state: dict[str, bool | None] = {"drum": None, "taxel": None}
        self._last = (time.monotonic(), 0)

    def update_from(self, poller, taxels) -> None:
        if poller is None:
            self.drum.setText("Drum: not connected")
            self.drum.setToolTip("")
            self.drum.setStyleSheet("")
            self.state["drum"] = None
        else:
            ok = poller.ok
            now = time.monotonic()
            dt = now - self._last[0]
            rate = (poller.reads - self._last[1]) / dt if dt > 0 else 0.0
            self._last = (now, poller.reads)
            self.drum.setText(f"Drum: {'connected' if ok else 'NO RESPONSE'}, {rate:.0f} polls/s")
            self.drum.setToolTip(f"status polls: {poller.reads} read, {poller.failures} failed"
                                 + (f"\nlast error: {poller.error}" if poller.error else ""))
            self.drum.setStyleSheet(OK if ok else BAD)
            self._set("drum", ok)
        if taxels is None:
            self.taxel.setText("Taxels: not connected")
            self.taxel.setToolTip("")
            self.taxel.setStyleSheet("")
            self.state["taxel"] = None
        else:
            s = taxels.stats
            ok = bool(s.connected)
            self.taxel.setText(f"Taxels: {'connected' if ok else 'DISCONNECTED'}, {s.frames_per_s:.0f} frames/s, "
                               f"{s.dropped} dropped")
            self.taxel.setToolTip(f"{s.frames} frames, {s.dropped} dropped, {s.crc_errors} CRC errors, "
                                  f"{s.reconnects} reconnects")
            self.taxel.setStyleSheet(OK if ok else BAD)
            self._set("taxel", ok)

    def _set(self, board: str, ok: bool) -> None:
        old, self.state[board] = self.state[board], ok
        if old != ok and (old is not None or not ok):  # a board found down at the first look is news too
            self.link_changed.emit(board, ok)


class Banner(QtWidgets.QFrame):
    """A non-modal message strip: red for a problem, green for good news (which hides itself after a while)."""

    def __init__(self, name: str = "", parent=None):
        super().__init__(parent)
        self.setObjectName(f"banner_{name}" if name else "banner")
        self.label = QtWidgets.QLabel()
        self.label.setObjectName("banner_text")
        self.label.setTextFormat(QtCore.Qt.PlainText)  # error text is shown whole, '<' included
        self.label.setWordWrap(True)
        self.label.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(8, 2, 8, 2)
        lay.addWidget(self.label, 1)
        self.close_btn = QtWidgets.QPushButton("Dismiss")
        self.close_btn.clicked.connect(self.hide)
        lay.addWidget(self.close_btn)
        self.error = False
        self._timer = QtCore.QTimer(self, singleShot=True)
        self._timer.timeout.connect(self.hide)
        self.hide()

    def show_message(self, text: str, *, error: bool, hide_after_s: float | None = None) -> None:
        self.error = error
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


class Banners(QtWidgets.QWidget):
    """The banners above the tabs, one strip per topic: ``"drum"`` and ``"taxel"`` (link lost / back), ``"fault"``
    (a latched controller fault) and ``"app"`` (the app's own errors); each shows and hides on its own, so one
    board's message never overwrites the other's."""

    TOPICS = ("drum", "taxel", "fault", "app")

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(2)
        self.strips = {}
        for t in self.TOPICS:
            self.strips[t] = Banner(t)
            lay.addWidget(self.strips[t])

    def __getitem__(self, topic: str) -> Banner:
        return self.strips[topic]

    def on_link_changed(self, board: str, connected: bool) -> None:
        name = BOARD_NAMES[board]
        if connected:
            self.strips[board].show_message(f"{name} reconnected.", error=False, hide_after_s=5)
        elif board == "drum":
            self.strips[board].show_message(
                f"{name} not responding - trying to reconnect. Check its USB cable and power. While the link is "
                "down STOP cannot reach it: if the drum turns, stop it at the rig.", error=True)
        else:
            self.strips[board].show_message(
                f"{name} disconnected - trying to reconnect. Check the USB cable; data from the gap is lost "
                "and counted as dropped frames.", error=True)
