"""Every message in the window: the event log panel (the app's own messages and the library's stdlib ``logging``
records), the guard that shows an unhandled exception in the window instead of losing it on the console, and the
plain-text helpers that keep an error's text whole (a QLabel in rich-text mode cuts ``"(> 0 and <= 150)"`` at the
first ``<``).

Records may come from any thread (the protocol runner, the drum poll, the stream reader): they go into a thread-safe
queue and the GUI thread drains it from its refresh timer (:meth:`EventLog.drain`), so no worker touches a widget.
"""

from __future__ import annotations

import html
import logging
import queue
import sys
import threading
import time
import traceback
from collections.abc import Callable

from PySide6 import QtCore, QtGui, QtWidgets

from rigctl.core.errors import describe_error
from rigctl_gui.colours import on_window, readable

#: colours of the log levels in the panel; info lines take the palette's text colour (a fixed black was black on
#: near-black with a dark palette), the others these hues made readable on the log's background
#: (:func:`rigctl_gui.colours.readable`)
LEVEL_COLOURS: dict[int, str | None] = {logging.DEBUG: "#888", logging.INFO: None, logging.WARNING: "#d80",
                                        logging.ERROR: "#e33", logging.CRITICAL: "#e33"}
#: the panel keeps this many lines (older ones scroll away)
MAX_LINES = 2000


def escaped(text: object) -> str:
    """``text`` safe to put inside rich text (``<`` and ``&`` shown as typed, never taken as markup)."""
    return html.escape(str(text), quote=False)


def set_plain(label: QtWidgets.QLabel, text: str, *, error: bool = False, colour: str | None = None) -> None:
    """Show ``text`` in ``label`` as plain text (never cut at a ``<``), red when ``error``."""
    label.setTextFormat(QtCore.Qt.TextFormat.PlainText)
    label.setText(str(text))
    label.setStyleSheet(f"color: {on_window(colour or '#c00', label)};" if (error or colour) else "")


class _QueueHandler(logging.Handler):
    """A logging handler that queues records for the GUI thread (any thread may log)."""

    def __init__(self, q: queue.SimpleQueue, level: int):
        super().__init__(level)
        self.q = q

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.q.put((record.created, record.levelno, record.name, record.getMessage()))
        except Exception:  # noqa: BLE001 - a logging handler never raises
            self.handleError(record)


