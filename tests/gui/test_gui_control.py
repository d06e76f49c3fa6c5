"""Rig control and the app an experimenter trusts (issue 14), on the simulated rig (real ptys, real Modbus stack,
real Qt window offscreen): setpoints reach the drum controller, out-of-range and zero setpoints are refused visibly,
the big STOP stops the drum, and STOP works with every dialog open (no dialog is modal; Esc there only closes it); a protocol run owns
the rig (manual motion, calibration and Connect disabled, saying why; closing the window asks first, then stops
safely); a latched fault is shown with its meaning and cleared only by the operator; every message reaches the
window (event log with the library's logging records, status bar, one banner per board, stale markers, failed-trial
reasons, the run strip on every tab, errors never cut at '<', unexpected exceptions); both boards pulled and plugged
back in turn, each reconnecting by itself."""

from __future__ import annotations

import logging

import pytest
import shiboken6
from PySide6 import QtCore, QtWidgets

from rigctl.devices.wire import DrumState, Fault, HoldingRegister
from rigctl.operations._control import rig_of
from rigctl_gui.dialogs import open_dialogs
from rigctl_gui.events import wait_for

# wall: a real window driving the rig on ptys: reconnects, stale markers and banners timed on the wall clock
pytestmark = pytest.mark.realtime


def test_setpoints_reach_the_simulated_drum_and_stop_stops_it(window, qapp, qtbot):
    panel = window.control
    window.tabs.setCurrentWidget(panel)
    panel.speed.setValue(72.5)
    panel.force.setValue(420)
    qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
    drum = window.handle.drum
    # deadlines here only bound a hang: the GUI, its poller and the simulated rig share a loaded machine
    assert wait_for(qapp, lambda: drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 725
                 and drum.read_holding(HoldingRegister.FORCE_SETPOINT_G) == 420, 30)

    qtbot.mouseClick(panel.buttons["run"], QtCore.Qt.LeftButton)
    poller = window.poller
    assert wait_for(qapp, lambda: poller.latest is not None and poller.latest.state == DrumState.RUNNING
                 and abs(poller.latest.speed_mm_s - 72.5) < 1.0, 30), poller.latest
    # the panel shows the state in words and the plots hold the history
    assert wait_for(qapp, lambda: panel.state_label.text().startswith("Running"), 30)
    # ... and every tab's top strip says the drum is turning (issue 38 part 8)
    window.tabs.setCurrentWidget(window.analysis)
    assert wait_for(qapp, lambda: window.drum_state.text().startswith("Drum: Running"), 10), window.drum_state.text()
    assert window.drum_state.isVisible()
    window.tabs.setCurrentWidget(panel)
    assert wait_for(qapp, lambda: panel.speed_curve.getData()[1] is not None
                 and abs(panel.speed_curve.getData()[1][-1] - 72.5) < 1.5, 30)
    # the force loop holds the setpoint while the drum turns (it may settle after the speed: polled, not read once)
    assert wait_for(qapp, lambda: poller.latest.state == DrumState.RUNNING
                    and abs(poller.latest.force_g - 420) < 30, 30), poller.latest

    qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: poller.latest.state == DrumState.IDLE and abs(poller.latest.speed_mm_s) < 0.5, 20)
    assert poller.latest.force_setpoint_active_g == 0


