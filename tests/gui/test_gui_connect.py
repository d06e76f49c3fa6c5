"""Connect dialog and sources: the dialog lists serial ports with VID:PID from rigctl.devices.ports, its choice
persists in QSettings, and the FabricSlide replay streams recorded signals into the live view."""

from __future__ import annotations

import pytest

from rigctl_gui.events import wait_for

# wall: a real window's live view, a FabricSlide replay streaming into it
pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def window(inprocess_window):
    """The module's main window, the one that connects to the replays and the HIL rig: it starts on the in-process
    rig and goes back to it after each test (a source it leaves; a real-time rig on ptys took seconds to boot and
    home, each time)."""
    return inprocess_window


def test_connect_dialog_lists_ports_and_persists_the_choice(qapp, gui_home, tmp_path):
    from rigctl.devices.ports import find_ports
    from rigctl.simulation.rig import SimulatedRig
    from rigctl_gui.app import make_settings
    from rigctl_gui.connect_dialog import ConnectDialog, load_source, save_source
    from rigctl_gui.workers import RigSource

    with SimulatedRig() as sim:
        dlg = ConnectDialog(RigSource("serial", drum_port=sim.drum_port, taxel_port=sim.taxel_port))
        n = len(find_ports())
        assert dlg.drum_port.count() == n
        assert f"{n} serial port(s) found" in dlg.port_info.text()
        assert dlg.serial.isChecked()
        src = dlg.source()  # the saved ports are kept even when the scan does not list them (ptys)
    # the composition root's kind (rigctl.rigs.KINDS)
    assert (src.kind, src.drum_port, src.taxel_port) == ("hardware", sim.drum_port, sim.taxel_port)
    dlg.replay.setChecked(True)
    dlg.replay_dir.setText(str(tmp_path))
    assert dlg.source() == RigSource("replay", replay_dir=str(tmp_path))
    dlg.hil.setChecked(True)
    assert dlg.source() == RigSource("hil")
    dlg.sim.setChecked(True)
    dlg.hil_bootloaders.setChecked(True)  # ticking the bootloaders chooses the firmware under simavr
    assert dlg.hil.isChecked() and dlg.source() == RigSource("hil", bootloaders=True)
    dlg.sim.setChecked(True)
    assert dlg.source() == RigSource("sim")
    assert ConnectDialog(RigSource("hil", bootloaders=True)).source() == RigSource("hil", bootloaders=True)

    settings = make_settings()
    save_source(settings, RigSource("serial", drum_port="/dev/ttyACM0", taxel_port="/dev/ttyACM1"))
    settings.sync()
    again = load_source(make_settings())
    assert again == RigSource("serial", drum_port="/dev/ttyACM0", taxel_port="/dev/ttyACM1")
    settings.setValue("source/kind", "serial")  # what earlier versions saved for the hardware rig
    settings.sync()
    assert load_source(make_settings()).kind == "hardware"
    settings.setValue("source/kind", "no such kind")
    settings.sync()
    assert load_source(make_settings()) == RigSource("sim")
    save_source(settings, RigSource("hil", bootloaders=True))
    settings.sync()
    assert load_source(make_settings()) == RigSource("hil", bootloaders=True)
    finger = RigSource("handheld", motion="lsl:Tracker@3", taxel_port="/dev/ttyACM1")  # the Handheld tab's rig
    save_source(settings, finger)
    settings.sync()
    assert load_source(make_settings()) == finger
    save_source(settings, RigSource("sim"))
    settings.sync()
    assert load_source(make_settings()) == RigSource("sim")


def test_fabricslide_replay_source_feeds_the_live_view(window, qapp, fabricslide_dir):
    from rigctl_gui.workers import RigSource

    window.connect_source(RigSource("replay", replay_dir=str(fabricslide_dir)))
    assert wait_for(qapp, lambda: window.handle is not None or "Could not" in window.banner.text, 90), \
        window.banner.text
    assert window.handle is not None, window.banner.text
    assert "FabricSlide replay" in window.source_label.text()
    window.tabs.setCurrentWidget(window.live)
    assert wait_for(qapp, lambda: window.live.buffer is not None and window.live.buffer.n_samples > 1000, 20)
    x = window.live.buffer.view()[1]
    assert x.std(axis=0).max() > 0  # recorded signals, not a constant
    window.connect_source(RigSource("inprocess"))
    assert wait_for(qapp, lambda: window.handle is not None, 60)


