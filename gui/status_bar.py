"""Status bar and banners.

The status bar shows both boards' link health on every tab (:class:`LinkStatus`, one
:class:`rigctl.acquisition.link_health.LinkHealth` per board: connected / stalled / lost / reconnected / controller
reset, with polls/s, frames/s and the dropped frames graded against the running protocol's threshold). The banners
(:class:`Banners`) sit in a strip of fixed height above the tabs, one per topic side by side, so a banner appearing or
going never moves a control.
"""

from __future__ import annotations

import time

from PySide6 import QtCore, QtWidgets

from rigctl.acquisition.link_health import LinkEvent, LinkHealth, LinkState, dropped_frames_severity
from rigctl_gui.colours import on_window
from rigctl_gui.widgets import FittedText, restyle

OK = "color: #007700;"  # 5:1 on a light window; made readable on the label's palette where it is shown (_show)
WARN = "color: #000; background: #fc0; padding: 0 4px;"
BAD = "color: #fff; background: #c00; padding: 0 4px;"
SEVERITY_STYLES = {"ok": OK, "warn": WARN, "bad": BAD}

#: the boards by the names the banners and the status bar use
BOARD_NAMES = {"drum": "Drum controller (Mega)", "taxel": "Taxel board (Uno)"}
#: a board is stalled when nothing arrived for this long with its port open, s: the taxel board streams 1000
#: frames/s; the drum status is polled at 10 Hz and a simulated controller may answer up to 2 s late
STALL_AFTER_S = {"drum": 2.5, "taxel": 1.0}
#: "reconnected" / "controller reset" are held (green / red banner) this long before "connected", s
SETTLE_S = 5.0


