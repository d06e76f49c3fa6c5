"""Protocol tab on the simulated rig on ptys: STOP stops a run, resumable (Abort ends it). Calibration tab: the load
cell is calibrated with a (simulated) known mass and the scale lands in the controller and the rig config. (The
protocol tab's record, pause, resume and abort flows run on the in-process rig: test_gui_protocol_flow.py.)"""

from __future__ import annotations

import json
import os

import pytest
from PySide6 import QtCore

from rigctl.devices.wire import HoldingRegister
from rigctl.operations._control import rig_of
from rigctl_gui.events import wait_for

from .conftest import gui_protocol

# wall: the app's STOP and calibration against the rig on ptys, in a real window's event loop
pytestmark = pytest.mark.realtime

def test_stop_button_stops_a_run_resumably(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    tab.load(gui_protocol(tmp_path, 3))
    tab.out_edit.setText(str(tmp_path / "stopped.h5"))
    tab.resume_box.setChecked(False)
    clock = rig_of(window.handle.control).backend.sim.clock  # the rig's time (a starved machine's wall runs on)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    try:
        assert wait_for(qapp, lambda: tab._current is not None, 30)
        t0 = clock.now()
        qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: tab._paused and "STOPPED" in tab.status.text(), 60), tab.status.text()
        assert clock.now() - t0 < 15  # (a loaded CI run: 15.6 s of wall)
        assert "STOPPED (the operator pressed STOP)" in tab.status.text() and "Resume records" in tab.status.text()
        statuses = [tab.row_status(r) for r in range(tab.table.rowCount())]
        assert "stopped (not recorded: recorded again on Resume)" in statuses, statuses  # the trial cut short says so
        assert not any(st.startswith(("settling", "recording", "mounting")) for st in statuses), statuses
        # stopped, not aborted: the run still owns the rig, Resume or Abort
        assert tab.running and tab.resume_btn.isEnabled() and tab.abort_btn.isEnabled()
        assert not tab.start_btn.isEnabled()
    finally:  # (the window is the module's: a run left going failed every test after this one too)
        tab.request_abort()
        aborted = wait_for(qapp, lambda: tab.job is None, 60)
    assert aborted and "aborted" in tab.status.text(), tab.status.text()


def test_loadcell_calibration_with_a_known_mass(window, qapp, qtbot):
    tab = window.calibration
    window.tabs.setCurrentWidget(tab)
    tab.mass.setValue(200.0)
    qtbot.mouseClick(tab.loadcell_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab.job is None, 60), tab.status.text()
    assert "counts/g written" in tab.status.text(), tab.status.text()
    cfg = json.loads(open(os.environ["RIGCTL_CONFIG"]).read())
    lc = cfg["loadcell"]
    assert lc["mass_g"] == 200.0
    assert abs(lc["check_force_g"] - 200.0) < 10
    reg = window.handle.drum.read_holding(HoldingRegister.LOADCELL_SCALE_X100)
    assert reg == round(lc["counts_per_g"] * 100)
    assert "200 g mass" in tab.loadcell_info.text()


def test_taxel_calibration_of_an_idle_drum_is_refused_and_undo_restores_the_previous(window, qapp, qtbot):
    """A calibration run with the drum idle (taxels span ~16 counts: noise) is refused and changes nothing; Undo
    and Reset move between the stored normalisations, and the live encoder follows each."""
    import numpy as np

    from rigctl.acquisition import calibration as cal

    tab = window.calibration
    window.tabs.setCurrentWidget(tab)
    cfg_path = os.environ["RIGCTL_CONFIG"]
    old = cal.TaxelNormalisation(np.full(18, 100.0), np.full(18, 700.0), 3, "older run", "2026-01-01T00:00:00")
    cur = cal.TaxelNormalisation(np.full(18, 150.0), np.full(18, 650.0), 5, "last run", "2026-01-02T00:00:00")
    cal.store_taxel_normalisation(old, cfg_path)
    cal.store_taxel_normalisation(cur, cfg_path)
    tab.show_config()
    before = json.loads(open(cfg_path).read())
    tab.norm_seconds.setValue(1)
    qtbot.mouseClick(tab.norm_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab.job is None, 30), tab.status.text()
    assert "spans only" in tab.status.text() and "Not stored" in tab.status.text(), tab.status.text()
    assert json.loads(open(cfg_path).read()) == before  # the calibration in use is unchanged
    # Undo: the older run is back, in the config and in the live encoder
    assert tab.undo_btn.isEnabled()
    qtbot.mouseClick(tab.undo_btn, QtCore.Qt.LeftButton)
    cfg = json.loads(open(cfg_path).read())
    assert cfg["taxel_normalisation"]["source"] == "older run"
    assert cfg["taxel_normalisation_previous"]["source"] == "last run"
    assert window.encoder.normaliser.maximum.tolist() == [700.0] * 18
    assert "older run" in tab.norm_info.text()
    # Reset: the full ADC range; Undo brings the older run back
    qtbot.mouseClick(tab.reset_btn, QtCore.Qt.LeftButton)
    assert "taxel_normalisation" not in json.loads(open(cfg_path).read())
    assert window.encoder.normaliser.maximum.tolist() == [1023.0] * 18
    qtbot.mouseClick(tab.undo_btn, QtCore.Qt.LeftButton)
    assert json.loads(open(cfg_path).read())["taxel_normalisation"]["source"] == "older run"
    qtbot.mouseClick(tab.reset_btn, QtCore.Qt.LeftButton)  # leave the full range for the tests after this one


def test_open_protocol_offers_the_built_in_protocols(window, qapp):
    """The protocols that ship with rigctl are one choice away (the drop-down) and in the file dialog's side bar."""
    from rigctl.acquisition.builtin import builtin_folder, builtin_protocols

    tab = window.protocol
    names = [tab.builtin.itemText(i) for i in range(1, tab.builtin.count())]
    assert names == list(builtin_protocols()) and "quick_check" in names
    i = names.index("quick_check") + 1
    tab.builtin.activated.emit(i)  # what choosing it in the drop-down does
    assert tab.protocol is not None and tab.path_label.text().endswith("quick_check.toml"), tab.path_label.text()
    assert tab.table.rowCount() == len(tab.plan) > 0 and tab.builtin.currentIndex() == 0
    dlg = tab._browse_protocol()
    try:
        assert str(builtin_folder()) in [u.toLocalFile() for u in dlg.sidebarUrls()]
    finally:
        dlg.reject()


def test_publish_on_lsl_follows_the_rig_config_and_says_what_is_missing(window, qapp, tmp_path, monkeypatch):
    import sys
    from types import SimpleNamespace

    tab = window.protocol
    tab.take_rig_defaults(SimpleNamespace(host_config={"lsl": {"enabled": True}}))
    assert tab.lsl_box.isChecked()  # the rig config switches it on ...
    tab.take_rig_defaults(window.handle.control)
    assert not tab.lsl_box.isChecked()  # ... the test rig's config says nothing: off
    tab.load(gui_protocol(tmp_path, 1))
    out = tmp_path / "lsl.h5"
    tab.out_edit.setText(str(out))
    monkeypatch.setitem(sys.modules, "pylsl", None)  # import pylsl raises ImportError
    tab.lsl_box.setChecked(True)
    tab.start()
    assert not tab.running and not out.exists()
    assert "pip install 'rigctl[lsl]'" in tab.status.text() and "untick" in tab.status.text()
    tab.lsl_box.setChecked(False)
