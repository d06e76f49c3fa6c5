"""The protocol tab's flows on the in-process rig (the model and controller logic on a simulated clock, a trial in a
fraction of its time): a short protocol records a session file; pause, resume and abort behave; an aborted session
is resumed to completion. The same tab on the simulated rig on ptys, over the wire: test_gui_protocol.py (STOP aborts
a run) and the X11 tests (Esc in a dialog during a run)."""

from __future__ import annotations

import time

from PySide6 import QtCore, QtWidgets

from rigctl.storage.session import open_session
from rigctl_gui.dialogs import open_dialogs
from rigctl_gui.events import wait_for

from .conftest import gui_protocol


def test_protocol_run_records_a_session_file(inprocess_window, qapp, qtbot, tmp_path):
    window = inprocess_window
    tab = window.protocol
    window.tabs.setCurrentWidget(tab)
    tab.load(gui_protocol(tmp_path, 1))
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


def test_pause_resume_abort_and_resume_the_session(inprocess_window, qapp, qtbot, tmp_path):
    window = inprocess_window
    tab = window.protocol
    tab.load(gui_protocol(tmp_path, 10))  # 20 trials: the in-process rig records one in a fraction of a second
    out = tmp_path / "paused.h5"
    tab.out_edit.setText(str(out))
    tab.resume_box.setChecked(False)
    try:
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
            assert 2 <= n_done < 20
        # resume the interrupted file: only the missing trials are recorded
        tab.resume_box.setChecked(True)
        qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
        assert wait_for(qapp, lambda: tab.job is None, 180), tab.status.text()  # (a hang's bound)
        assert "finished: 20/20" in tab.status.text(), tab.status.text()
        with open_session(out) as s:
            assert s.completed_ids() == list(range(20))
    finally:  # (the window is the module's: a run left going failed its rerun at load, 'a protocol is running')
        tab.abort_and_wait(60.0)
