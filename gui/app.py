"""The main window and the application entry point.

``python -m rigctl_gui.app [--drum-port P --taxel-port P] [--replay PATH] [--screenshot PATH --quit-after S] [--tab NAME]``
(also ``rigctl gui``). With no ports the app starts on the simulated rig.

The window fits the screen it opens on (a saved size is restored only if it fits). Its top strip, of fixed height
and outside any scroll area, holds Connect, the source, the run strip (a protocol run's state and operator prompt,
seen from every tab) and the big STOP button, which acts on the first click even while a menu or a drop-down is
open, and on an Esc that no popup, dialog or widget takes (:mod:`rigctl_gui.guards`; every dialog is non-modal:
:mod:`rigctl_gui.dialogs`). STOP stops a protocol run, resumable; Abort asks. The rig's monitor (the library's
status poll, watchdog feed and dead man's switch) reaches the window as events (:mod:`rigctl_gui.rig_events`). Below it a
banner strip of fixed height (one banner per board, for faults and for errors: a banner never moves a control),
one tab per panel, the event log (the app's messages and the library's logging records) and a status bar with both
boards' link health (:mod:`rigctl.acquisition.link_health`). One QTimer pulls from the worker threads at the GUI's
own pace. While a protocol run owns the rig (running, paused or stopped) manual motion, calibration and Connect are
disabled.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import sys
import threading
import time
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import shiboken6
from PySide6 import QtCore, QtGui, QtWidgets

from rigctl.core.faults import FaultSpecError, parse_faults
from rigctl.operations import DEADMAN_TIMEOUT_S
from rigctl_gui.colours import on_window
from rigctl_gui.connect_dialog import source_problem
from rigctl_gui.dialogs import ask, show_dialog
from rigctl_gui.frame_clock import FrameClock
from rigctl_gui.guards import WheelGuard, install_guards
from rigctl_gui.messages import EventLog, ExceptionGuard
from rigctl_gui.workers import (
    CommandExecutor,
    Job,
    LiveEncoder,
    RigSource,
    job_server_state,
    open_rig,
    start_job_server,
)

if TYPE_CHECKING:
    from rigctl.operations import RigMonitor
    from rigctl_gui.analysis_tab import AnalysisTab
    from rigctl_gui.connect_dialog import ConnectDialog
    from rigctl_gui.live_view import LiveView
    from rigctl_gui.rig_events import RigEvents

#: the frame cap: the app's clock ticks (and the visible live view redraws) at most this often, per s, and this often
#: on average while the event loop keeps up (:class:`rigctl_gui.frame_clock.FrameClock`); 30 frames/s is smooth for 2 s
#: of scrolling traces without drawing (and paying for) frames nobody needs (issue 26: < 20 % of a core). ``rigctl gui
#: --max-fps`` sets it
MAX_FPS = 30.0
#: the range ``--max-fps`` accepts, frames/s
FPS_RANGE = (1.0, 120.0)
TAB_NAMES = ("control", "live", "protocol", "analysis", "calibration", "classify", "handheld")
#: the live plots are marked stale when no taxel frame has arrived for this long, s
STALE_AFTER_S = 1.0
#: the window's size on a screen with room for it (px); a smaller screen gets its available area
PREFERRED_SIZE = (1400, 900)
#: the smallest screen the window is laid out for (px): STOP and every tab fit
MIN_SCREEN = (1024, 600)
#: why the manual controls are disabled while a protocol run owns the rig
RUN_LOCK_REASON = ("a protocol run owns the rig (running, paused or stopped). Abort it on the Protocol tab "
                   "to get the manual controls back")
#: why Connect is disabled while a handheld block owns the rig
HANDHELD_LOCK_REASON = "a handheld block owns the rig (running or stopped). Abort it on the Handheld tab first"


def configure_pyqtgraph() -> None:
    """White plots, no antialiasing (faster software rendering under Xvfb/offscreen)."""
    import pyqtgraph as pg

    pg.setConfigOptions(antialias=False, background="w", foreground="k")


def make_settings() -> QtCore.QSettings:
    """The app's QSettings (INI format under the user scope; tests point it at a temporary directory)."""
    return QtCore.QSettings(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope, "rigctl", "gui")


def sensor_layout(handle):
    """The :class:`rigctl.core.sensor.SensorLayout` of an open rig: its taxel stream's (from the board's identify
    reply), else the rig's, else the paper's 3x3x2 at 1 kHz."""
    from rigctl.core.sensor import PAPER_SENSOR

    return (getattr(handle.taxels, "layout", None) or handle.control.layout or PAPER_SENSOR)


def open_rig_keeping_faults(source: RigSource, host_config_path: str | None = None):
    """Open ``source``, moving nothing (the Home action is the start); a fault the drum controller latches is left
    latched for the operator to see and acknowledge (:data:`rigctl.operations.Home.UNLESS_FAULTED`). Returns the
    :class:`rigctl_gui.workers.RigHandle`; raises what :func:`rigctl_gui.workers.open_rig` raises."""
    from rigctl.operations import Home

    return open_rig(source, host_config_path=host_config_path, home=Home.UNLESS_FAULTED)


#: the rigs a STOP reaches, by name (the window's own, and the attached ``rigctl serve``'s)
LOCAL_RIG = "this PC's rig"
SERVER_RIG = "the server's rig"
#: how long STOP is sent again to an attached server that has not answered, s (each try waits the client's timeout)
SERVER_STOP_WAIT_S = 30.0


class StopOutcome(NamedTuple):
    """What one STOP did on one rig: ``rig`` (:data:`LOCAL_RIG`, :data:`SERVER_RIG`), ``outcome`` ("stopped",
    "waiting": no answer yet, "no answer", "failed") and ``detail`` (words)."""

    rig: str
    outcome: str
    detail: str = ""