def test_out_of_range_and_zero_setpoints_are_refused_visibly(window, qapp, qtbot):
    """200 typed in the speed box stays 200 (not cut to 20.0) and is refused with a message; nothing is sent; 0 is
    refused where it means nothing; the panel shows the protocol range and the controller's hard limits."""
    panel = window.control
    window.tabs.setCurrentWidget(panel)
    drum = window.handle.drum
    limit = drum.read_holding(HoldingRegister.SPEED_LIMIT_0P1MMS) / 10.0
    flimit = drum.read_holding(HoldingRegister.FORCE_LIMIT_G)
    text = panel.limits_label.text()
    assert f"controller hard limits {limit:g} mm/s, {flimit:g} g" in text and "protocol range > 0 to 150 mm/s" in text
    panel.speed.setValue(50.0)
    panel.force.setValue(300.0)
    qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 500
                    and drum.read_holding(HoldingRegister.FORCE_SETPOINT_G) == 300, 5)
    writes = rig_of(window.handle.control).backend.sim.mega.write_requests
    for box, typed, unit in ((panel.speed, "200", "mm/s"), (panel.force, "2000", "g")):
        box.lineEdit().selectAll()
        qtbot.keyClicks(box.lineEdit(), typed)
        qtbot.keyClick(box.lineEdit(), QtCore.Qt.Key_Return)
        assert box.value() == float(typed)  # shown as typed, not truncated to its first digits
        assert panel.setpoint_error.isVisible() and f"{typed} {unit} refused" in panel.setpoint_error.text()
        qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
        assert "refused" in panel.message.text() and "nothing sent" in panel.message.text()
        assert f"{typed} {unit} refused" in window.events.text()  # and in the event log
        box.setValue(50.0 if box is panel.speed else 300.0)
    panel.force.setValue(0)
    qtbot.mouseClick(panel.buttons["press"], QtCore.Qt.LeftButton)
    assert "force 0 g refused: it must be above 0 g" in panel.message.text()
    panel.force.setValue(300)
    assert not panel.setpoint_error.isVisible()
    wait_for(qapp, lambda: False, 0.3)
    assert rig_of(window.handle.control).backend.sim.mega.write_requests == writes  # nothing refused reached the controller
    assert drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 500
    # and the library refuses it again before anything is sent, reported in the panel
    window.commands.submit("set speed", window.handle.control.apply_setpoints, limit * 3, 300.0)
    assert wait_for(qapp, lambda: "failed" in panel.message.text(), 5), panel.message.text()
    assert rig_of(window.handle.control).backend.sim.mega.write_requests == writes
    assert not hasattr(drum, "set_speed")  # the GUI holds the controller read-only (issue 76)


PROTOCOL = """
name = "safety"
textures = ["A"]
speeds_mm_s = [100]
forces_g = [300]
trials_per_condition = {n}
duration_s = 0.3
retries = 0

[settle]
force_timeout_s = 10
speed_timeout_s = 5
speed_tolerance_mm_s = 3
"""


def _protocol(tmp_path, n=2, name="safety.toml", text=PROTOCOL):
    p = tmp_path / name
    p.write_text(text.format(n=n))
    return str(p)


def _state(window):
    st = window.poller.latest
    return DrumState(int(st.state)) if st is not None else None


def _spin(window, qapp):
    """Turn the drum (press, run) and wait until it turns."""
    window.control.speed.setValue(60.0)
    window.control.force.setValue(300.0)
    window.control.command("run")
    assert wait_for(qapp, lambda: _state(window) == DrumState.RUNNING and window.poller.latest.speed_mm_s > 20, 20), \
        window.poller.latest


def _stopped(window, qapp) -> bool:
    return wait_for(qapp, lambda: _state(window) in (DrumState.IDLE, DrumState.HOMING)
                    and window.poller.latest.speed_target_mm_s == 0, 10)


def _dialog_openers(window, tmp_path):
    """Every dialog the app opens, by name: a function that opens it and returns it."""
    def connect_file():
        return window.choose_source()._browse_file()

    def new_file_dialog(click):
        def opener():
            click()
            return next(d for d in open_dialogs() if isinstance(d, QtWidgets.QFileDialog))
        return opener

    return {
        "open protocol": window.protocol._browse_protocol,
        "output file": window.protocol._browse_output,
        "connect": window.choose_source,
        "connect: session file": connect_file,
        "calibration: session file": new_file_dialog(window.calibration.from_session_btn.click),
        "analysis: open": new_file_dialog(window.analysis.open_btn.click),
        "analysis: export tables": new_file_dialog(window.analysis._export_csv_dialog),
        "classification: model file": window.classify._choose_model,
    }


def _close_dialogs(qapp):
    for d in open_dialogs():
        d.reject()
    wait_for(qapp, lambda: not open_dialogs(), 2)


