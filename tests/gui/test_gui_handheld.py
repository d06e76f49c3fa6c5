"""The handheld tab (issue 37) in a real main window, offscreen: it connects the window to the handheld rig (the
window's one rig, through the operations layer), runs the calibration block and the real-time block of a small
protocol on the simulated operator, shows each prompt the rig gives its operator (plate, profile, go: the simulated
operator scans what the cue said) and each scan's end-of-scan prediction as a big letter, green when right and red
when wrong; the predictions land in the session file. A block is the rig's run: the main STOP (and Esc) pauses it,
the operator told to lift the finger, Resume goes on at the next cue and completes it; Abort block ends it only once
confirmed."""

from __future__ import annotations

import threading

import pytest
from PySide6 import QtCore, QtTest, QtWidgets

from rigctl_gui.dialogs import open_dialogs
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
    assert wait_for(qapp, lambda: tab.control is not None and tab.cal_btn.isEnabled(), 60)
    assert tab.control is handheld_window.handle.control  # the window's one rig, not the tab's own
    assert wait_for(qapp, lambda: handheld_window.drum_state.text() == "Drum: none (handheld rig)", 5)
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


@pytest.fixture
def slow_operator(monkeypatch):
    """The simulated operator as a person is: a scan takes until the test lets it go (``gate``), and a STOP during
    it (the rig's ``stop()``) ends it unfinished, as a lifted finger does."""
    from rigctl.simulation.operator import SimulatedOperator

    gate = threading.Event()
    scan = SimulatedOperator.scan

    def slow_scan(self, planned, *, stop=None):
        while not gate.wait(0.02):
            if stop is not None and stop():
                return None
        return scan(self, planned, stop=stop)

    monkeypatch.setattr(SimulatedOperator, "scan", slow_scan)
    return gate


def _abort_question_button(text: str) -> QtWidgets.QAbstractButton:
    """The button ``text`` of the handheld tab's question "Abort the handheld block?" on screen: that question by
    its title, not the first message box open (in CI a message box of an earlier test in the same worker process,
    still open, was taken for it: StopIteration on its buttons)."""
    boxes = [d for d in open_dialogs() if isinstance(d, QtWidgets.QMessageBox)]
    box = next((d for d in boxes if d.windowTitle() == "Abort the handheld block?"), None)
    assert box is not None, [d.windowTitle() for d in boxes]
    return next(b for b in box.buttons() if b.text() == text)


def test_stop_pauses_a_block_resume_completes_it_and_abort_asks(handheld_window, qapp, slow_operator):
    from rigctl.storage.session import open_session

    w, tab, gate = handheld_window, handheld_window.handheld, slow_operator
    click = QtCore.Qt.MouseButton.LeftButton
    QtTest.QTest.mouseClick(tab.open_btn, click)
    assert wait_for(qapp, lambda: tab.control is not None and tab.cal_btn.isEnabled(), 60)
    prompts = []
    tab.control.subscribe(lambda ev: prompts.append(dict(ev.fields)) if ev.kind == "prompt" else None)
    QtTest.QTest.mouseClick(tab.cal_btn, click)
    assert wait_for(qapp, lambda: [p["cue"] for p in prompts] == ["plate", "go"], 30), prompts
    assert not w.connect_btn.isEnabled()  # the block owns the rig

    QtTest.QTest.mouseClick(w.stop_btn, click)  # the main STOP, during the first scan
    assert wait_for(qapp, lambda: tab.run.state == "paused", 30), tab.status.text()
    assert prompts[-1]["cue"] == "stop"  # the rig told its operator
    assert wait_for(qapp, lambda: "lift the finger" in tab.cue_text.text(), 5), tab.cue_text.text()
    assert tab.cue.property("cue") == "stop" and "the operator pressed STOP" in tab.cue_text.text()
    assert tab.resume_btn.isEnabled() and tab.abort_btn.isEnabled()
    gate.set()  # the operator is ready again: nothing is recorded before Resume
    wait_for(qapp, lambda: False, 0.5)
    assert tab.run.state == "paused" and [p["cue"] for p in prompts].count("go") == 1
    gate.clear()
    QtTest.QTest.mouseClick(tab.resume_btn, click)
    # the discarded scan is cued again (the next cue), then the block goes on to its end
    assert wait_for(qapp, lambda: [p["cue"] for p in prompts].count("go") == 2, 30), prompts
    assert prompts[-1]["trial_id"] == prompts[1]["trial_id"]
    assert tab.cue.property("cue") != "stop" or wait_for(qapp, lambda: tab.cue.property("cue") == "go", 5)
    gate.set()
    assert wait_for(qapp, lambda: tab.run is None and tab.calibration_enc is not None, 120), tab.status.text()
    with open_session(tab.last_output) as s:
        assert len(s.completed_ids()) == len(s.plan) == 4 and not s.failed_ids()
    first = tab.last_output

    gate.clear()
    del prompts[:]
    QtTest.QTest.mouseClick(tab.cal_btn, click)
    assert wait_for(qapp, lambda: tab.run is not None and tab.last_output != first
                    and [p["cue"] for p in prompts][-1:] == ["go"], 30), prompts
    QtTest.QTest.keyClick(w.tabs.tabBar(), QtCore.Qt.Key.Key_Escape)  # Esc is STOP in the window
    assert wait_for(qapp, lambda: tab.run.state == "paused", 30), tab.status.text()
    QtTest.QTest.mouseClick(tab.abort_btn, click)  # asks first; keeping the block keeps it stopped
    QtTest.QTest.mouseClick(_abort_question_button("Keep the block"), click)
    wait_for(qapp, lambda: False, 0.5)
    assert tab.block_running and tab.run.state == "paused" and not tab.run.stop_event.is_set()
    QtTest.QTest.mouseClick(tab.abort_btn, click)
    QtTest.QTest.mouseClick(_abort_question_button("Abort the block"), click)
    assert wait_for(qapp, lambda: tab.run is None, 30), tab.status.text()
    assert "aborted" in tab.status.text()
    assert wait_for(qapp, lambda: w.connect_btn.isEnabled(), 5)  # the rig is the window's again
    with open_session(tab.last_output) as s:
        assert len(s.completed_ids()) == 0 and len(s.plan) == 4
