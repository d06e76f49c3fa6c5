"""Issue 35 in a real Qt window (offscreen): nothing slow on the GUI thread, the library's dead man's switch, and
what STOP and Esc mean during a run.

- The first analysis job (Encode) starts without stalling the GUI thread: its longest stall, measured with a QTimer
  heartbeat while a fresh fork server loads the analysis stack, stays under 100 ms plus twice the longest delay a
  probe thread of the same process saw over the same span (the machine's load, not the app); and none of the fork
  server's blocking calls runs on the GUI thread.
- A GUI thread frozen for 1 s while the drum turns: the library stops the drum and the window says why when it wakes.
- Esc closing a drop-down during a run stops nothing; Esc with no popup is STOP, which stops the run resumably, and
  Resume completes the session.
"""

from __future__ import annotations

import threading
import time

import pytest
from PySide6 import QtCore, QtTest, QtWidgets

from rigctl.acquisition.safety import operator_name
from rigctl.core.drum import DrumState
from rigctl.operations import DEADMAN_TIMEOUT_S
from rigctl.operations._control import rig_of
from rigctl.storage.session import open_session
from rigctl_gui.events import wait_for

from .conftest import TEST_DEADMAN_S, gui_protocol, run_queue_wait_s

#: how long the GUI thread may stall while the first analysis job starts, s (issue 35)
MAX_STALL_S = 0.1

class Stalls(QtCore.QObject):
    """A QTimer on the GUI thread every 5 ms: the longest gap between two of its ticks, less the time the GUI thread
    itself waited for a CPU within it (the kernel's schedstat, read at each tick), is the GUI thread's longest stall
    of its own making: blocked in a read, waiting for the GIL, or busy. A probe thread of the same process sleeping
    2 ms at a time measures what the machine's load does to the other threads the GUI thread may wait on (its longest
    overshoot): a GUI thread blocked in a read, or kept off the GIL, stalls while the probe keeps its pace (the GIL
    changes hands every few ms). On a loaded CI machine the GUI thread waited up to 1 s in the run queue with 2 ms
    of work done (measured), where the probe, which never works, saw 26-50 ms."""

    def __init__(self):
        super().__init__()
        self.worst_s, self._last, self.when = 0.0, None, ""
        self.worst_gap_s = self.worst_wait_s = 0.0  # the worst stall's gap and run-queue wait
        self.phase = "start"
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self._tick)
        self._halt = threading.Event()
        self.sched_s = 0.0

    def _tick(self):
        now, waited = time.monotonic(), run_queue_wait_s()
        if self._last is not None:
            gap, wait = now - self._last[0], waited - self._last[1]
            if gap - wait > self.worst_s:
                self.worst_s, self.when, self.worst_gap_s, self.worst_wait_s = gap - wait, self.phase, gap, wait
        self._last = (now, waited)

    def _probe(self):
        while not self._halt.is_set():
            t = time.monotonic()
            time.sleep(0.002)
            self.sched_s = max(self.sched_s, time.monotonic() - t - 0.002)

    def __enter__(self):
        self.thread = threading.Thread(target=self._probe, name="sched-probe", daemon=True)
        self.thread.start()
        self.timer.start(5)
        return self

    def __exit__(self, *exc):
        self.timer.stop()
        self._halt.set()
        self.thread.join(5)


@pytest.fixture
def fresh_job_server(monkeypatch):
    """A fork server of the analysis jobs not started yet in this process (another test may have started the
    module-global one): the first job here is a true first job. Stopped afterwards."""
    import multiprocessing.forkserver as fs

    import rigctl_gui.workers as workers
    from rigctl_gui.once import StartOnce

    fresh = fs.ForkServer()
    fresh.callers = []  # the threads that started the server or a process through it (each may block for seconds)
    monkeypatch.setattr(fs, "_forkserver", fresh)

    def recorded(fn):
        def call(*args, **kwargs):
            fresh.callers.append((fn.__name__, threading.current_thread().name))
            return fn(*args, **kwargs)
        return call

    for name in ("ensure_running", "connect_to_new_process"):
        monkeypatch.setattr(fs, name, recorded(getattr(fresh, name)))
    for name in ("get_inherited_fds", "set_forkserver_preload"):
        monkeypatch.setattr(fs, name, getattr(fresh, name))
    monkeypatch.setattr(workers, "_job_server", StartOnce(workers._warm_up, "job-server-start"))  # not started yet
    yield fresh
    fresh._stop()


