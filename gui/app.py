"""The main window and the application entry point.

``python -m rigctl_gui.app [--drum-port P --taxel-port P] [--replay PATH] [--screenshot PATH --quit-after S] [--tab NAME]``
(also ``rigctl gui``). With no ports the app starts on the simulated rig.

The window holds a big STOP button that is always visible, a non-modal banner for disconnects, one tab per panel
and a status bar with both boards' link status. One QTimer pulls from the worker threads at the GUI's own pace.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from rigctl_gui.workers import CommandExecutor, Job, LiveEncoder, RigSource, StatusPoller, open_rig

#: the app's refresh period (ms): 25 ms = 40 Hz, so the live view keeps >= 30 frames/s with slack
REFRESH_MS = 25
TAB_NAMES = ("control", "live", "protocol", "analysis", "calibration", "classify")


def configure_pyqtgraph() -> None:
    """White plots, no antialiasing (faster software rendering under Xvfb/offscreen)."""
    import pyqtgraph as pg

    pg.setConfigOptions(antialias=False, background="w", foreground="k")


def make_settings() -> QtCore.QSettings:
    """The app's QSettings (INI format under the user scope; tests point it at a temporary directory)."""
    return QtCore.QSettings(QtCore.QSettings.IniFormat, QtCore.QSettings.UserScope, "rigctl", "gui")


def sensor_layout(handle):
    """The :class:`rigctl.core.sensor.SensorLayout` of an open rig: its taxel stream's (from the board's identify
    reply), else the rig's, else the paper's 3x3x2 at 1 kHz."""
    from rigctl.core.sensor import PAPER_SENSOR

    return (getattr(handle.taxels, "layout", None) or getattr(handle.rig, "layout", None) or PAPER_SENSOR)