def test_stop_stops_the_drum_with_every_dialog_open_and_esc_only_closes_a_dialog(window, qapp, qtbot, tmp_path,
                                                                                  monkeypatch):
    window.tabs.setCurrentWidget(window.control)
    openers = _dialog_openers(window, tmp_path)
    # the drum really turns and really stops: STOP clicked with a file dialog open
    _spin(window, qapp)
    dlg = openers["open protocol"]()
    assert dlg.isVisible() and QtWidgets.QApplication.activeModalWidget() is None
    qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
    assert _stopped(window, qapp), window.poller.latest
    _close_dialogs(qapp)
    # every dialog: neither modal nor in the way of STOP (each click reaches the rig's safe stop); Esc in the dialog
    # closes it and stops nothing
    stops = []
    safe_stop = rig_of(window.handle.control).safe_stop
    monkeypatch.setattr(rig_of(window.handle.control), "safe_stop", lambda: stops.append(1) or safe_stop())
    for name, opener in openers.items():
        dlg = opener()
        assert dlg.isVisible() and not dlg.isModal() and QtWidgets.QApplication.activeModalWidget() is None, name
        n = len(stops)
        qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: len(stops) == n + 1, 5), name
        qtbot.keyClick(dlg, QtCore.Qt.Key_Escape)  # Esc in the dialog: it closes, nothing else
        assert wait_for(qapp, lambda: not shiboken6.isValid(dlg) or not dlg.isVisible(), 5), name
        assert len(stops) == n + 1, name
        _close_dialogs(qapp)
    wait_for(qapp, lambda: False, 0.4)  # a stop an Esc sent would have reached the rig by now: one per click only
    assert len(stops) == len(openers)
    assert "STOP sent" in window.events.text()


def _answer(qapp, qtbot, button_text: str) -> None:
    """Click ``button_text`` in the open (non-modal) question box."""
    assert wait_for(qapp, lambda: any(isinstance(d, QtWidgets.QMessageBox) for d in open_dialogs()), 5)
    box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
    qtbot.mouseClick(next(b for b in box.buttons() if b.text() == button_text), QtCore.Qt.LeftButton)