class MainWindow(QtWidgets.QMainWindow):
    """The rigctl main window. ``source=None`` reads the last source from QSettings (simulated rig by default)."""

    #: how long the GUI thread may not answer while the rig moves before the library stops it, s (the dead man's
    #: switch, :class:`rigctl.operations.RigMonitor`)
    deadman_s: float = DEADMAN_TIMEOUT_S
    #: emitted once, on the GUI thread, right after the Analysis tab is built (:attr:`analysis`: its first show or use)
    analysis_built = QtCore.Signal()

    def __init__(self, source: RigSource | None = None, *, autoconnect: bool = True, max_fps: float = MAX_FPS):
        super().__init__()
        from rigctl_gui.connect_dialog import ConnectDialog, load_source, save_source
        from rigctl_gui.status_bar import Banners, LinkStatus

        self._ConnectDialog, self._save_source = ConnectDialog, save_source
        self.settings = make_settings()
        self.source = source or load_source(self.settings)
        self.handle = None
        self._doctor = None  # the doctor dialog (Rig > Doctor...), made on first use
        self.poller: RigMonitor | None = None  # the open rig's monitor (status poll, watchdog feed, events)
        self.rig_events: RigEvents | None = None  # the subscription and the GUI thread's heartbeat
        self.fault_dialog: Any = None  # the latched-fault dialog (rigctl_gui.fault_dialog), while one is open
        self._latch_seen: Any = None  # the latch the dialog was last opened for (opened once per latch)
        self.commands: CommandExecutor | None = None
        self.encoder: LiveEncoder | None = None
        #: what the Live view shows once built (taxels, encoder, layout, the ring's frame count when connected: its
        #: traces start there, as when it was built at connect)
        self._live_source: tuple[Any, LiveEncoder, Any, int] | None = None
        self._live_ring: Any = None  # the taxel stream's ring buffer when the sensor side was built
        self._connect_job: Job | None = None
        self._connect_dialog: ConnectDialog | None = None
        self._close_confirmed = False
        self._run_lock: str | None = None
        self._faults = 0
        self._server_dialog: Any = None  # the window attached to a rigctl serve, once opened
        self._stop_results: list[StopOutcome] = []  # each STOP's outcome per rig (the worker threads append)
        self._banner_holds: tuple[str, Any] | None = None  # the app banner's text and the condition it holds while
        self.setWindowTitle("rigctl - tactile texture rig")

        # --- messages first: everything below may report into them ---
        self.events = EventLog()
        self.events.attach_logging("rigctl")
        self.banners = Banners()
        self.banner = self.banners["app"]  # the app's own errors (connect failures, unexpected errors)
        self.events.problem.connect(self._on_problem)
        self.guard = ExceptionGuard(self.events, lambda text: self.banner.show_message(text, error=True)).install()

        self._build_top_bar()

        self._build_tabs()
        self._build_layout()

        self.links = LinkStatus()
        self.links.health_changed.connect(self.banners.on_health)
        self.links.health_changed.connect(self._on_health)
        self.statusBar().addPermanentWidget(self.links)  # no stretch: the temporary messages keep their room
        self._build_menus()

        state = self.settings.value("ui/state")
        if state is not None:
            self.restoreState(state)
        geom = self.settings.value("ui/geometry")
        if geom is not None:
            self.restoreGeometry(geom)
        else:
            self.resize(*PREFERRED_SIZE)
        self.fit_to_screen()
        self.stop_guard, self.wheel_guard = install_guards(self, self.stop_btn, self.emergency_stop)
        self._log_user_actions()

        self._tick = 0
        self.clock = FrameClock(max_fps, self.refresh, self)
        self.timer = self.clock.timer  # its timeout is each tick
        period_s = self.clock.period_s
        self._slow_every = max(1, round(0.12 / period_s))  # the other tabs, events and faults: every ~0.12 s
        self._health_every = max(1, round(0.3 / period_s))  # link health: every ~0.3 s
        self.clock.start()
        self._update_source_label("not connected")
        if autoconnect:
            self.connect_source(self.source)

    def _build_tabs(self) -> None:
        """The tabs (rig control, live view, protocol, analysis, calibration, real-time classification,
        handheld) and the stale-data marker over the live view."""
        from rigctl_gui.calibration_tab import CalibrationTab
        from rigctl_gui.classify_view import ClassifyView
        from rigctl_gui.control_panel import ControlPanel
        from rigctl_gui.handheld_tab import HandheldTab
        from rigctl_gui.protocol_tab import ProtocolTab
        from rigctl_gui.widgets import PageTabs

        self.tabs = PageTabs()  # each page scrolls when the window is smaller than it (a small screen at 1.5x)
        self.control = ControlPanel()
        self.control.refused.connect(lambda text: self.notify(text, level=logging.WARNING, source="rig control"))
        self.control.acted.connect(lambda text: self.notify(text, source="rig control"))
        self.control.question.connect(self._ask)
        self.control.acknowledge_wanted.connect(self.open_fault_dialog)
        self._live: LiveView | None = None  # built on first use (:attr:`live`)
        live_page = QtWidgets.QWidget()  # its place until then
        self.protocol = ProtocolTab(self)
        self._analysis: AnalysisTab | None = None  # built on first use (:attr:`analysis`)
        analysis_page = QtWidgets.QWidget()  # its place until then
        self.calibration = CalibrationTab(self)
        self.classify = ClassifyView(self)
        self.handheld = HandheldTab(self)
        for w, name in (
            (self.control, "Rig control"),
            (live_page, "Live view"),
            (self.protocol, "Protocol"),
            (analysis_page, "Analysis"),
            (self.calibration, "Calibration"),
            (self.classify, "Real-time classification"),
            (self.handheld, "Handheld"),
        ):
            self.tabs.add_page(w, name)
        self._analysis_index = self.tabs.indexOf(analysis_page)
        self._live_index = self.tabs.indexOf(live_page)
        self.tabs.currentChanged.connect(self._build_shown_tab)
        self.tabs.setCurrentIndex(int(str(self.settings.value("ui/tab", 0))))

    @property
    def live(self) -> LiveView:
        """The Live view (:class:`rigctl_gui.live_view.LiveView`), built the first time it is shown or asked for (its
        plots were ~40 % of the window's start-up, and a session that never looks at it does not pay for them), with
        the stale-data marker over it; it shows the connected rig's stream from then on. Asked for, it is built (or
        its staged build finished) at once; shown, it is built one plot per pass of the event loop (:meth:`_build_live`)."""
        if self._live is None:
            self._build_live(staged=False)
        elif self._live.building:
            self._live.finish_build()
        assert self._live is not None
        return self._live

    def _build_live(self, *, staged: bool) -> None:
        """Make the Live view; ``staged``: its plots one per pass of the event loop (the first showing while the
        drum turns held the GUI thread 0.5-1.2 s beside two CPU hogs: issue 51), shown once built."""
        from rigctl_gui.live_view import LiveView

        view = self._live = LiveView(staged=staged)
        self.tabs.replace_page(self._live_index, view)
        # a marker over the live view when its plots stop moving (no taxel frame for STALE_AFTER_S)
        self.stale_label = QtWidgets.QLabel(view)
        self.stale_label.setObjectName("stale_marker")
        self.stale_label.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.stale_label.setStyleSheet("background: #c00; color: white; font-weight: bold; padding: 4px 10px;")
        self.stale_label.hide()
        if staged:
            view.built.connect(self._live_built)
        else:
            self._live_built()

    def _live_built(self) -> None:
        """The Live view's plots exist: it shows the connected rig's stream (unless attached meanwhile)."""
        view = self._live
        if view is None:
            return
        if self._live_source is not None and view.buffer is None:
            view.attach(*self._live_source)
        self._guard_new_widgets(view)
        QtWidgets.QApplication.sendPostedEvents(None, QtCore.QEvent.Type.LayoutRequest)

    @property
    def analysis(self) -> AnalysisTab:
        """The Analysis tab (:class:`rigctl_gui.analysis_tab.AnalysisTab`), built the first time it is shown or
        asked for: its plots were ~40 % of the window's start-up, and most sessions at the rig never open it. Asked
        for, it is built (or its staged build finished) at once; shown, one plot per pass of the event loop."""
        if self._analysis is None:
            self._build_analysis(staged=False)
        elif self._analysis.building:
            self._analysis.finish_build()
        assert self._analysis is not None
        return self._analysis

    def _build_analysis(self, *, staged: bool) -> None:
        from rigctl_gui.analysis_tab import AnalysisTab

        tab = AnalysisTab(self, staged=staged)
        self.tabs.replace_page(self._analysis_index, tab)
        self._analysis = tab
        if staged:
            tab.built.connect(self._analysis_done)
        else:
            self._analysis_done()

    def _analysis_done(self) -> None:
        """The Analysis tab's views exist: the window's guards on them, laid out, :attr:`analysis_built`."""
        tab = self._analysis
        if tab is None:
            return
        self._guard_new_widgets(tab)
        # laid out now, as the window's other pages were before it was shown (not an event loop pass later)
        QtWidgets.QApplication.sendPostedEvents(None, QtCore.QEvent.Type.LayoutRequest)
        self.analysis_built.emit()

    def _build_shown_tab(self, index: int) -> None:
        if index == self._analysis_index and self._analysis is None:
            self._build_analysis(staged=True)  # built on first show, a plot at a time
        elif index == self._live_index and self._live is None:
            self._build_live(staged=True)  # built on first show, a plot at a time
        if self.encoder is not None:  # the live encoder runs while its spikes are shown (it catches up on showing)
            self.encoder.set_active(self._live_shown())

    def _live_shown(self) -> bool:
        """True when the Live view is the tab shown (its spike rasters are drawn)."""
        return self._live is not None and self.tabs.currentWidget() is self._live

    def _build_top_bar(self) -> None:
        """The top bar's widgets: the rig source, Connect... and the big STOP."""
        from rigctl_gui.widgets import FittedText, StatusText

        # the whole source, wrapped or in a smaller font where the strip is narrow (a small screen at 1.5x), never cut
        self.source_label = FittedText(bold=True)
        self.source_label.setObjectName("source")

        # room for the usual line; a longer one loses its start (right-aligned), never its end ("fault latched")
        self.drum_state = StatusText("Drum: not connected", template="Drum: Seeking force 120 mm/s, 1000 g",
                                     align=QtCore.Qt.AlignmentFlag.AlignRight)
        self.drum_state.setObjectName("drum_state")
        self.drum_state.setStyleSheet("font-weight: bold;")
        self.connect_btn = QtWidgets.QPushButton("Connect...")
        self.connect_btn.setToolTip("Choose the rig: the simulated rig, two serial ports, or a replay")
        self.connect_btn.clicked.connect(self.choose_source)
        self.stop_btn = QtWidgets.QPushButton("STOP")
        self.stop_btn.setObjectName("big_stop")
        self.stop_btn.setToolTip("Safe stop: stop the drum, back the actuator off and stop a protocol run, resumable "
                                 "(Esc when no drop-down or dialog takes it; one click works with a menu or a "
                                 "drop-down open)")
        self.stop_btn.setMinimumSize(160, 48)
        self.stop_btn.setStyleSheet(
            "QPushButton { background: #d00; color: white; font-size: 20px; font-weight: bold; border-radius: 6px; }"
            "QPushButton:pressed { background: #900; }"
        )
        self.stop_btn.clicked.connect(self.emergency_stop)
        # Esc = STOP in the main window: rigctl_gui.guards.StopGuard (also with a menu or a drop-down open)
        self.stop_btn.setFixedSize(160, 48)

    def _show_drum_state(self) -> None:
        """The drum's state in the top strip (seen from every tab), in its state's colour."""
        from PySide6 import QtGui

        from rigctl_gui.control_panel import drum_summary

        if self.handle is not None and not self.handle.control.has_drum:
            text, colour = "Drum: none (handheld rig)", "#555"
        else:
            latch = self.handle.control.latch if self.handle is not None else None
            text, colour = drum_summary(self.poller, latch.label if latch is not None else None)
        colour = on_window(colour, self)  # the state's colour, readable on this window's palette
        pal = self.drum_state.palette()
        if pal.color(QtGui.QPalette.ColorRole.WindowText).name() != colour or self.drum_state.text() != text:
            pal.setColor(QtGui.QPalette.ColorRole.WindowText, QtGui.QColor(colour))
            self.drum_state.setPalette(pal)
            self.drum_state.setText(text)

    def _build_layout(self) -> None:
        """The top strip (source, run strip, STOP: fixed height, never in a scroll area; the run strip shows and hides
        inside it), the banners, the tabs and the event log dock."""
        from rigctl_gui.top_strip import TopStrip

        self.top_strip = TopStrip(self.connect_btn, self.source_label, self.drum_state, self.protocol.run_strip,
                                  self.stop_btn)

        central = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(central)
        lay.setContentsMargins(6, 4, 6, 2)
        lay.setSpacing(3)
        lay.addWidget(self.top_strip)
        lay.addWidget(self.banners)
        lay.addWidget(self.tabs, 1)
        self.setCentralWidget(central)

        self.log_dock = QtWidgets.QDockWidget("Event log", self)
        self.log_dock.setObjectName("event_log_dock")
        self.log_dock.setWidget(self.events)
        feature = QtWidgets.QDockWidget.DockWidgetFeature
        self.log_dock.setFeatures(feature.DockWidgetClosable | feature.DockWidgetMovable
                                  | feature.DockWidgetFloatable)
        self.addDockWidget(QtCore.Qt.DockWidgetArea.BottomDockWidgetArea, self.log_dock)
        self.resizeDocks([self.log_dock], [110], QtCore.Qt.Orientation.Vertical)

    # ------------------------------------------------------------------------------------------------------
    # the screen
    # ------------------------------------------------------------------------------------------------------
    def frame_margins(self) -> tuple[int, int]:
        """The window manager's frame around the window (width, height, px): measured once the window is shown,
        else a typical title bar and border (none offscreen)."""
        fg, g = self.frameGeometry(), self.geometry()
        dw, dh = fg.width() - g.width(), fg.height() - g.height()
        if self.isVisible() and dh > 0:
            return dw, dh
        if QtGui.QGuiApplication.platformName() in ("offscreen", "minimal"):
            return 0, 0
        return max(dw, 8), max(dh, 40)

    def fit_to_screen(self) -> bool:
        """Keep the whole window, frame included, inside the available area of its screen (the screen less panels
        and docks): shrink it and move it in when it does not fit (a first start on a small screen, a size saved on
        a larger one). Returns True when it changed anything."""
        if self.isMaximized() or self.isFullScreen():
            return False
        screen = self.screen() or QtGui.QGuiApplication.primaryScreen()
        if screen is None:
            return False
        avail = screen.availableGeometry()
        dw, dh = self.frame_margins()
        w = min(self.width(), avail.width() - dw)
        h = min(self.height(), avail.height() - dh)
        changed = (w, h) != (self.width(), self.height())
        if changed:
            self.resize(w, h)
        fg = self.frameGeometry()
        x = min(max(fg.x(), avail.x()), avail.x() + avail.width() - (w + dw))
        y = min(max(fg.y(), avail.y()), avail.y() + avail.height() - (h + dh))
        if (x, y) != (fg.x(), fg.y()):
            self.move(x, y)
            changed = True
        return changed

    def showEvent(self, ev):  # noqa: N802 - Qt override
        super().showEvent(ev)
        if not getattr(self, "_fitted_shown", False):
            self._fitted_shown = True
            # the window manager's frame is known only once it has framed the window: fit again then
            QtCore.QTimer.singleShot(300, self.fit_to_screen)
            QtCore.QTimer.singleShot(1500, self.fit_to_screen)

    # ------------------------------------------------------------------------------------------------------
    # menus
    # ------------------------------------------------------------------------------------------------------
    def _build_menus(self) -> None:
        """File, Rig, Run, View, Help. An action that mirrors a button is enabled exactly when the button is
        (:meth:`_sync_actions`), so the interlock covers the menus too."""
        mb = self.menuBar()
        self._mirrored: list[tuple[QtGui.QAction, QtWidgets.QAbstractButton]] = []
        K = QtGui.QKeySequence

        def act(menu, text, slot, shortcut=None, button=None, tip=""):
            a = menu.addAction(text)
            a.triggered.connect(lambda _=False: slot())
            if shortcut is not None:
                a.setShortcut(K(shortcut))
            if tip:
                a.setStatusTip(tip)
            if button is not None:
                self._mirrored.append((a, button))
            return a

        m = mb.addMenu("&File")
        act(m, "&Open protocol...", self._open_protocol, K.StandardKey.Open, self.protocol.open_btn)
        act(m, "Open session for &analysis...", self._open_analysis, "Ctrl+Shift+O")
        act(m, "Choose &output session file...", self.protocol._browse_output, "Ctrl+Shift+S")
        m.addSeparator()
        act(m, "&Quit", self.close, K.StandardKey.Quit)

        m = mb.addMenu("&Rig")
        self.act_connect = act(m, "&Connect...", self.choose_source, "Ctrl+K", self.connect_btn)
        act(m, "STOP (safe stop)", self.emergency_stop, tip="Esc in the window when no popup or dialog takes it")
        m.addSeparator()
        b = self.control.buttons
        act(m, "&Press", lambda: self.control.command("press"), "Ctrl+P", b["press"])
        act(m, "R&un drum", lambda: self.control.command("run"), "Ctrl+Shift+R", b["run"])
        act(m, "Stop &drum", lambda: self.control.command("stop_drum"), "Ctrl+.", b["stop_drum"])
        act(m, "&Tare", lambda: self.control.command("tare"), None, b["tare"])
        act(m, "&Home", lambda: self.control.command("home"), None, b["home"])
        act(m, "Clear &fault / acknowledge...", self.open_fault_dialog,
            tip="name the latched fault and acknowledge it with a reason (written into the session's event log)")
        act(m, "&Mount plate", self.control.mount_plate, "Ctrl+M", self.control.mount_btn)
        m.addSeparator()
        act(m, "&Doctor...", self.open_doctor, tip="bring-up checks on the connected rig (rigctl doctor)")
        act(m, "Attach to a rigctl &server...", self.open_server,
            tip="a rigctl serve owns the rig: its status and run queue, queue / pause / resume / abort, STOP")

        m = mb.addMenu("R&un")
        p = self.protocol
        act(m, "&Start protocol", p.start, "Ctrl+R", p.start_btn)
        act(m, "&Pause", p.pause, "Ctrl+Shift+P", p.pause_btn)
        act(m, "Res&ume", p.resume, "Ctrl+Shift+U", p.resume_btn)
        act(m, "&Abort...", p.ask_abort, "Ctrl+Shift+A", p.abort_btn)

        m = mb.addMenu("&View")
        for i in range(self.tabs.count()):
            act(m, self.tabs.tabText(i), lambda i=i: self.tabs.setCurrentIndex(i), f"Ctrl+{i + 1}")
        m.addSeparator()
        log_act = self.log_dock.toggleViewAction()
        log_act.setShortcut(K("Ctrl+L"))
        m.addAction(log_act)
        act(m, "&Full screen", lambda: self.showNormal() if self.isFullScreen() else self.showFullScreen(),
            K.StandardKey.FullScreen)

        m = mb.addMenu("&Help")
        act(m, "&Keyboard shortcuts", self._show_shortcuts, K.StandardKey.HelpContents)
        act(m, "&About rigctl", self._show_about)

    def _ask(self, title: str, text: str, yes: str, no: str, on_yes) -> None:
        """A non-modal question for a panel (its ``question`` signal)."""
        self._question = ask(self, title, text, yes, no, on_yes)

    def _log_user_actions(self) -> None:
        """Every button pressed and menu item chosen is written to the event log (what the operator did, in
        order, beside what the rig did)."""
        self._log_buttons(self)
        for menu in self.menuBar().findChildren(QtWidgets.QMenu):
            for a in menu.actions():
                if a.text() and not a.isSeparator():
                    a.triggered.connect(lambda _=False, a=a, m=menu: self.events.add(
                        logging.INFO, "user", f"menu {m.title().replace('&', '')} > {a.text().replace('&', '')}"))

    def _log_buttons(self, root: QtWidgets.QWidget) -> None:
        """Every button under ``root`` writes its presses to the event log."""
        for b in root.findChildren(QtWidgets.QAbstractButton):
            if b is self.stop_btn or isinstance(b, (QtWidgets.QCheckBox, QtWidgets.QRadioButton)) or not b.text():
                continue
            b.clicked.connect(lambda _=False, b=b: self.events.add(
                logging.INFO, "user", f"pressed {b.text().replace('&', '')!r}"))

    def _guard_new_widgets(self, page: QtWidgets.QWidget) -> None:
        """A page built after the window (:attr:`analysis`) gets what the window's own widgets got at start: the
        wheel guard's focus policy on its spin and combo boxes, and its button presses in the event log."""
        if hasattr(self, "wheel_guard"):  # (asked for while the window is built: the window's own pass covers it)
            WheelGuard.protect(page)
            self._log_buttons(page)

    def _open_protocol(self) -> None:
        self.tabs.setCurrentWidget(self.protocol)
        self.protocol._browse_protocol()

    def _open_analysis(self) -> None:
        self.tabs.setCurrentWidget(self.analysis)
        btn = getattr(self.analysis, "open_btn", None)
        if btn is not None:
            btn.click()

    def _sync_actions(self) -> None:
        for a, b in self._mirrored:
            on = b.isEnabled()
            if a.isEnabled() != on:  # (the tooltip changes with it: the reason a control is disabled)
                a.setEnabled(on)
                a.setToolTip(b.toolTip())

    def _show_shortcuts(self) -> None:
        lines = ["Esc: STOP (safe stop; a run stops, resumable) in the window when nothing else takes it (Esc "
                 "closing a menu or a drop-down only closes it; in a dialog Esc only closes the dialog)"]
        for menu in self.menuBar().findChildren(QtWidgets.QMenu):
            for a in menu.actions():
                if not a.shortcut().isEmpty():
                    lines.append(f"{a.shortcut().toString(QtGui.QKeySequence.SequenceFormat.NativeText)}: {a.text().replace('&', '')}")
        box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Information, "Keyboard shortcuts", "\n".join(lines),
                                    QtWidgets.QMessageBox.StandardButton.Close, self)
        box.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        show_dialog(box)

    def open_doctor(self) -> None:
        """Rig > Doctor...: the bring-up checks on the connected rig (:mod:`rigctl_gui.doctor_dialog`)."""
        from rigctl_gui.doctor_dialog import DoctorDialog

        if self.handle is None:
            self.notify("Doctor: connect a rig first (Rig > Connect...)", level=logging.WARNING, source="doctor")
            return
        if self._doctor is None or self._doctor.control is not self.handle.control:
            self._doctor = DoctorDialog(self.handle.control, self)
        self._doctor.show()
        self._doctor.raise_()

    def _show_about(self) -> None:
        import rigctl

        box = QtWidgets.QMessageBox(
            QtWidgets.QMessageBox.Icon.Information, "About rigctl",
            f"rigctl {getattr(rigctl, '__version__', '')}: control, recording and neuromorphic analysis for a "
            "tactile texture drum rig.\nThe app's guide: docs/gui.md.", QtWidgets.QMessageBox.StandardButton.Close, self)
        box.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        show_dialog(box)

    # ------------------------------------------------------------------------------------------------------
    # messages
    # ------------------------------------------------------------------------------------------------------
    def notify(self, text: str, *, level: int = logging.INFO, source: str = "app", timeout_s: float = 8.0) -> None:
        """Tell the operator: the event log always, the status bar for a few seconds, and the error banner (seen
        from every tab) for errors."""
        self.events.add(level, source, text)
        self.statusBar().showMessage(text, int(timeout_s * 1000))

    #: sources whose errors have their own banner (faults, links, the dead man's switch; a latch opens the fault
    #: dialog) or are shown by the exception guard
    OWN_BANNER = ("drum controller", "link", "dead man's switch", "rigctl.acquisition.safety")

    def _on_problem(self, level: int, source: str, text: str) -> None:
        """Errors (the library's included) go to the error banner, seen from every tab."""
        if level >= logging.ERROR and source not in self.OWN_BANNER and not text.startswith("unexpected error"):
            shown = f"{source}: {text}" if source not in ("app",) else text
            self.banner.show_message(shown, error=True)
            if source == "protocol" and "waits on a latched fault" in text:  # until acknowledged, or the run ends
                self._banner_while(shown, lambda: self.protocol.running and self.protocol.latched is not None)

    def _banner_while(self, text: str, holds: Any) -> None:
        """The app banner now shows ``text``, true while ``holds()`` is: it goes by itself once its condition has
        (checked every slow tick: :meth:`_clear_stale_banner`), unless another message replaced it."""
        self._banner_holds = (text, holds)

    def _clear_stale_banner(self) -> None:
        """Hide the app banner whose condition is over ("STOPPED by the library" once the rig moves again, "waits
        on a latched fault" once acknowledged or the run ended)."""
        held = self._banner_holds
        if held is None:
            return
        text, holds = held
        if not self.banner.isVisible() or self.banner.text != text:  # closed, or another message took its place
            self._banner_holds = None
            return
        if not holds():
            self.banner.hide()
            self._banner_holds = None

    def _on_health(self, board: str, event) -> None:
        """A board's link health changed: the event log says so (the banner and the status bar show it), the
        header names a board that is not responding."""
        from rigctl.acquisition.link_health import LinkState

        if event.state == LinkState.NOT_CONNECTED:
            return
        level = logging.WARNING if event.state.is_problem else logging.INFO
        self.events.add(level, "link", event.text)
        self._update_source_label(None)

    # ------------------------------------------------------------------------------------------------------
    # connection
    # ------------------------------------------------------------------------------------------------------
    def choose_source(self) -> QtWidgets.QDialog | None:
        """Show the (non-modal) Connect dialog; accepting it connects to the chosen source."""
        if self._run_lock:
            self.notify(f"Connect is disabled: {self._run_lock}", level=logging.WARNING)
            return None
        if self._connect_dialog is not None:
            self._connect_dialog.raise_()
            self._connect_dialog.activateWindow()
            return self._connect_dialog
        dlg = self._connect_dialog = self._ConnectDialog(self.source, self)

        def accepted():
            if self._run_lock:  # a run started while the dialog was open: the run keeps the rig
                self.notify(f"not connected to another rig: {self._run_lock}", level=logging.WARNING)
                return
            source = dlg.source()
            if self.drum_turning():
                self._connect_question = ask(
                    self, "The drum is turning",
                    f"The drum is turning. Connecting to the {source.label()} first stops this rig safely (drum to "
                    "rest, actuator backed off) and closes it.", "Stop the drum and connect", "Cancel",
                    self._connect_pending)
                self._pending_source = source
                return
            self.connect_source(source)

        dlg.destroyed.connect(lambda *_: setattr(self, "_connect_dialog", None))
        dlg.finished.connect(lambda *_: setattr(self, "_connect_dialog", None))
        return show_dialog(dlg, accepted)

    def _connect_pending(self) -> None:
        source, self._pending_source = getattr(self, "_pending_source", None), None
        if source is not None:
            self.connect_source(source)

    def connect_source(self, source: RigSource) -> None:
        """Open ``source`` in a worker thread (the boards take ~2 s to boot); :meth:`refresh` finishes the job."""
        problem = source_problem(source)
        if problem:
            self.banner.show_message(f"Could not open the {source.label()}: {problem}", error=True)
            self.events.add(logging.ERROR, "connect", problem)
            return
        self.disconnect_rig()
        self.source = source
        self._save_source(self.settings, source)
        cfg_path = self.rig_config_path()
        self._connect_job = Job(lambda job: open_rig_keeping_faults(source, cfg_path), name="connect")
        self._connect_job.start()
        self._update_source_label("connecting...")
        self.events.add(logging.INFO, "connect", f"opening the {source.label()}")
        self.connect_btn.setEnabled(False)

    def _finish_connect(self) -> None:
        job, self._connect_job = self._connect_job, None
        if job is None:  # no connect under way
            return
        self.connect_btn.setEnabled(True)
        if job.error:
            self._update_source_label("not connected")
            self.banner.show_message(f"Could not open the {self.source.label()}: {job.error}", error=True)
            self.events.add(logging.ERROR, "connect", f"could not open the {self.source.label()}: {job.error}")
            return
        h = self.handle = job.result
        from rigctl_gui.rig_events import RigEvents

        self.poller = h.control.monitor  # started by the library; the GUI only reads it and listens
        self.rig_events = RigEvents(self.poller, self, timeout_s=self.deadman_s)  # the GUI thread's heartbeat
        self.rig_events.happened.connect(self._on_rig_event)
        if self.poller.latest is not None:
            self._show_faults(int(self.poller.latest.faults))
        self.commands = CommandExecutor(h.control)
        if getattr(h.taxels, "ring", None) is not None:  # the handheld rig's sensor model keeps no live stream
            self._attach_sensor(h, sensor_layout(h))
        if h.control.has_drum:
            self.control.attach(h.drum, self.poller, self.commands, h.control)
        else:  # the handheld rig: an operator moves the finger; its blocks run on the Handheld tab
            self.control.state_label.setText("No drum: the handheld rig (the Handheld tab runs its blocks)")
        self.protocol.take_rig_defaults(h.control)
        self._update_source_label("connected")
        self.events.add(logging.INFO, "connect", f"connected to the {self.source.label()}")
        # everything long-lived exists now: move it out of the cyclic GC's reach, so full collections (which
        # otherwise traverse every Qt wrapper and pyqtgraph item, ~150 ms) do not stall the display
        gc.collect()
        gc.freeze()
        self.banner.hide()

    def disconnect_rig(self) -> None:
        """Abort a run, stop the rig safely (the library's safe stop), close it, then stop the workers."""
        self.protocol.abort_and_wait()
        self.handheld.abort_and_wait()
        if self.rig_events is not None:  # the face leaves in order: no heartbeat left to go silent
            self.rig_events.close()
            self.rig_events = None
        self.control.detach()
        self._live_source = self._live_ring = None
        if self._live is not None:
            self._live.detach()
        self.calibration.detach()
        if self.handle is not None:
            try:
                self.handle.close()  # safe stop first: the controller's watchdog never sees a silent host
            except Exception as exc:  # noqa: BLE001
                self.notify(f"closing the rig: {exc}", level=logging.ERROR, source="connect")
        if self.commands is not None:
            self.commands.close()
        if self.encoder is not None:
            self.encoder.stop()
            if self.encoder.ident is not None:  # (an encoder never started, after a failed connect, has no thread)
                self.encoder.join(timeout=5)  # never leave a numba call running at interpreter exit
        self.handle = self.poller = self.commands = self.encoder = None
        self._faults = 0
        self._latch_seen = None
        if self.fault_dialog is not None and shiboken6.isValid(self.fault_dialog):
            self.fault_dialog.close()
        self.fault_dialog = None
        self.banners["fault"].hide()
        for board in ("drum", "taxel"):
            self.banners[board].hide()

    def rig_config_path(self) -> str | None:
        """The rig config file (calibration) from QSettings ``rig/config_path``; None = the library's default."""
        return str(self.settings.value("rig/config_path", "")) or None

    def _update_source_label(self, state: str | None) -> None:
        """``state``: "connecting...", "not connected", "connected"; None = from the boards' links now."""
        if state is None or (state == "connected" and self.handle is not None):
            st = self.links.state
            down = [n for n, b in (("drum controller", "drum"), ("taxel board", "taxel")) if st.get(b) is False]
            state = f"connected, {' and '.join(down)} not responding" if down else "connected"
        self._source_state = state
        self.source_label.setText(f"Source: {self.source.label()} - {state}")

    # ------------------------------------------------------------------------------------------------------
    def emergency_stop(self) -> None:
        """STOP: the library's STOP (:meth:`rigctl.operations.RigControl.stop`: a protocol run hears it first and
        stops, resumable; then drum to rest, actuator backed off, three tries) at once on a fresh thread (never
        queued behind other commands), and the attached server's ``POST /stop`` on another. It never aborts a run
        (Abort asks). Its outcome is shown per rig, named ("this PC's rig", "the server's rig"): stopped, no answer
        yet (a slow reply is not a failure: STOP is sent again until it is answered), or failed (the error banner:
        stop the rig by hand)."""
        reason = "the operator pressed STOP"
        self.protocol.request_stop(reason)
        if self._doctor is not None and self._doctor.running:
            self._doctor.cancel()
        server = self._server_dialog.client if self._server_dialog is not None else None
        if server is not None:  # attached to a rigctl serve: it owns its rig, STOP goes there too, at once
            threading.Thread(target=lambda: self._server_stop(server), name="server-stop", daemon=True).start()
            self.notify(f"STOP sent to {SERVER_RIG} ({server.url})", level=logging.WARNING, source="STOP")
        h = self.handle
        if h is None and server is not None:
            return
        if h is None:
            self.notify("STOP: no rig connected", level=logging.WARNING, source="STOP")
            return
        results = self._stop_results

        def work():
            try:
                ok = bool(h.control.stop(reason))
            except Exception as exc:  # noqa: BLE001 - said in the window
                results.append(StopOutcome(LOCAL_RIG, "failed", str(exc)))
            else:
                results.append(StopOutcome(LOCAL_RIG, "stopped" if ok else "failed",
                                           "" if ok else "could not send STOP to its drum controller"))

        threading.Thread(target=work, name="drum-stop", daemon=True).start()
        if not h.control.has_drum:  # the handheld rig: nothing moves by itself, the operator lifts the finger
            self.notify("the handheld block stopped, the operator lifts the finger (Resume continues at the next cue)"
                        if self.handheld.block_running else "nothing was running (the handheld rig has no drum)",
                        level=logging.WARNING, source="STOP")
            return
        self.notify(f"STOP sent to {LOCAL_RIG}: drum to rest, actuator backing off" + (
            ", the run stopped (Resume continues it)" if self.protocol.running else ""),
            level=logging.WARNING, source="STOP")

    def _server_stop(self, server) -> None:
        """``POST /stop`` to the attached server until it answers (worker thread): a reply slower than the
        client's timeout is "no answer yet" and STOP is sent again (it is idempotent) for up to
        :data:`SERVER_STOP_WAIT_S`; a refusal or an unreachable server is a failure."""
        import httpx

        from rigctl.server.client import ServerError

        t0 = time.monotonic()
        told = False
        while True:
            try:
                reply = server.stop()
            except ServerError as exc:
                waited = time.monotonic() - t0
                timed_out = exc.status == 0 and isinstance(exc.__context__, httpx.TimeoutException)
                if not timed_out:
                    self._stop_results.append(StopOutcome(SERVER_RIG, "failed", str(exc)))
                    return
                if waited >= SERVER_STOP_WAIT_S:
                    self._stop_results.append(StopOutcome(SERVER_RIG, "no answer", f"after {waited:.0f} s"))
                    return
                if not told:
                    told = True
                    self._stop_results.append(StopOutcome(SERVER_RIG, "waiting", f"after {waited:.1f} s"))
                continue
            ok = bool(reply.get("acknowledged"))
            self._stop_results.append(StopOutcome(
                SERVER_RIG, "stopped" if ok else "failed",
                f"after {time.monotonic() - t0:.1f} s" if ok else "the server could not send STOP to its drum "
                "controller"))
            return

    def open_server(self) -> None:
        """The window attaching to a running ``rigctl serve`` (:class:`rigctl_gui.server_dialog.ServerDialog`)."""
        if self._server_dialog is None:
            from rigctl_gui.server_dialog import ServerDialog

            def loaded():
                proto = self.protocol.protocol
                return getattr(proto, "source", None) if proto is not None else None

            self._server_dialog = ServerDialog(self, protocol_source=loaded)
        self._server_dialog.show()
        self._server_dialog.raise_()

    def _drain_stop_results(self) -> None:
        """Each STOP outcome into the window, per rig: stopped (status bar, event log), no answer yet (a warning:
        not a failure), no answer at all or failed (the error banner: stop the rig by hand)."""
        while self._stop_results:
            r = self._stop_results.pop(0)
            if r.outcome == "stopped":
                text = f"STOP: {r.rig} stopped (its drum controller acknowledged STOP{', ' + r.detail if r.detail else ''})"
                self.events.add(logging.INFO, "STOP", text)
                self.statusBar().showMessage(text, 5000)
            elif r.outcome == "waiting":
                text = (f"STOP: {r.rig}: no answer yet ({r.detail}; STOP sent again until it answers, for up to "
                        f"{SERVER_STOP_WAIT_S:.0f} s)")
                self.events.add(logging.WARNING, "STOP", text)
                self.statusBar().showMessage(text, 8000)
            elif r.outcome == "no answer":
                text = (f"STOP: {r.rig} has not answered ({r.detail}): it may still move. Look at it and stop it by "
                        "hand if it does")
                self.events.add(logging.CRITICAL, "STOP", text)
                self.banner.show_message(text + ".", error=True)
            else:
                text = f"STOP FAILED on {r.rig}: {r.detail}: stop the rig by hand"
                self.events.add(logging.CRITICAL, "STOP", text)
                self.banner.show_message(text + ".", error=True)

    def refresh(self) -> None:
        """One tick of the GUI's own clock: pull from the workers, redraw what is visible."""
        self._tick += 1
        if self._connect_job is not None and self._connect_job.done:
            self._finish_connect()
        if self.commands is not None:
            while not self.commands.results.empty():
                name, ok, text = self.commands.results.get()
                self.control.show_result(ok, text)
                self.notify(text, level=logging.INFO if ok else logging.ERROR, source="rig control")
        self._drain_stop_results()
        current = self.tabs.currentWidget()
        if self._live is not None and current is self._live:
            self._live.refresh()
        if self._tick % self._slow_every == 0:
            if current is self.control:
                self.control.refresh()
            self.protocol.refresh()
            if self._analysis is not None:
                self._analysis.refresh()
            self.calibration.refresh()
            self.classify.refresh()
            self.events.drain()
            self.guard.drain()
            self.apply_run_lock()
            self._sync_actions()
            self._check_latch()
            self._show_drum_state()
            self._clear_stale_banner()
        if self._tick % self._health_every == 0:  # link health every 0.3 s: a stalled board is shown within ~1.3 s
            self._judge_dropped_frames()
            self.links.update_from(*self._links())
        if self._tick % 20 == 0:
            self._update_stale(current)
            self.follow_sensor()

    # ------------------------------------------------------------------------------------------------------
    # the run owns the rig; faults; stale plots
    # ------------------------------------------------------------------------------------------------------
    def _judge_dropped_frames(self) -> None:
        """While a protocol records a trial, the status bar grades that trial's dropped frames against the
        protocol's ``max_dropped_frames``; otherwise it shows the frames dropped since connecting."""
        p = self.protocol
        base = p.trial_dropped_base if p.running and p._current is not None else None
        limit = getattr(p.protocol, "max_dropped_frames", None) if base is not None else None
        self.links.judge_trial(base, limit)

    def _links(self) -> tuple[Any, Any]:
        """What the status bar's link labels read: the drum's monitor (None without a drum: the handheld rig) and the
        taxel stream (None when it keeps no link statistics: the handheld rig's sensor model)."""
        h = self.handle
        if h is None:
            return None, None
        return (self.poller if h.control.has_drum else None,
                h.taxels if getattr(h.taxels, "stats", None) is not None else None)

    def _rig_moving(self) -> bool:
        """True when the drum controller last reported the force loop engaged or the drum running (the rig was
        started again; a drum still slowing down after a STOP is not)."""
        from rigctl.core.drum import DrumState

        st = self.poller.latest if self.poller is not None and self.poller.ok else None
        return st is not None and int(st.state) in (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED,
                                                    DrumState.RUNNING)

    def drum_turning(self) -> bool:
        """True when the drum controller last reported the drum running or moving (> 0.5 mm/s)."""
        from rigctl.devices.wire import DrumState

        st = self.poller.latest if self.poller is not None and self.poller.ok else None
        return st is not None and (int(st.state) == DrumState.RUNNING or abs(st.speed_mm_s) > 0.5)

    def apply_run_lock(self) -> None:
        """While a protocol run owns the rig (running or paused): manual motion, calibration and Connect disabled,
        their tooltips saying why. Re-applied every tick (another panel may re-enable its buttons)."""
        reason = (RUN_LOCK_REASON if self.protocol.running else
                  HANDHELD_LOCK_REASON if self.handheld.block_running else None)
        changed = reason != self._run_lock
        self._run_lock = reason
        self.control.set_run_lock(reason)
        cal = self.calibration
        for b in (self.connect_btn, cal.loadcell_btn, cal.norm_btn, cal.from_session_btn):
            if b.property("normal_tip") is None:
                b.setProperty("normal_tip", b.toolTip())
            if reason:
                b.setEnabled(False)
                b.setToolTip(f"Disabled: {reason}")
            elif changed:
                b.setToolTip(b.property("normal_tip"))
        if changed and not reason:
            self.connect_btn.setEnabled(self._connect_job is None)
            cal.from_session_btn.setEnabled(True)
            cal._enable(cal.handle is not None)

    def _on_rig_event(self, ev) -> None:
        """An event of the rig's monitor (:class:`rigctl.operations.RigEvent`, on the GUI thread): latched faults
        raise the fault banner, and the dead man's switch says why it stopped the rig."""
        if ev.kind == "faults" and ev.status is not None:
            self._show_faults(int(ev.status.faults))
        elif ev.kind == "deadman":
            if "answers again" in ev.message:
                self.events.add(logging.INFO, "dead man's switch", ev.message)
                return
            text = f"STOPPED by the library: {ev.message}. Resume the run (or command the rig) when ready."
            self.banner.show_message(text, error=True)
            self._banner_while(text, lambda: not self._rig_moving())  # until the rig presses or turns again
            self.events.add(logging.ERROR, "dead man's switch", ev.message)
            self.statusBar().showMessage(text, 15000)

    def _latch_key(self) -> Any:
        """What is latched now: the library's latch (the safety table's state; the rig's monitor latches every
        controller fault it reads), or None. The window derives no latch of its own (issue 76: it merged the
        controller's fault bits in and debounced them for 2 s after an acknowledgement)."""
        h = self.handle
        return None if h is None else h.control.latch

    def _check_latch(self) -> None:
        """A new latched fault opens the fault dialog (once per latch: Later closes it, Rig > Acknowledge fault...
        opens it again); an open dialog follows the controller's status (the e-stop's contact)."""
        key = self._latch_key()
        if key is not None and key != self._latch_seen:
            self._latch_seen = key
            self.open_fault_dialog()
        elif key is None:
            self._latch_seen = None
        dlg = self.fault_dialog
        if dlg is not None and shiboken6.isValid(dlg) and dlg.isVisible() and self.poller is not None \
                and self.poller.ok:
            dlg.update_from(self.poller.latest)

    def open_fault_dialog(self) -> QtWidgets.QDialog | None:
        """The latched-fault dialog (:class:`rigctl_gui.fault_dialog.FaultDialog`, non-modal) for the fault latched
        now; None (said in the status bar) when nothing is latched."""
        from rigctl_gui.fault_dialog import FaultDialog

        if self.handle is None or self._latch_key() is None:
            self.notify("no latched fault to acknowledge")
            return None
        if self.fault_dialog is not None and shiboken6.isValid(self.fault_dialog) and self.fault_dialog.isVisible():
            self.fault_dialog.raise_()
            return self.fault_dialog
        dlg = self.fault_dialog = FaultDialog(self.handle.control, self._faults, self, log=self.events.add)
        dlg.destroyed.connect(lambda *_: setattr(self, "fault_dialog", None))  # deleted when closed
        if self.poller is not None and self.poller.ok:
            dlg.update_from(self.poller.latest)
        return show_dialog(dlg)

    def _show_faults(self, faults: int) -> None:
        """A latched controller fault raises the fault banner with its meaning; only Clear fault (the operator)
        clears it on the controller, and the banner goes when the controller reports it clear."""
        from rigctl_gui.control_panel import fault_meaning

        if faults == self._faults:
            return
        self._faults = faults
        if faults:
            text = (f"Drum controller FAULT (latched). {fault_meaning(faults)} The drum is stopped. Fix the cause, "
                    "then press Clear fault on the Rig control tab (the fault dialog: give a reason).")
            self.banners["fault"].show_message(text, error=True)
            self.events.add(logging.ERROR, "drum controller", text)
        else:
            self.banners["fault"].hide()
            self.events.add(logging.INFO, "drum controller", "faults cleared")

    def _update_stale(self, current) -> None:
        """Mark the live view stale when its plots stopped moving (no taxel frame for :data:`STALE_AFTER_S`)."""
        taxels = self.handle.taxels if self.handle is not None else None
        stale = None
        if taxels is not None and self._live is not None and current is self._live:
            ring = taxels.ring
            total = ring.total
            now = time.monotonic()
            last = getattr(self, "_last_frames", None)
            if last is None or last[0] != total or last[2] is not ring:
                self._last_frames = (total, now, ring)
            elif now - last[1] >= STALE_AFTER_S:
                stale = (f"STALE: no taxel frame for {now - last[1]:.0f} s - the plots are frozen "
                         f"({'taxel board disconnected' if not taxels.stats.connected else 'stream silent'})")
        if stale:
            self.stale_label.setText(stale)
            self.stale_label.adjustSize()
            self.stale_label.move(max(0, (self.live.width() - self.stale_label.width()) // 2),
                                  max(0, (self.live.height() - self.stale_label.height()) // 2))
            self.stale_label.raise_()
            self.stale_label.show()
        elif self._live is not None:
            self.stale_label.hide()

    def follow_sensor(self) -> bool:
        """Rebuild the live view, its encoder and the calibration tab when the taxel board now reports another
        sensor than they were built for (another board plugged in: the stream has a new layout and ring buffer).
        Returns True when they were rebuilt."""
        h, enc = self.handle, self.encoder
        if h is None or enc is None:
            return False
        layout = sensor_layout(h)
        buf = self._live.buffer if self._live is not None else None
        ring = buf.ring if buf is not None else self._live_ring  # what the Live view shows (or will, once built)
        if layout == enc.layout and (ring is None or ring is h.taxels.ring):
            return False
        enc.stop()  # its thread ends at its next poll; it reads the old ring only
        self._attach_sensor(h, layout)
        self.banner.show_message(f"The taxel board now reports another sensor: {layout.describe()}. The live view "
                                 "and calibration follow it.", error=False, hide_after_s=10)
        return True

    def _attach_sensor(self, h, layout) -> None:
        """Build the sensor side for ``layout``: the calibration tab, a started live encoder (with the stored
        normalisation when it fits the layout) and the live view."""
        self.calibration.attach(h, layout)
        self.encoder = LiveEncoder(h.taxels, normaliser=self.calibration.taxel_range(h.control, layout), layout=layout,
                                   active=self._live_shown())
        self.encoder.start()
        self._live_source, self._live_ring = (h.taxels, self.encoder, layout, h.taxels.ring.total), h.taxels.ring
        if self._live is not None:
            self._live.attach(*self._live_source)

    def closeEvent(self, ev):  # noqa: N802 - Qt override
        if self.handheld.block_running and not self._close_confirmed:
            ev.ignore()
            self._close_question = ask(
                self, "A handheld block is running",
                f"The handheld {self.handheld.block} block is running. Closing the window aborts it: the finished "
                "scans stay in its file.", "Abort the block and close", "Keep running", self._close_after_abort)
            return
        if self.protocol.running and not self._close_confirmed:
            # the run owns the rig: ask first (non-modal, STOP stays usable), then stop it safely and close
            ev.ignore()
            self._close_question = ask(
                self, "A protocol is running",
                f"The protocol {self.protocol.protocol_name()} is running. Closing the window aborts it: the rig "
                "stops safely and the finished trials stay in the session file (resume it later).",
                "Abort the run and close", "Keep running", self._close_after_abort)
            return
        if self.drum_turning() and not self._close_confirmed:
            ev.ignore()
            self._close_question = ask(
                self, "The drum is turning",
                "The drum is turning. Quitting stops the rig safely (drum to rest, actuator backed off) and closes "
                "the app.", "Stop the drum and quit", "Keep running", self._close_after_abort)
            return
        self.settings.setValue("ui/geometry", self.saveGeometry())
        self.settings.setValue("ui/state", self.saveState())
        self.settings.setValue("ui/tab", self.tabs.currentIndex())
        self.clock.stop()
        self.disconnect_rig()
        self.events.detach_logging("rigctl")
        self.guard.uninstall()
        self.stop_guard.uninstall()
        self.wheel_guard.uninstall()
        super().closeEvent(ev)

    def _close_after_abort(self) -> None:
        self._close_confirmed = True
        self.protocol.request_abort()
        self.handheld.request_abort()
        self.close()


# ----------------------------------------------------------------------------------------------------------------
def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="rigctl gui", description="The rigctl desktop app.")
    ap.add_argument("--drum-port", help="serial port of the drum controller (Mega)")
    ap.add_argument("--taxel-port", help="serial port of the taxel streamer (Uno)")
    ap.add_argument("--sim", action="store_true", help="the simulated rig (default: the source last chosen in the "
                    "Connect dialog, the simulated rig the first time)")
    ap.add_argument("--hil", action="store_true", help="the rig's own firmware under simavr (hardware-in-the-loop; "
                    "needs the AVR toolchain and simavr)")
    ap.add_argument("--hil-bootloaders", action="store_true", help="--hil with the boards' real bootloaders: each "
                    "connect resets them, as USB does on a bench")
    ap.add_argument("--replay", metavar="PATH",
                    help="stream recorded taxel signals through the simulated rig: a session file (at its own rate "
                    "and sensor layout) or a FabricSlide directory")
    ap.add_argument("--screenshot", metavar="PATH", help="save a PNG of the main window before quitting")
    ap.add_argument("--quit-after", type=float, metavar="SECONDS", help="quit after this many seconds")
    ap.add_argument("--tab", choices=TAB_NAMES, help="tab to show first")
    ap.add_argument("--run", action="store_true", help="press and run the drum at the setpoints once connected")
    ap.add_argument("--texture", metavar="LABEL", help="mount this texture plate (a label of the rig's texture set, "
                    "A-P on the paper's rig) once connected")
    ap.add_argument("--stats-out", metavar="PATH", help="append display statistics (JSON lines) every second "
                    "(benchmarks/bench_gui.py)")
    ap.add_argument("--max-fps", type=float, default=MAX_FPS, metavar="N",
                    help=f"frame cap of the live view, frames/s ({FPS_RANGE[0]:g}-{FPS_RANGE[1]:g}; default "
                         f"{MAX_FPS:g})")
    ap.add_argument("--inject", action="append", default=[], metavar="FAULT@T[+D]",
                    help="inject a fault into the simulated rig (repeatable; rigctl gui --help, docs/safety.md)")
    args = ap.parse_args(argv)
    try:
        args.inject = parse_faults(args.inject)
    except FaultSpecError as exc:
        ap.error(str(exc))
    if not FPS_RANGE[0] <= args.max_fps <= FPS_RANGE[1]:
        ap.error(f"--max-fps must be {FPS_RANGE[0]:g}-{FPS_RANGE[1]:g} frames/s, got {args.max_fps:g}")
    return args


def source_from_args(args) -> RigSource | None:
    """The rig the command line names (:meth:`RigSource.from_flags`, as the CLI's flags select it), or None: the
    source last chosen in the Connect dialog (QSettings)."""
    if bool(args.drum_port) != bool(args.taxel_port):
        raise SystemExit("give both --drum-port and --taxel-port")
    if args.drum_port or args.replay or args.hil or args.hil_bootloaders or args.sim or args.inject:
        return RigSource.from_flags(hil=args.hil, drum_port=args.drum_port, taxel_port=args.taxel_port,
                                    replay=args.replay, bootloaders=args.hil_bootloaders, inject=args.inject)
    return None


def write_stats(window: MainWindow, path: str, state: dict) -> None:
    """Append one JSON line of display statistics (benchmarks): cumulative paints of the live view and the
    frame-to-screen latencies (s) measured since the previous line; ``job_server``: the analysis jobs' fork server
    (:func:`rigctl_gui.workers.job_server_state`)."""
    lv = window.live
    n = lv._lat_n
    start = max(state.get("lat_n", 0), n - len(lv.latencies_s))
    idx = np.arange(start, n) % len(lv.latencies_s)
    state["lat_n"] = n
    enc = window.encoder
    line = {
        "time": time.monotonic(),
        "paints": lv.paints,
        "latency_s": [round(float(v), 6) for v in lv.latencies_s[idx]],
        "frames": lv.buffer.n_samples if lv.buffer else 0,
        "sa_spikes": enc.sa.total if enc else 0,
        "ra_spikes": enc.ra.total if enc else 0,
        "encoder_error": enc.encoder_error if enc else None,
        "connected": window.handle is not None,
        "job_server": job_server_state(),
    }
    with open(path, "a") as f:
        f.write(json.dumps(line) + "\n")


def start_job_server_with_analysis(window: MainWindow) -> None:
    """Start the analysis jobs' fork server (:func:`rigctl_gui.workers.start_job_server`, in the background) when
    ``window``'s Analysis tab is built (its first show or use; now, if it is already built), so the first Encode /
    Run analyses / Train finds the analysis stack loaded: every job starts from that tab, and a session at the rig
    that never opens it does not pay the server's ~2 CPU-s of imports (at start-up, beside the rig's connect). The
    GUI thread never waits on it; only the app does this, not each window (tests start their own)."""
    if window._analysis is not None:
        start_job_server()
    else:
        window.analysis_built.connect(start_job_server)


def _save_screenshot(window, path: str) -> None:
    """The main window as an image at ``path``, marked as rigctl's (:data:`rigctl.storage.outputs.FIGURE_MARK` in
    its text) and written under the output policy (a later ``--screenshot PATH --overwrite`` replaces only it)."""
    from rigctl.storage.outputs import FIGURE_MARK, replacing

    image = window.grab().toImage()
    image.setText("Software", FIGURE_MARK)
    with replacing(path, kind="figure", option="--screenshot") as tmp:
        if not image.save(str(tmp)):
            raise OSError(f"--screenshot {path}: Qt could not write the image")


def main(argv=None) -> int:
    args = parse_args(argv)
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("rigctl")
    # the console keeps the library's warnings (the window's event log shows them too, from INFO up)
    console = logging.StreamHandler()
    console.setLevel(logging.WARNING)
    console.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(console)
    # the GUI thread shares the GIL with the stream reader, the encoder and the drum poll: hand it back sooner
    # than the default 5 ms so a paint is not kept waiting behind a worker
    sys.setswitchinterval(0.001)
    configure_pyqtgraph()
    window = MainWindow(source_from_args(args), max_fps=args.max_fps)
    if args.tab:
        window.tabs.setCurrentIndex(TAB_NAMES.index(args.tab))
    window.show()
    start_job_server_with_analysis(window)
    if args.run or args.texture:
        def _run_when_ready():
            if window.commands is None:
                QtCore.QTimer.singleShot(200, _run_when_ready)
                return
            if args.texture:
                window.control.mount_plate(args.texture)
            if args.run:
                window.control.command("run")

        QtCore.QTimer.singleShot(200, _run_when_ready)
    if args.stats_out:
        stats_state: dict = {}
        st = QtCore.QTimer(window)
        st.timeout.connect(lambda: write_stats(window, args.stats_out, stats_state))
        st.start(1000)
    if args.quit_after is not None:
        def _finish():
            if args.screenshot:
                _save_screenshot(window, args.screenshot)
            # --quit-after is the answer to "the drum is turning / a protocol is running": stop the rig safely and
            # close (Qt 6's quit() first closes the windows, so a close left waiting for an answer kept the app up)
            window._close_after_abort()
            app.quit()

        QtCore.QTimer.singleShot(int(args.quit_after * 1000), _finish)
    return app.exec()


if __name__ == "__main__":
    sys.exit(main())