class MainWindow(QtWidgets.QMainWindow):
    """The rigctl main window. ``source=None`` reads the last source from QSettings (simulated rig by default)."""

    def __init__(self, source: RigSource | None = None, *, autoconnect: bool = True):
        super().__init__()
        from rigctl_gui.analysis_tab import AnalysisTab
        from rigctl_gui.calibration_tab import CalibrationTab
        from rigctl_gui.classify_view import ClassifyView
        from rigctl_gui.connect_dialog import ConnectDialog, load_source, save_source
        from rigctl_gui.control_panel import ControlPanel
        from rigctl_gui.live_view import LiveView
        from rigctl_gui.protocol_tab import ProtocolTab
        from rigctl_gui.status_bar import Banner, LinkStatus

        self._ConnectDialog, self._save_source = ConnectDialog, save_source
        self.settings = make_settings()
        self.source = source or load_source(self.settings)
        self.handle = None
        self.poller = None
        self.commands = None
        self.encoder = None
        self._connect_job = None
        self.setWindowTitle("rigctl - tactile texture rig")

        # --- top bar: source, connect, STOP ---
        self.source_label = QtWidgets.QLabel()
        self.source_label.setStyleSheet("font-weight: bold;")
        self.connect_btn = QtWidgets.QPushButton("Connect...")
        self.connect_btn.clicked.connect(self.choose_source)
        self.stop_btn = QtWidgets.QPushButton("STOP")
        self.stop_btn.setObjectName("big_stop")
        self.stop_btn.setToolTip("Safe stop: abort any protocol run, stop the drum, back the actuator off (Esc)")
        self.stop_btn.setMinimumSize(160, 48)
        self.stop_btn.setStyleSheet(
            "QPushButton { background: #d00; color: white; font-size: 20px; font-weight: bold; border-radius: 6px; }"
            "QPushButton:pressed { background: #900; }"
        )
        self.stop_btn.clicked.connect(self.emergency_stop)
        QtGui.QShortcut(QtGui.QKeySequence("Esc"), self, activated=self.emergency_stop)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.connect_btn)
        top.addWidget(self.source_label, 1)
        top.addWidget(self.stop_btn)

        self.banner = Banner()
        self.tabs = QtWidgets.QTabWidget()
        self.control = ControlPanel()
        self.live = LiveView()
        self.protocol = ProtocolTab(self)
        self.analysis = AnalysisTab(self)
        self.calibration = CalibrationTab(self)
        self.classify = ClassifyView(self)
        for w, name in (
            (self.control, "Rig control"),
            (self.live, "Live view"),
            (self.protocol, "Protocol"),
            (self.analysis, "Analysis"),
            (self.calibration, "Calibration"),
            (self.classify, "Real-time classification"),
        ):
            self.tabs.addTab(w, name)
        self.tabs.setCurrentIndex(int(self.settings.value("ui/tab", 0)))

        central = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(central)
        lay.addLayout(top)
        lay.addWidget(self.banner)
        lay.addWidget(self.tabs, 1)
        self.setCentralWidget(central)

        self.links = LinkStatus()
        self.links.link_changed.connect(self.banner.on_link_changed)
        self.statusBar().addPermanentWidget(self.links, 1)

        geom = self.settings.value("ui/geometry")
        if geom is not None:
            self.restoreGeometry(geom)
        else:
            self.resize(1400, 900)

        self._tick = 0
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.PreciseTimer)
        self.timer.timeout.connect(self.refresh)
        self.timer.start(REFRESH_MS)
        self._update_source_label("not connected")
        if autoconnect:
            self.connect_source(self.source)

    # ------------------------------------------------------------------------------------------------------
    # connection
    # ------------------------------------------------------------------------------------------------------
    def choose_source(self) -> None:
        dlg = self._ConnectDialog(self.source, self)
        if dlg.exec() == QtWidgets.QDialog.Accepted:
            self.connect_source(dlg.source())

    def connect_source(self, source: RigSource) -> None:
        """Open ``source`` in a worker thread (the boards take ~2 s to boot); :meth:`refresh` finishes the job."""
        self.disconnect_rig()
        self.source = source
        self._save_source(self.settings, source)
        cfg_path = self.rig_config_path()
        self._connect_job = Job(lambda job: open_rig(source, host_config_path=cfg_path), name="connect")
        self._connect_job.start()
        self._update_source_label("connecting...")
        self.connect_btn.setEnabled(False)

    def _finish_connect(self) -> None:
        job, self._connect_job = self._connect_job, None
        self.connect_btn.setEnabled(True)
        if job.error:
            self._update_source_label("not connected")
            self.banner.show_message(f"Could not open the {self.source.label()}: {job.error}", error=True)
            return
        h = self.handle = job.result
        self.poller = StatusPoller(h.drum, period_s=0.1)
        self.poller.start()
        self.commands = CommandExecutor(h.drum)
        self._attach_sensor(h, sensor_layout(h))
        self.control.attach(h.drum, self.poller, self.commands, h.rig)
        self._update_source_label("connected")
        # everything long-lived exists now: move it out of the cyclic GC's reach, so full collections (which
        # otherwise traverse every Qt wrapper and pyqtgraph item, ~150 ms) do not stall the display
        gc.collect()
        gc.freeze()
        self.banner.hide()

    def disconnect_rig(self) -> None:
        """Abort a run, stop the rig safely (the library's safe stop), close it, then stop the workers."""
        self.protocol.abort_and_wait()
        self.control.detach()
        self.live.detach()
        self.calibration.detach()
        if self.handle is not None:
            try:
                self.handle.close()  # safe stop first: the controller's watchdog never sees a silent host
            except Exception as exc:  # noqa: BLE001
                self.statusBar().showMessage(f"closing the rig: {exc}", 5000)
        if self.commands is not None:
            self.commands.close()
        for w in (self.poller, self.encoder):
            if w is not None:
                w.stop()
        for w in (self.poller, self.encoder):
            if w is not None:
                w.join(timeout=5)  # never leave a numba call running at interpreter exit
        self.handle = self.poller = self.commands = self.encoder = None

    def rig_config_path(self) -> str | None:
        """The rig config file (calibration) from QSettings ``rig/config_path``; None = the library's default."""
        return str(self.settings.value("rig/config_path", "")) or None

    def _update_source_label(self, state: str) -> None:
        self.source_label.setText(f"Source: {self.source.label()} - {state}")

    # ------------------------------------------------------------------------------------------------------
    def emergency_stop(self) -> None:
        """STOP: abort a protocol run (its stop event) and send the safe-stop command at once, off the GUI thread."""
        self.protocol.request_abort()
        if self.commands is not None:
            self.commands.emergency_stop()
        self.statusBar().showMessage("STOP sent", 3000)

    def refresh(self) -> None:
        """One tick of the GUI's own clock: pull from the workers, redraw what is visible."""
        self._tick += 1
        if self._connect_job is not None and self._connect_job.done:
            self._finish_connect()
        if self.commands is not None:
            while not self.commands.results.empty():
                _name, ok, text = self.commands.results.get()
                self.control.show_result(ok, text)
                self.statusBar().showMessage(text, 4000)
        current = self.tabs.currentWidget()
        if current is self.live:
            self.live.refresh()
        if self._tick % 4 == 0:
            if current is self.control:
                self.control.refresh()
            self.protocol.refresh()
            self.analysis.refresh()
            self.calibration.refresh()
            self.classify.refresh()
        if self._tick % 20 == 0:
            self.links.update_from(self.poller, self.handle.taxels if self.handle else None)
            self.follow_sensor()

    def follow_sensor(self) -> bool:
        """Rebuild the live view, its encoder and the calibration tab when the taxel board now reports another
        sensor than they were built for (another board plugged in: the stream has a new layout and ring buffer).
        Returns True when they were rebuilt."""
        h, enc = self.handle, self.encoder
        if h is None or enc is None:
            return False
        layout = sensor_layout(h)
        buf = self.live.buffer
        if layout == enc.layout and (buf is None or buf.ring is h.taxels.ring):
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
        self.encoder = LiveEncoder(h.taxels, normaliser=self.calibration.taxel_range(h.rig, layout), layout=layout)
        self.encoder.start()
        self.live.attach(h.taxels, self.encoder, layout)

    def closeEvent(self, ev):  # noqa: N802 - Qt override
        self.settings.setValue("ui/geometry", self.saveGeometry())
        self.settings.setValue("ui/tab", self.tabs.currentIndex())
        self.timer.stop()
        self.disconnect_rig()
        super().closeEvent(ev)