class LinkStatus(QtWidgets.QWidget):
    """Labels in the status bar, one per board (and the taxel board's dropped frames); :meth:`update_from` reads
    the live objects (no blocking) and feeds each board's :class:`LinkHealth`.

    Each label is short (it shares the bar with the temporary messages); its tooltip has the full counters."""

    #: emitted with ("drum" | "taxel", LinkEvent) whenever a board's link health changes
    health_changed = QtCore.Signal(str, object)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.drum = QtWidgets.QLabel("Drum: -")
        self.drum.setObjectName("drum_link")
        self.taxel = QtWidgets.QLabel("Taxels: -")
        self.taxel.setObjectName("taxel_link")
        self.dropped = QtWidgets.QLabel("")
        self.dropped.setObjectName("dropped_frames")
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.drum)
        lay.addSpacing(16)
        lay.addWidget(self.taxel)
        lay.addSpacing(4)
        lay.addWidget(self.dropped)
        self.health = {b: LinkHealth(BOARD_NAMES[b], stall_after_s=STALL_AFTER_S[b], settle_s=SETTLE_S)
                       for b in ("drum", "taxel")}
        self._last = (time.monotonic(), 0)
        #: dropped frames counted from here (the current trial's start; None: since the stream opened)
        self.dropped_base: int | None = None
        #: the running protocol's max_dropped_frames (None: no trial is being judged)
        self.max_dropped: int | None = None

    @property
    def state(self) -> dict[str, bool | None]:
        """Per board: True (frames / answers arrive), False (stalled, lost or reset), None (not connected)."""
        return {b: (None if h.state == LinkState.NOT_CONNECTED else not h.state.is_problem)
                for b, h in self.health.items()}

    def judge_trial(self, base_dropped: int | None, max_dropped: int | None) -> None:
        """Grade the dropped frames counted since ``base_dropped`` against ``max_dropped`` (a trial of a running
        protocol); ``None, None``: no trial, any loss is shown amber."""
        self.dropped_base, self.max_dropped = base_dropped, max_dropped

    def update_from(self, poller, taxels, now_s: float | None = None) -> None:
        """Show both links' state (every ~0.3 s); a label's text, tooltip and style are set only when they change
        (a style sheet re-polishes the label and a new text relayouts the bar: most ticks change neither)."""
        now = time.monotonic() if now_s is None else now_s
        if poller is None:
            self._observe("drum", now, connected=None)
            _show(self.drum, text="Drum: not connected")
            _show(self.drum, tip="")
            _show(self.drum, style="")
        else:
            st = poller.latest
            state = self._observe("drum", now, connected=bool(poller.ok), progress=poller.reads,
                                  heartbeat=int(st.heartbeat) if st is not None and poller.ok else None)
            dt = now - self._last[0]
            rate = (poller.reads - self._last[1]) / dt if dt > 0 else 0.0
            self._last = (now, poller.reads)
            word = {LinkState.LOST: "NO RESPONSE", LinkState.STALLED: "NO RESPONSE (stalled)",
                    LinkState.CONTROLLER_RESET: "RESET"}.get(state, state.value)
            _show(self.drum, text=f"Drum: {word}, {rate:.0f} polls/s")
            _show(self.drum, tip=f"link: {state.value}\nstatus polls: {poller.reads} read, {poller.failures} "
                                 "failed" + (f"\nlast error: {poller.error}" if poller.error else ""))
            _show(self.drum, style=BAD if state.is_problem else OK)
        if taxels is None:
            self._observe("taxel", now, connected=None)
            _show(self.taxel, text="Taxels: not connected")
            _show(self.taxel, tip="")
            _show(self.taxel, style="")
            _show(self.dropped, text="")
            _show(self.dropped, style="")
            return
        s = taxels.stats
        state = self._observe("taxel", now, connected=bool(s.connected), progress=int(s.frames))
        word = {LinkState.LOST: "DISCONNECTED", LinkState.STALLED: "STALLED"}.get(state, state.value)
        rate = 0.0 if state == LinkState.STALLED else s.frames_per_s
        _show(self.taxel, text=f"Taxels: {word}, {rate:.0f} frames/s,")
        _show(self.taxel, tip=f"link: {state.value}\n{s.frames} frames, {s.dropped} dropped, {s.crc_errors} CRC "
                              f"errors, {s.reconnects} reconnects")
        _show(self.taxel, style=BAD if state.is_problem else OK)
        base = self.dropped_base if self.dropped_base is not None else 0
        lost = max(0, int(s.dropped) - base)
        severity = dropped_frames_severity(lost, self.max_dropped)
        where = "this trial" if self.max_dropped is not None else "since connected"
        _show(self.dropped, text=f"{lost:,} dropped ({where})")
        _show(self.dropped, tip=
            f"taxel frames lost {where}: {lost}"
            + (f"; the protocol keeps a trial with at most {self.max_dropped}" if self.max_dropped is not None
               else "; no trial is being recorded") + f"\n{s.dropped} dropped since the stream opened")
        _show(self.dropped, style=SEVERITY_STYLES[severity])

    def _observe(self, board: str, now: float, **kw) -> LinkState:
        ev = self.health[board].observe(now, **kw)
        if ev is not None:
            self.health_changed.emit(board, ev)
        return self.health[board].state


class Banner(QtWidgets.QFrame):
    """A non-modal message: red for a problem, green for good news (which hides itself after a while). Its text is
    shown whole, wrapped (never cut with "..."): in a smaller font down to :attr:`MIN_PX` when it needs more lines
    than the strip has, and past that scrollable inside the strip (whose height never changes); the tooltip and the
    event log have it too."""

    MIN_PX = FittedText.MIN_PX

    def __init__(self, name: str = "", parent=None):
        super().__init__(parent)
        self.setObjectName(f"banner_{name}" if name else "banner")
        self.text_area = FittedText()  # wrapped, a smaller font when long, past that scrolling in the strip
        self.label = self.text_area.label
        self.label.setObjectName("banner_text")
        self.label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(6, 1, 4, 1)
        lay.addWidget(self.text_area, 1)
        self.close_btn = QtWidgets.QPushButton("Dismiss")
        self.close_btn.clicked.connect(self.hide)
        lay.addWidget(self.close_btn, 0, QtCore.Qt.AlignmentFlag.AlignTop)
        self.error = False
        self.text = ""  # the whole message (the label may show it cut to the strip's lines)
        self._timer = QtCore.QTimer(self, singleShot=True)
        self._timer.timeout.connect(self.hide)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Ignored)
        self.hide()

    def show_message(self, text: str, *, error: bool, hide_after_s: float | None = None) -> None:
        self.error = error
        self.text = text
        self._fit_text()
        self.setToolTip(text)
        frame = f"QFrame#{self.objectName()}"
        self.setStyleSheet(
            f"{frame} {{ background: #fdd; border: 1px solid #c00; }} QLabel {{ color: #900; font-weight: bold; "
            "border: none; }" if error
            else f"{frame} {{ background: #dfd; border: 1px solid #080; }} QLabel {{ color: #060; font-weight: bold; "
            "border: none; }"
        )
        self.show()
        if hide_after_s:
            self._timer.start(int(hide_after_s * 1000))
        else:
            self._timer.stop()

    def _fit_text(self) -> None:
        """Fit :attr:`text` to the strip (:meth:`rigctl_gui.widgets.FittedText.fit`)."""
        self.text_area.setText(self.text)
        self.text_area.fit()