def test_connect_dialog_picks_a_session_file_to_replay(qapp, gui_home, tmp_path):
    """A session file of any sensor can be chosen for replay (not only a FabricSlide folder), in a non-modal file
    dialog; OK is refused, saying why, while the replay source is empty."""
    from PySide6 import QtWidgets

    from rigctl_gui.connect_dialog import ConnectDialog
    from rigctl_gui.workers import RigSource

    session = tmp_path / "finger9.h5"
    session.write_bytes(b"")
    dlg = ConnectDialog(RigSource("sim"))
    dlg.replay.setChecked(True)
    dlg.accept()
    assert dlg.result() != QtWidgets.QDialog.Accepted and "choose a session file" in dlg.problem.text()
    fd = dlg._browse_file()
    assert fd.isVisible() and not fd.isModal() and QtWidgets.QApplication.activeModalWidget() is None
    assert "*.h5" in fd.nameFilters()[0]
    fd.selectFile(str(session))
    fd.accept()
    assert dlg.source() == RigSource("replay", replay_dir=str(session))
    dlg.accept()
    assert dlg.result() == QtWidgets.QDialog.Accepted
    qapp.processEvents()  # the file dialog (deleted on close) goes while its parent lives


def test_the_app_opens_the_source_chosen_last_unless_told_otherwise():
    """No source option: the one saved by the Connect dialog (MainWindow(None) loads it); --sim, --replay and the
    ports choose."""
    from rigctl_gui.app import parse_args, source_from_args
    from rigctl_gui.workers import RigSource

    assert source_from_args(parse_args([])) is None
    assert source_from_args(parse_args(["--sim"])) == RigSource("sim")
    assert source_from_args(parse_args(["--replay", "x.h5"])) == RigSource("replay", replay_dir="x.h5")
    assert source_from_args(parse_args(["--drum-port", "a", "--taxel-port", "b"])) == \
        RigSource("serial", drum_port="a", taxel_port="b")
    assert source_from_args(parse_args(["--hil"])) == RigSource("hil")
    assert source_from_args(parse_args(["--hil-bootloaders"])) == RigSource("hil", bootloaders=True)


@pytest.mark.hil
def test_the_app_drives_the_firmware_under_simavr(window, qapp, qtbot, build_tools):
    """The HIL source (issue 22 left the app without one): the window connects to the Mega and Uno images under
    simavr (built from the installed sources on first use), the rig is homed, the Uno's frames reach the live view,
    and a setpoint run and STOP reach the firmware, read back through the app's own status poll."""
    from PySide6 import QtCore

    from rigctl.core.drum import DrumState
    from rigctl_gui.workers import RigSource

    try:
        window.connect_source(RigSource("hil"))
        assert wait_for(qapp, lambda: window.handle is not None or "Could not" in window.banner.text, 240), \
            window.banner.text
        assert window.handle is not None, window.banner.text
        assert "firmware under simavr" in window.source_label.text()
        # the Live view shown (it draws the stream while shown: run alone, the window starts on another tab; in the
        # module, the replay test before it left the Live view shown)
        window.tabs.setCurrentWidget(window.live)
        assert wait_for(qapp, lambda: window.live.buffer is not None and window.live.buffer.n_samples > 500, 60)
        panel, poller = window.control, window.poller
        window.tabs.setCurrentWidget(panel)
        panel.speed.setValue(60.0)
        panel.force.setValue(300.0)
        qtbot.mouseClick(panel.buttons["run"], QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: poller.latest is not None and poller.latest.state == DrumState.RUNNING
                        and abs(poller.latest.speed_mm_s - 60.0) < 1.5, 90), poller.latest
        qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: poller.latest.state == DrumState.IDLE and abs(poller.latest.speed_mm_s) < 0.5,
                        30), poller.latest
    finally:
        window.connect_source(RigSource("inprocess"))
        assert wait_for(qapp, lambda: window.handle is not None and "simulated rig" in window.source_label.text(), 60)