def test_setpoints_are_not_sent_while_a_run_owns_the_rig_and_the_menus_follow(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    tab.load(_protocol(tmp_path, n=3))
    tab.out_edit.setText(str(tmp_path / "owned.h5"))
    tab.resume_box.setChecked(False)
    window.tabs.setCurrentWidget(window.control)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert tab.running
    manual = [*window.control.buttons.values(), window.control.apply_btn, window.control.mount_btn,
              window.calibration.loadcell_btn, window.calibration.norm_btn, window.calibration.from_session_btn,
              window.connect_btn]
    for b in manual:
        assert not b.isEnabled() and "protocol run owns the rig" in b.toolTip(), b.text()
    menu = {a.text().replace("&", ""): a for m in window.menuBar().findChildren(QtWidgets.QMenu) for a in m.actions()}
    assert wait_for(qapp, lambda: not menu["Run drum"].isEnabled(), 2)  # (mirrored at the next tick)
    assert not menu["Run drum"].isEnabled() and not menu["Connect..."].isEnabled()
    assert menu["Abort..."].isEnabled() and menu["STOP (safe stop)"].isEnabled()
    # the run's state and the operator's prompt are seen from any tab (the run strip above the tabs)
    assert window.protocol.run_strip.isVisible() and "Protocol safety" in window.protocol.run_label.text()
    tab.job.events.put(("prompt", "Mount texture plate L"))  # what the runner asks on hardware
    assert wait_for(qapp, lambda: tab.prompt_frame.isVisible(), 2)
    assert tab.prompt_label.text() == "Mount texture plate L" and "operator: Mount texture plate L" in \
        window.events.text()
    qtbot.mouseClick(tab.prompt_ok, QtCore.Qt.LeftButton)
    assert not tab.prompt_frame.isVisible()
    # paused: the rig is released, and still owned by the run
    qtbot.mouseClick(tab.pause_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab._paused, 30), tab.status.text()
    assert not window.control.buttons["run"].isEnabled() and not window.connect_btn.isEnabled()
    assert window.choose_source() is None and "Connect is disabled" in window.events.text()
    qtbot.mouseClick(window.control.buttons["run"], QtCore.Qt.LeftButton)  # a disabled button does nothing
    wait_for(qapp, lambda: False, 0.5)
    assert _state(window) != DrumState.RUNNING
    qtbot.mouseClick(tab.abort_btn, QtCore.Qt.LeftButton)  # Abort asks first
    _answer(qapp, qtbot, "Abort the run")
    assert wait_for(qapp, lambda: tab.job is None, 30), tab.status.text()
    assert wait_for(qapp, lambda: all(b.isEnabled() for b in manual), 2)
    assert "protocol run owns the rig" not in window.control.buttons["run"].toolTip()
    assert menu["Run drum"].isEnabled() and not window.protocol.run_strip.isVisible()
    assert "aborted" in window.events.text()


def test_a_latched_fault_is_shown_with_its_meaning_and_cleared_only_by_the_operator(window, qapp, qtbot):
    mega = rig_of(window.handle.control).backend.sim.mega
    window.tabs.setCurrentWidget(window.control)
    mega.set_loadcell_alive(False)  # the HX711 stops answering: LOADCELL_TIMEOUT latches
    try:
        banner = window.banners["fault"]
        assert wait_for(qapp, lambda: banner.isVisible(), 10)
        text = banner.text
        assert "Load cell not responding: the load cell amplifier (HX711)" in text and "latched" in text
        assert not window.banner.isVisible() or "FAULT" not in window.banner.text  # said once
        assert "Clear fault" in banner.text
        assert wait_for(qapp, lambda: "Latched faults: Load cell" in window.control.fault_label.text(), 2)
        assert wait_for(qapp, lambda: window.drum_state.text().startswith("Drum: FAULT"), 2), window.drum_state.text()
    finally:
        mega.set_loadcell_alive(True)
    wait_for(qapp, lambda: False, 1.0)  # nothing clears it by itself
    assert _state(window) == DrumState.FAULT and int(window.poller.latest.faults) & Fault.LOADCELL_TIMEOUT
    assert banner.isVisible() and "drum controller FAULT" in window.events.text().replace("Drum", "drum")
    if window.fault_dialog is not None and window.fault_dialog.isVisible():  # (the latch opened it) Later
        window.fault_dialog.later_btn.click()
    qtbot.mouseClick(window.control.buttons["clear_fault"], QtCore.Qt.LeftButton)  # the fault dialog: a reason
    dlg = window.fault_dialog
    assert dlg is not None and dlg.isVisible() and "load cell not responding" in dlg.title.text().lower()
    wait_for(qapp, lambda: False, 0.5)
    assert _state(window) == DrumState.FAULT  # the click itself cleared nothing
    dlg.reason.setText("re-seated the HX711's cable")
    qtbot.mouseClick(dlg.ok_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: _state(window) != DrumState.FAULT and not banner.isVisible(), 30)
    assert wait_for(qapp, lambda: "re-seated the HX711's cable" in window.events.text(), 10)
    assert "faults cleared" in window.events.text()


def test_a_controller_in_fault_at_connect_is_left_latched(qapp):
    """The app opens the rig without clearing a latched fault (the library clears it only when homing)."""
    from rigctl.simulation.rig import SimulatedRig
    from rigctl_gui.app import open_rig_keeping_faults
    from rigctl_gui.workers import RigSource

    with SimulatedRig() as sim:
        sim.mega.set_loadcell_alive(False)
        assert wait_for(qapp, lambda: sim.mega.state == DrumState.FAULT, 5)
        sim.mega.set_loadcell_alive(True)
        h = open_rig_keeping_faults(RigSource("serial", drum_port=sim.drum_port, taxel_port=sim.taxel_port))
        try:
            st = h.drum.read_status()
            assert st.state == DrumState.FAULT and st.faults & Fault.LOADCELL_TIMEOUT
        finally:
            h.close()


def test_every_message_reaches_the_window(window, qapp, qtbot, tmp_path, monkeypatch):
    # the library's logging records land in the event log
    logging.getLogger("rigctl.acquisition.test").warning("a library warning with <angle> brackets")
    assert wait_for(qapp, lambda: "a library warning with <angle> brackets" in window.events.text(), 2)
    # a STOP result is drawn in the status bar (the link status no longer fills it)
    qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: "STOP" in window.statusBar().currentMessage(), 2)
    assert window.statusBar().findChild(QtWidgets.QLabel, "drum_link").isVisible()
    # an error with '<' is shown whole (a protocol outside the rig limits)
    bad = _protocol(tmp_path, name="bad.toml", text=PROTOCOL.replace("[100]", "[400]"))
    window.protocol.load(_protocol(tmp_path, n=1))
    window.protocol.load(bad)
    assert "(> 0 and <= 150" in window.protocol.status.text()
    assert window.protocol.protocol is None and not window.protocol.start_btn.isEnabled()  # the old one is unloaded
    assert "(> 0 and <= 150" in window.events.text()
    # a replay of nothing: a clear message, the rig stays connected
    from rigctl_gui.workers import RigSource

    window.connect_source(RigSource("replay", replay_dir=None))
    assert "choose a session file or a FabricSlide folder" in window.banner.text
    assert window.handle is not None
    # a failed trial's reason is in the plan table
    from rigctl.acquisition.rig import RigError

    record = rig_of(window.handle.control).record_trial

    def fail_trial_0(planned, **kw):
        if planned.trial_id == 0:
            raise RigError("the <test> made trial 0 fail")
        return record(planned, **kw)

    monkeypatch.setattr(rig_of(window.handle.control), "record_trial", fail_trial_0)
    tab = window.protocol
    tab.load(_protocol(tmp_path, n=1))
    tab.out_edit.setText(str(tmp_path / "failing.h5"))
    tab.resume_box.setChecked(False)
    window.tabs.setCurrentWidget(window.live)
    tab.start()
    assert wait_for(qapp, lambda: tab.job is None, 60), tab.status.text()
    assert tab.row_status(0).startswith("FAILED: ") and "the <test> made trial 0 fail" in tab.row_status(0)
    assert "trial 0 failed" in window.events.text()