class Banners(QtWidgets.QFrame):
    """The banner strip above the tabs: a fixed height (two lines of text), one banner per topic side by side:
    ``"drum"`` and ``"taxel"`` (link health), ``"fault"`` (a latched controller fault) and ``"app"`` (the app's own
    errors). Each shows and hides on its own (one board's message never overwrites the other's), and the strip keeps
    its height whether none or all are shown, so nothing below it moves."""

    TOPICS = ("drum", "taxel", "fault", "app")
    LINES = 2

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setObjectName("banner_strip")
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(3)
        self.strips = {}
        for t in self.TOPICS:
            self.strips[t] = Banner(t)
            lay.addWidget(self.strips[t], 1)
        fm = self.fontMetrics()
        button_h = self.strips["app"].close_btn.sizeHint().height()
        self.setFixedHeight(max(self.LINES * fm.lineSpacing() + 8, button_h + 4))

    def __getitem__(self, topic: str) -> Banner:
        return self.strips[topic]

    def on_health(self, board: str, event: LinkEvent) -> None:
        """Show a board's link health: red while stalled, lost or reset; green for a while once it is back."""
        name = BOARD_NAMES[board]
        strip = self.strips[board]
        st = event.state
        if st == LinkState.RECONNECTED:
            strip.show_message(f"{name} reconnected.", error=False, hide_after_s=SETTLE_S)
        elif st == LinkState.CONTROLLER_RESET:
            strip.show_message(f"{name} RESET: it restarted (power, brown-out or watchdog) and lost its homing "
                               "and setpoints. Home it before the next run.", error=True)
        elif st == LinkState.STALLED and board == "taxel":
            strip.show_message(f"{name} stalled: no taxel frame for {STALL_AFTER_S['taxel']:g} s although its "
                               "port is open - the live plots show a gap; data from the gap is lost.", error=True)
        elif st in (LinkState.LOST, LinkState.STALLED) and board == "drum":
            strip.show_message(
                f"{name} not responding - trying to reconnect. Check its USB cable and power. While the link is "
                "down STOP cannot reach it: if the drum turns, stop it at the rig.", error=True)
        elif st == LinkState.LOST:
            strip.show_message(
                f"{name} disconnected - trying to reconnect. Check the USB cable; data from the gap is lost "
                "and counted as dropped frames.", error=True)
        elif st == LinkState.NOT_CONNECTED:
            strip.hide()
        elif st == LinkState.CONNECTED and strip.isVisible() and strip.error:
            strip.hide()


def _show(label: QtWidgets.QLabel, *, text: str | None = None, tip: str | None = None, style: str | None = None) -> None:
    """Set what differs of a label's text, tooltip and style sheet (:data:`OK`'s green readable on the label's
    background, a dark palette's too)."""
    if style == OK:
        style = f"color: {on_window('#007700', label)};"
    if text is not None and label.text() != text:
        label.setText(text)
    if tip is not None and label.toolTip() != tip:
        label.setToolTip(tip)
    if style is not None:
        restyle(label, style)

