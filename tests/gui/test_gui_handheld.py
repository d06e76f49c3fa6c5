"""The handheld tab (issue 37) in a real main window, offscreen: it opens the handheld rig through the operations
layer, runs the calibration block and the real-time block of a small protocol on the simulated operator, shows each
prompt the rig gives its operator (plate, profile, go: the simulated operator scans what the cue said) and each
scan's end-of-scan prediction as a big letter, green when right and red when wrong; the predictions land in the
session file."""

from __future__ import annotations

import pytest
from PySide6 import QtCore, QtTest

from rigctl_gui.events import wait_for

from ..conftest import small_handheld_protocol

SMALL = small_handheld_protocol("B", "L")


@pytest.fixture
def handheld_window(qapp, gui_home, tmp_path):
    from rigctl_gui.app import MainWindow, configure_pyqtgraph

    configure_pyqtgraph()
    w = MainWindow(autoconnect=False)
    w.resize(1280, 800)
    w.show()
    w.tabs.setCurrentWidget(w.handheld)
    (tmp_path / "small.toml").write_text(SMALL)
    w.handheld.protocols = {"calibration": str(tmp_path / "small.toml"), "realtime": str(tmp_path / "small.toml")}
    w.handheld.out_dir.setText(str(tmp_path / "out"))
    yield w
    w.close()
    w.deleteLater()
    qapp.processEvents()


def test_the_handheld_blocks_with_prompts_and_predictions(handheld_window, qapp):
    from rigctl.storage.session import open_session

    tab = handheld_window.handheld
    click = QtCore.Qt.MouseButton.LeftButton
    QtTest.QTest.mouseClick(tab.open_btn, click)
    assert wait_for(qapp, lambda: tab.control is not None, 60)
    prompts = []
    tab.control.subscribe(lambda ev: prompts.append(dict(ev.fields)) if ev.kind == "prompt" else None)
    QtTest.QTest.mouseClick(tab.cal_btn, click)
    assert wait_for(qapp, lambda: tab.calibration_enc is not None, 120), tab.status.text()
    # the rig's prompts, in the plan's order: the plate, then a go cue per scan with its profile
    assert [(p["cue"], p["texture"], p.get("profile")) for p in prompts] == [
        ("plate", "B", None), ("go", "B", "fast"), ("go", "B", "slow-to-fast"),
        ("plate", "L", None), ("go", "L", "fast"), ("go", "L", "slow-to-fast")]
    cal = tab.last_output
    with open_session(cal) as s:  # the simulated operator scanned what each cue said
        done = [(s.trial(t).attrs["operator_texture"], s.trial(t).attrs["operator_profile"]) for t in s.completed_ids()]
    assert done == [(p["texture"], p["profile"]) for p in prompts if p["cue"] == "go"]
    assert tab.cue_plate.text() == "" and "4/4 scans" in tab.cue_text.text()

    tab.training.setText(tab.calibration_enc)  # a classifier trained on this block (enough for the view)
    QtTest.QTest.mouseClick(tab.rt_btn, click)
    assert wait_for(qapp, lambda: len(tab.board.results) == 4 and tab.run is None and tab.job is None, 120), \
        tab.status.text()
    trial_id, truth, predicted = tab.board.results[-1]
    assert tab.board.latest.text() == predicted
    assert tab.board.latest.property("correct") == (truth == predicted)
    assert ("#2a2" if truth == predicted else "#d22") in tab.board.latest.styleSheet()
    assert [r[1] for r in tab.board.results] == ["B", "B", "L", "L"]
    with open_session(tab.last_output) as s:
        logged = [(e["trial_id"], e["truth"], e["predicted"]) for e in s.events if e["kind"] == "prediction"]
    assert logged == tab.board.results
    assert tab.cal_btn.isEnabled() and tab.rt_btn.isEnabled()