def test_the_first_analysis_job_never_stalls_the_gui_thread(qapp, gui_home, tmp_path, fresh_job_server):
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.simulation.dataset import generate_dataset
    from rigctl_gui.app import MainWindow

    session = tmp_path / "tiny.h5"
    generate_dataset(parse_protocol('name = "tiny"\ntextures = ["A", "L"]\nspeeds_mm_s = [80]\nforces_g = [500]\n'
                                    'trials_per_condition = 2\nduration_s = 0.3\n'), session, workers=0,
                     progress=False)
    w = MainWindow(autoconnect=False)
    try:
        w.show()
        tab = w.analysis
        w.tabs.setCurrentWidget(tab)
        tab.open(str(session))
        qapp.processEvents()
        assert fresh_job_server._forkserver_pid is None  # no server yet: this Encode starts it
        with Stalls() as stalls:
            assert wait_for(qapp, lambda: stalls._last is not None, 5)  # ticking: a stall in the click counts too
            QtTest.QTest.mouseClick(tab.encode_btn, QtCore.Qt.LeftButton)
            job = tab.job
            assert job is not None

            def phase():
                stalls.phase = "launching" if not job.started.is_set() else "running"
                return tab.job is None

            assert wait_for(qapp, phase, 120), tab.status.text()
        assert "encoded into" in tab.status.text(), tab.status.text()
        assert fresh_job_server._forkserver_pid is not None
        # the calls that block until the server has loaded the analysis stack: never on the GUI thread
        gui = threading.current_thread().name
        assert fresh_job_server.callers and all(who != gui for _, who in fresh_job_server.callers), \
            fresh_job_server.callers
        print(f"GUI thread's longest stall {stalls.worst_s * 1000:.0f} ms ({stalls.when}; a gap of "
              f"{stalls.worst_gap_s * 1000:.0f} ms less {stalls.worst_wait_s * 1000:.0f} ms in the run queue); a probe "
              f"thread's longest delay {stalls.sched_s * 1000:.0f} ms")
        # two threads sampled side by side on a loaded machine see different worst cases: the GUI thread gets
        # MAX_STALL_S beyond twice the probe's (the old code stalled for the server's whole import: seconds)
        assert stalls.worst_s < MAX_STALL_S + 2 * stalls.sched_s, (stalls.worst_s, stalls.sched_s, stalls.worst_gap_s)
    finally:
        w.close()
        w.deleteLater()
        qapp.processEvents()


def _state(window) -> DrumState | None:
    st = window.poller.latest if window.poller is not None else None
    return DrumState(int(st.state)) if st is not None else None


def test_a_frozen_gui_thread_stops_the_turning_drum(inprocess_window, qapp):
    window = inprocess_window
    window.tabs.setCurrentWidget(window.control)
    window.control.speed.setValue(60.0)
    window.control.force.setValue(300.0)
    window.control.command("run")
    assert wait_for(qapp, lambda: _state(window) == DrumState.RUNNING, 30), window.poller.latest
    assert window.poller.deadman is None
    heartbeat = window.rig_events.heartbeat
    assert heartbeat.name == "GUI thread"
    heartbeat.timeout_s = DEADMAN_TIMEOUT_S  # the app's own limit (the shared test windows get a longer one)
    try:
        time.sleep(1.0)  # this test runs on the GUI thread: it does not answer for 1 s
    finally:
        heartbeat.timeout_s = TEST_DEADMAN_S
    st = window.handle.control.status()  # what the library did meanwhile (nobody else commanded the rig)
    assert st.state != DrumState.RUNNING and st.speed_target_mm_s == 0, st
    assert "GUI thread did not answer" in (window.poller.deadman or "") and "limit 0.5 s" in window.poller.deadman
    # the window says why once it wakes (the event waited in the queue)
    assert wait_for(qapp, lambda: "STOPPED by the library" in window.banner.text, 5), window.banner.text
    assert "dead man's switch" in window.events.text()
    window.banner.hide()