# ----------------------------------------------------------------------------------------------------------------
def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="rigctl gui", description="The rigctl desktop app.")
    ap.add_argument("--drum-port", help="serial port of the drum controller (Mega)")
    ap.add_argument("--taxel-port", help="serial port of the taxel streamer (Uno)")
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
    return ap.parse_args(argv)


def source_from_args(args) -> RigSource | None:
    if args.drum_port or args.taxel_port:
        if not (args.drum_port and args.taxel_port):
            raise SystemExit("give both --drum-port and --taxel-port")
        return RigSource("serial", drum_port=args.drum_port, taxel_port=args.taxel_port)
    if args.replay:
        return RigSource("replay", replay_dir=args.replay)
    return RigSource("sim")


def write_stats(window: MainWindow, path: str, state: dict) -> None:
    """Append one JSON line of display statistics (benchmarks): cumulative paints of the live view and the
    frame-to-screen latencies (s) measured since the previous line."""
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
    }
    with open(path, "a") as f:
        f.write(json.dumps(line) + "\n")


def main(argv=None) -> int:
    args = parse_args(argv)
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("rigctl")
    # the GUI thread shares the GIL with the stream reader, the encoder and the drum poll: hand it back sooner
    # than the default 5 ms so a paint is not kept waiting behind a worker
    sys.setswitchinterval(0.001)
    configure_pyqtgraph()
    window = MainWindow(source_from_args(args))
    if args.tab:
        window.tabs.setCurrentIndex(TAB_NAMES.index(args.tab))
    window.show()
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
                window.grab().save(args.screenshot)
            window.close()
            app.quit()

        QtCore.QTimer.singleShot(int(args.quit_after * 1000), _finish)
    return app.exec()


if __name__ == "__main__":
    sys.exit(main())
