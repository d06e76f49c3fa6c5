"""Protocol tab on the simulated rig: a short protocol records a session file; pause, resume and abort behave; an
aborted session is resumed to completion. Calibration tab: the load cell is calibrated with a (simulated) known
mass and the scale lands in the controller and the rig config."""

from __future__ import annotations

import json
import os
import time

import pytest
from PySide6 import QtCore, QtWidgets

from rigctl.devices.wire import HoldingRegister
from rigctl.storage.session import open_session
from rigctl_gui.dialogs import open_dialogs
from rigctl_gui.events import wait_for

pytestmark = pytest.mark.realtime

PROTOCOL = """
name = "gui_test"
description = "GUI test: two textures, short trials"
textures = ["A", "L"]
speeds_mm_s = [100]
forces_g = [300]
trials_per_condition = {n}
duration_s = 0.3
order = "blocked"

[settle]
force_timeout_s = 10
speed_timeout_s = 5
speed_tolerance_mm_s = 3
"""


def _protocol(tmp_path, n):
    p = tmp_path / f"gui_test_{n}.toml"
    p.write_text(PROTOCOL.format(n=n))
    return str(p)


def test_protocol_run_records_a_session_file(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    window.tabs.setCurrentWidget(tab)
    tab.load(_protocol(tmp_path, 1))
    assert tab.table.rowCount() == 2
    assert "2 trials" in tab.summary.text() and "textures A, L" in tab.summary.text()
    out = tmp_path / "run.h5"
    tab.out_edit.setText(str(out))
    tab._trial_started = time.monotonic() - 355.0  # the app has been open a while (the clock of an old trial)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert tab.running
    shown = []  # the trial bar's "trial N: S s" while it runs: each trial's own clock, from its first event

    def done():
        fmt = tab.trial_bar.format()
        if fmt.startswith("trial ") and " s (" in fmt:
            shown.append(float(fmt.split(": ")[1].split(" s")[0]))
        return tab.job is None

    assert wait_for(qapp, done, 60), tab.status.text()
    assert shown and max(shown) < 30, shown
    assert "finished: 2/2" in tab.status.text(), tab.status.text()
    assert [tab.table.item(r, 6).text() for r in range(2)] == ["recorded", "recorded"]
    with open_session(out) as s:
        assert s.completed_ids() == [0, 1]
        tr = s.trial(1)
        assert tr.taxels.shape == (300, 18)
        assert s.plan["texture"][1] in (b"L", "L")


def test_pause_resume_abort_and_resume_the_session(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    tab.load(_protocol(tmp_path, 3))
    out = tmp_path / "paused.h5"
    tab.out_edit.setText(str(out))
    tab.resume_box.setChecked(False)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: len(tab._done_ids) >= 1, 60), tab.status.text()
    qtbot.mouseClick(tab.pause_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab._paused, 30), tab.status.text()
    assert "PAUSED" in tab.status.text()
    assert tab.resume_btn.isEnabled() and not tab.pause_btn.isEnabled()
    done = len(tab._done_ids)
    wait_for(qapp, lambda: False, 1.0)
    assert len(tab._done_ids) == done  # nothing recorded while paused
    qtbot.mouseClick(tab.resume_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: len(tab._done_ids) > done, 60), tab.status.text()
    qtbot.mouseClick(tab.abort_btn, QtCore.Qt.LeftButton)  # Abort asks first; Esc in the question keeps the run
    box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
    qtbot.keyClick(box, QtCore.Qt.Key_Escape)
    wait_for(qapp, lambda: False, 0.5)
    assert tab.running and not tab.stop_event.is_set()
    qtbot.mouseClick(tab.abort_btn, QtCore.Qt.LeftButton)
    box = next(d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox))
    qtbot.mouseClick(next(b for b in box.buttons() if b.text() == "Abort the run"), QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab.job is None, 30), tab.status.text()
    assert "aborted" in tab.status.text()
    with open_session(out) as s:
        n_done = len(s.completed_ids())
        assert 2 <= n_done < 6
    # resume the interrupted file: only the missing trials are recorded
    tab.resume_box.setChecked(True)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab.job is None, 90), tab.status.text()
    assert "finished: 6/6" in tab.status.text(), tab.status.text()
    with open_session(out) as s:
        assert s.completed_ids() == list(range(6))


def test_stop_button_aborts_a_run(window, qapp, qtbot, tmp_path):
    tab = window.protocol
    tab.load(_protocol(tmp_path, 3))
    tab.out_edit.setText(str(tmp_path / "stopped.h5"))
    tab.resume_box.setChecked(False)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab._current is not None, 30)
    t0 = time.monotonic()
    qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab.job is None, 20), tab.status.text()
    assert time.monotonic() - t0 < 15
    assert "aborted" in tab.status.text()
    statuses = [tab.row_status(r) for r in range(tab.table.rowCount())]
    assert "aborted (not recorded)" in statuses, statuses  # the trial cut short says so
    assert not any(st.startswith(("settling", "recording", "mounting")) for st in statuses), statuses


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
    tab.take_rig_defaults(window.handle.rig)
    assert not tab.lsl_box.isChecked()  # ... the test rig's config says nothing: off
    tab.load(_protocol(tmp_path, 1))
    out = tmp_path / "lsl.h5"
    tab.out_edit.setText(str(out))
    monkeypatch.setitem(sys.modules, "pylsl", None)  # import pylsl raises ImportError
    tab.lsl_box.setChecked(True)
    tab.start()
    assert not tab.running and not out.exists()
    assert "pip install 'rigctl[lsl]'" in tab.status.text() and "untick" in tab.status.text()
    tab.lsl_box.setChecked(False)