def test_the_window_is_usable_at_1024x686(window, qapp):
    """Every tab fits a 1024x686 window; the left panels keep their width whatever their texts say; the analysis
    trial list keeps several rows."""
    assert window.minimumSizeHint().width() <= 1024 and window.minimumSizeHint().height() <= 686
    window.live.info.setText("a long encoder error " * 30)  # a status line never widens the window
    assert window.minimumSizeHint().width() <= 1024
    window.resize(1024, 686)
    window.tabs.setCurrentWidget(window.control)
    qapp.processEvents()
    left = window.control.layout().itemAt(0).widget()
    width = left.width()
    window.control.state_label.setText("a long state text " * 20)
    window.control.message.setText("a long command result " * 20)
    qapp.processEvents()
    assert left.width() == width
    window.tabs.setCurrentWidget(window.analysis)
    qapp.processEvents()
    rows = window.analysis.trials.verticalHeader().defaultSectionSize()
    assert window.analysis.trials.viewport().height() >= 4 * rows
    window.resize(1400, 900)
    window.control.message.setText("")


@pytest.mark.qt_no_exception_capture  # the app's own guard is what is tested
def test_an_unexpected_exception_is_shown_in_the_window(window, qapp):
    import threading

    window.guard.install()  # (pytest-qt's hook of earlier tests may have replaced it)
    QtCore.QTimer.singleShot(0, lambda: 1 / 0)  # a bug in a Qt callback
    assert wait_for(qapp, lambda: "ZeroDivisionError" in window.banner.text, 3)
    assert window.banner.isVisible() and "Traceback" in window.events.text()
    t = threading.Thread(target=lambda: [][1], name="buggy-worker")  # and in a worker thread
    t.start()
    t.join()
    assert wait_for(qapp, lambda: "IndexError" in window.banner.text, 3)
    assert "thread buggy-worker" in window.banner.text
    assert window.timer.isActive()  # the app carries on