def test_esc_closing_a_drop_down_during_a_run_stops_nothing_and_stop_is_resumable(inprocess_window, qapp, qtbot,
                                                                                   tmp_path):
    window = inprocess_window
    tab = window.protocol
    tab.load(gui_protocol(tmp_path, 6))  # 12 trials: the in-process rig records one in a fraction of a second
    out = tmp_path / "esc.h5"
    tab.out_edit.setText(str(out))
    tab.resume_box.setChecked(False)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: tab._current is not None, 60), tab.status.text()
    stops: list[str] = []
    window.handle.control.on_stop(stops.append)
    combo = window.events.level  # the event log's level drop-down, enabled on every tab during a run
    combo.showPopup()
    popup = QtWidgets.QApplication.activePopupWidget()
    assert popup is not None
    QtTest.QTest.keyClick(popup, QtCore.Qt.Key_Escape)
    assert wait_for(qapp, lambda: QtWidgets.QApplication.activePopupWidget() is None, 5)
    done = len(tab._done_ids)
    assert wait_for(qapp, lambda: len(tab._done_ids) > done, 60), tab.status.text()  # the run went on
    assert stops == [] and tab.running and not tab.pause_event.is_set() and tab.stopped_reason is None
    # Esc that no popup takes is STOP: the run stops (the engine's STOP: trial discarded, paused), resumable
    wait_for(qapp, lambda: False, 0.4)  # (past the debounce of one press)
    QtTest.QTest.keyClick(window.tabs.tabBar(), QtCore.Qt.Key_Escape)
    assert wait_for(qapp, lambda: tab._paused and "STOPPED" in tab.status.text(), 30), tab.status.text()
    assert stops == ["the operator pressed STOP"] and tab.stopped_reason == "the operator pressed STOP"
    assert tab.running and tab.resume_btn.isEnabled() and not tab.stop_event.is_set()  # stopped, not aborted
    assert "STOPPED (the operator pressed STOP)" in tab.run_label.text()
    assert not window.control.buttons["run"].isEnabled()  # the run still owns the rig
    assert not any(tab.row_status(r).startswith(("settling", "recording")) for r in range(tab.table.rowCount()))
    assert wait_for(qapp, lambda: _state(window) in (DrumState.IDLE, DrumState.HOMING), 10), window.poller.latest
    done = len(tab._done_ids)
    wait_for(qapp, lambda: False, 0.5)
    assert len(tab._done_ids) == done and _state(window) != DrumState.RUNNING  # nothing moves while stopped
    qtbot.mouseClick(tab.resume_btn, QtCore.Qt.LeftButton)  # Resume records the discarded trial and goes on
    assert wait_for(qapp, lambda: tab.job is None and not tab.running, 120), tab.status.text()
    assert "finished: 12/12" in tab.status.text(), tab.status.text()
    with open_session(out) as s:
        assert s.completed_ids() == list(range(12))


def test_a_latched_e_stop_opens_the_fault_dialog_whose_ok_acknowledges_it(inprocess_window, qapp, qtbot):
    window = inprocess_window
    controller = rig_of(window.handle.control).backend.engine.controller
    controller.set_estop(True)
    assert wait_for(qapp, lambda: window.fault_dialog is not None and window.fault_dialog.isVisible(), 10)
    dlg = window.fault_dialog
    assert "e-stop" in dlg.title.text() and not dlg.isModal()
    assert wait_for(qapp, lambda: "PRESSED" in dlg.estop.text(), 10), dlg.estop.text()
    dlg.reason.setText("a test pressed the e-stop")
    assert not dlg.ok_btn.isEnabled()  # not while the e-stop is pressed
    controller.set_estop(False)  # released: nothing moves, the fault stays latched
    assert wait_for(qapp, lambda: dlg.estop.text() == "released" and dlg.ok_btn.isEnabled(), 10), dlg.estop.text()
    assert int(window.poller.latest.faults) and _state(window) != DrumState.RUNNING
    qtbot.mouseClick(dlg.ok_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: not dlg.isVisible(), 30), dlg.message.text()
    assert f"fault acknowledged by {operator_name()}: a test pressed the e-stop" in window.events.text()
    assert wait_for(qapp, lambda: window.poller.latest is not None and not int(window.poller.latest.faults), 10)


def test_a_frozen_gui_thread_stops_a_protocol_run_resumably(inprocess_window, qapp, qtbot, tmp_path):
    window = inprocess_window
    tab = window.protocol
    tab.load(gui_protocol(tmp_path, 6))
    out = tmp_path / "frozen.h5"
    tab.out_edit.setText(str(out))
    tab.resume_box.setChecked(False)
    qtbot.mouseClick(tab.start_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: len(tab._done_ids) >= 1 and tab._current is not None, 60), tab.status.text()
    heartbeat = window.rig_events.heartbeat
    heartbeat.timeout_s = DEADMAN_TIMEOUT_S
    try:
        time.sleep(1.5)  # the GUI thread does not answer while the run presses and turns the drum
    finally:
        heartbeat.timeout_s = TEST_DEADMAN_S
    assert wait_for(qapp, lambda: tab._paused and "STOPPED" in tab.run_label.text(), 30), tab.status.text()
    assert tab.stopped_reason is not None and "GUI thread did not answer" in tab.stopped_reason, tab.stopped_reason
    assert tab.running and tab.resume_btn.isEnabled()
    st = window.handle.control.status()
    assert st.state != DrumState.RUNNING and st.speed_target_mm_s == 0, st
    tab.request_abort()
    window.banner.hide()
    assert wait_for(qapp, lambda: tab.job is None, 30), tab.status.text()