class EventLog(QtWidgets.QWidget):
    """The event log panel: time, level, source and text of every message, newest at the bottom.

    :meth:`add` is for the GUI thread; :meth:`post` may be called from any thread. The library's records (logger
    ``rigctl`` and its children, INFO and above) arrive through :meth:`attach_logging`.
    """

    #: emitted (in the GUI thread, from :meth:`drain`) for every WARNING-or-worse message: (level, source, text)
    problem = QtCore.Signal(int, str, str)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.view = QtWidgets.QPlainTextEdit()
        self.view.setObjectName("event_log")
        self.view.setReadOnly(True)
        self.view.setMaximumBlockCount(MAX_LINES)
        self.view.setLineWrapMode(QtWidgets.QPlainTextEdit.NoWrap)
        self.view.setMinimumHeight(40)  # two lines: the window stays usable when short (1024x686)
        f = QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.FixedFont)
        self.view.setFont(f)
        self.level = QtWidgets.QComboBox()
        self.level.addItems(["info", "warnings and errors"])
        self.level.setToolTip("Which messages the log shows (everything is kept)")
        self.level.currentIndexChanged.connect(self._refilter)
        clear = QtWidgets.QPushButton("Clear")
        clear.clicked.connect(self.clear)
        side = QtWidgets.QVBoxLayout()
        side.setContentsMargins(0, 0, 0, 0)
        side.addWidget(self.level)
        side.addWidget(clear)
        side.addStretch(1)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(4, 0, 4, 2)
        lay.addWidget(self.view, 1)
        lay.addLayout(side)
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self.entries: list[tuple[float, int, str, str]] = []
        # follow the newest line unless the operator scrolled up to read: decided by where the operator left the
        # scroll bar, and kept when the range changes later (a long line adds a horizontal scroll bar after the
        # text is laid out, which shortens the view and moved the end away from a bottom judged at append time)
        self._follow = True
        self._following = False
        bar = self.view.verticalScrollBar()
        bar.valueChanged.connect(self._scrolled)
        bar.rangeChanged.connect(self._range_changed)
        self._handler: logging.Handler | None = None

    # ------------------------------------------------------------------------------------------------------
    def attach_logging(self, logger_name: str = "rigctl", level: int = logging.INFO) -> None:
        """Show the records of ``logger_name`` (and its children) at ``level`` and above."""
        self._handler = _QueueHandler(self._q, level)
        lg = logging.getLogger(logger_name)
        lg.addHandler(self._handler)
        self._old_level = lg.level
        if lg.getEffectiveLevel() > level:
            lg.setLevel(level)

    def detach_logging(self, logger_name: str = "rigctl") -> None:
        if self._handler is not None:
            lg = logging.getLogger(logger_name)
            lg.removeHandler(self._handler)
            lg.setLevel(self._old_level)
            self._handler = None

    def post(self, level: int, source: str, text: str) -> None:
        """Queue a message from any thread (shown at the next :meth:`drain`)."""
        self._q.put((time.time(), int(level), source, str(text)))

    def add(self, level: int, source: str, text: str) -> None:
        """Show a message now (GUI thread)."""
        self.post(level, source, text)
        self.drain()

    def drain(self) -> int:
        """Show the queued messages (GUI thread; called by the main window's timer). Returns how many."""
        n = 0
        while True:
            try:
                entry = self._q.get_nowait()
            except queue.Empty:
                if n and self._follow:
                    bar = self.view.verticalScrollBar()
                    bar.setValue(bar.maximum())
                return n
            n += 1
            self.entries.append(entry)
            del self.entries[:-MAX_LINES]
            if self._shown(entry):
                self.view.appendHtml(self._line(entry))
            if entry[1] >= logging.WARNING:
                self.problem.emit(entry[1], entry[2], entry[3])

    def _scrolled(self, value: int) -> None:
        if not self._following:
            self._follow = value >= self.view.verticalScrollBar().maximum() - 2

    def _range_changed(self, _lo: int, hi: int) -> None:
        if self._follow:
            self._following = True
            self.view.verticalScrollBar().setValue(hi)
            self._following = False

    def text(self) -> str:
        """Everything shown, as plain text (tests, copy)."""
        return self.view.toPlainText()

    def clear(self) -> None:
        self.entries.clear()
        self.view.clear()

    def _shown(self, entry) -> bool:
        return entry[1] >= (logging.WARNING if self.level.currentIndex() == 1 else logging.INFO)

    def _refilter(self) -> None:
        self.view.clear()
        for e in self.entries:
            if self._shown(e):
                self.view.appendHtml(self._line(e))

    def _line(self, entry) -> str:
        t, level, source, text = entry
        stamp = time.strftime("%H:%M:%S", time.localtime(t))
        name = logging.getLevelName(level).lower()
        base = self.view.palette().color(QtGui.QPalette.ColorRole.Base)  # each colour readable on the log's own
        colour = LEVEL_COLOURS.get(level)
        body = escaped(text).replace("\n", "<br>&nbsp;&nbsp;")
        style = f" style='color:{readable(colour, base)}'" if colour else ""
        return (f"<span style='color:{readable('#888', base)}'>{stamp}</span> <span{style}><b>{name}</b> "
                f"{escaped(source)}: {body}</span>")


class ExceptionGuard:
    """Shows an exception no code caught (in a Qt slot, a timer callback or a worker thread) in the window: the
    event log gets the traceback and ``show(text)`` (the main window's error banner) the one-line message; the app
    keeps running. Installed as ``sys.excepthook`` and ``threading.excepthook``; :meth:`uninstall` restores them.
    """

    def __init__(self, log: EventLog, show: Callable[[str], None]):
        self.log = log
        self.show = show
        self._lines: queue.SimpleQueue = queue.SimpleQueue()
        self._prev = (sys.excepthook, threading.excepthook)
        self.count = 0

    def install(self) -> "ExceptionGuard":
        sys.excepthook = self._hook
        threading.excepthook = self._thread_hook
        return self

    def uninstall(self) -> None:
        if sys.excepthook == self._hook:
            sys.excepthook = self._prev[0]
        if threading.excepthook == self._thread_hook:
            threading.excepthook = self._prev[1]

    def _hook(self, etype, value, tb) -> None:
        if issubclass(etype, KeyboardInterrupt):
            self._prev[0](etype, value, tb)
            return
        self._report(etype, value, tb, where="the app")

    def _thread_hook(self, args) -> None:
        if args.exc_type is SystemExit:
            return
        name = args.thread.name if args.thread is not None else "a worker thread"
        self._report(args.exc_type, args.exc_value, args.exc_traceback, where=f"thread {name}")

    def _report(self, etype, value, tb, *, where: str) -> None:
        self.count += 1
        one_line = describe_error(value) if isinstance(value, BaseException) else etype.__name__
        full = "".join(traceback.format_exception(etype, value, tb)).rstrip()
        print(full, file=sys.__stderr__)  # the console keeps it too
        self.log.post(logging.ERROR, where, f"unexpected error: {full}")
        self._lines.put(f"Unexpected error in {where}: {one_line} (the event log has the details; the app "
                        "carries on)")

    def drain(self) -> None:
        """Show the queued errors (GUI thread)."""
        while True:
            try:
                text = self._lines.get_nowait()
            except queue.Empty:
                return
            self.show(text)