def test_both_boards_pulled_and_plugged_back_in_turn(window, qapp, qtbot, monkeypatch):
    sim = rig_of(window.handle.control).backend.sim
    window.tabs.setCurrentWidget(window.control)
    drum_banner, taxel_banner = window.banners["drum"], window.banners["taxel"]
    # "reconnected" is held 1 s before "connected", not the app's 5 s (its hold is link_health's to test; here each
    # board's way back, one after the other)
    for health in window.links.health.values():
        monkeypatch.setattr(health, "settle_s", 1.0)
    # the drum controller's cable
    sim.mega.bridge.unplug()
    try:
        assert wait_for(qapp, lambda: "NO RESPONSE" in window.links.drum.text(), 10), window.links.drum.text()
        assert wait_for(qapp, lambda: drum_banner.isVisible(), 2)
        assert "Drum controller (Mega) not responding" in drum_banner.text, drum_banner.text
        # (the taxel board may be named beside it: a GUI process starved on a loaded machine sees its stream stall
        # too, rightly, "drum controller and taxel board not responding")
        source = window.source_label.text()
        assert "connected, drum controller" in source and "not responding" in source, source
        assert wait_for(qapp, lambda: "STALE" in window.control.force_plot.titleLabel.text, 2), \
            window.control.force_plot.titleLabel.text
        # a STOP that cannot reach the controller says so in the window, on any tab
        window.tabs.setCurrentWidget(window.live)
        qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: "STOP FAILED" in window.banner.text, 20), window.banner.text
        assert window.banner.isVisible() and "stop the rig by hand" in window.banner.text
        window.tabs.setCurrentWidget(window.control)
        # the taxel board's cable too, while the drum's is out: each board keeps its own banner
        sim.unplug_taxel()
        window.tabs.setCurrentWidget(window.live)
        assert wait_for(qapp, lambda: "DISCONNECTED" in window.links.taxel.text(), 10), window.links.taxel.text()
        assert taxel_banner.isVisible() and "Taxel board (Uno) disconnected" in taxel_banner.text, \
            taxel_banner.text
        assert drum_banner.isVisible() and "not responding" in drum_banner.text, drum_banner.text
        assert wait_for(qapp, lambda: window.stale_label.isVisible(), 5)
        assert "STALE" in window.stale_label.text()
    finally:
        sim.mega.bridge.replug()
    # the drum reconnects by itself; its banner turns green; the taxel board is still out
    assert wait_for(qapp, lambda: window.links.drum.text().startswith("Drum: connected"), 30), window.links.drum.text()
    assert "reconnected" in drum_banner.text and "disconnected" in taxel_banner.text, \
        (drum_banner.text, taxel_banner.text)
    sim.replug_taxel()
    assert wait_for(qapp, lambda: window.links.taxel.text().startswith("Taxels: connected"), 30), \
        window.links.taxel.text()
    assert "reconnected" in taxel_banner.text, taxel_banner.text
    assert wait_for(qapp, lambda: not window.stale_label.isVisible(), 5), window.stale_label.text()
    assert window.source_label.text().endswith("- connected"), window.source_label.text()
    n = window.handle.taxels.ring.total
    assert wait_for(qapp, lambda: window.handle.taxels.ring.total > n + 200, 5)
    window.tabs.setCurrentWidget(window.control)
    assert wait_for(qapp, lambda: "STALE" not in window.control.force_plot.titleLabel.text, 2)


def test_quit_connect_and_mount_plate_ask_while_the_drum_turns(window, qapp, qtbot):
    """With the drum turning (no protocol run), Quit, Connect -> OK and Mount plate ask first; "Keep running" /
    "Cancel" leaves the drum turning, the rig connected and the plate where it was."""
    window.tabs.setCurrentWidget(window.control)
    _spin(window, qapp)
    handle, plate = window.handle, window.handle.control.plate
    for act, keep in ((window.close, "Keep running"),
                      (lambda: window.choose_source().accept(), "Cancel"),
                      (lambda: window.control.mount_plate("B" if plate != "B" else "C"), "Cancel")):
        act()
        box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
        assert "The drum is turning" in box.text(), box.text()
        qtbot.mouseClick(next(b for b in box.buttons() if b.text() == keep), QtCore.Qt.LeftButton)
        wait_for(qapp, lambda: False, 0.5)
        assert window.isVisible() and window.handle is handle and _state(window) == DrumState.RUNNING
        assert window.handle.control.plate == plate
    # asked again and answered yes: the plate is mounted (the drum stopped for it)
    window.control.mount_plate("C")
    _answer(qapp, qtbot, "Stop the drum and mount C")
    assert wait_for(qapp, lambda: window.handle.control.plate == "C", 30), window.handle.control.plate
    assert "mount plate C" in window.events.text()


def test_closing_the_window_mid_run_asks_then_stops_safely(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    tab.load(_protocol(tmp_path, n=4))
    tab.out_edit.setText(str(tmp_path / "closing.h5"))
    tab.resume_box.setChecked(False)
    tab.start()
    assert wait_for(qapp, lambda: tab._current is not None, 30)
    window.close()
    box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
    assert window.isVisible() and tab.running and not box.isModal()
    keep = next(b for b in box.buttons() if b.text() == "Keep running")
    qtbot.mouseClick(keep, QtCore.Qt.LeftButton)
    wait_for(qapp, lambda: False, 0.3)
    assert window.isVisible() and tab.running
    window.close()
    box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
    mega = rig_of(window.handle.control).backend.sim.mega
    qtbot.mouseClick(next(b for b in box.buttons() if b.text().startswith("Abort")), QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: not window.isVisible(), 20)
    assert window.handle is None and not tab.running
    # the rig was stopped safely before it closed: drum target 0, force loop released
    assert mega.state not in (DrumState.RUNNING, DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED)
    assert mega.speed_target_mm_s == 0

