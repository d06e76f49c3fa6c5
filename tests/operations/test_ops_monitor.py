"""The rig's monitor (rigctl.operations.RigMonitor, owned by RigControl): it polls the controller's status (feeding
its watchdog), publishes what changed to subscribers, and its dead man's switch stops a rig that moves while the face
that commanded it is silent. Judged on events and counts, never on wall-clock spans (a deadline only bounds a
hang)."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import pytest

from rigctl.core.drum import DrumState, DrumStatus, Fault
from rigctl.operations import RigEvent, RigMonitor, RigSource, open_control

#: a generous bound on a wait for an event: only a hang reaches it (the machine may be loaded 3x)
HANG_S = 30.0


class FakeDrum:
    """A drum controller's status, as tests set it; counts the reads (each would feed the watchdog)."""

    def __init__(self, state=DrumState.IDLE, speed=0.0, target=0.0):
        self.status = DrumStatus(force_g=0.0, speed_mm_s=speed, speed_target_mm_s=target, angle_deg=0.0,
                                 revolutions=0, actuator_mm=0.0, state=state, faults=Fault(0), firmware=(1, 0),
                                 heartbeat=0, loadcell_raw=0, force_setpoint_active_g=0.0)
        self.reads = 0
        self.fail = False

    def read_status(self) -> DrumStatus:
        if self.fail:
            raise OSError("port gone")
        self.reads += 1
        return self.status


class Events:
    """A subscriber that keeps every event and lets a test wait for one."""

    def __init__(self):
        self.seen: list[RigEvent] = []
        self._cv = threading.Condition()

    def __call__(self, ev: RigEvent) -> None:
        with self._cv:
            self.seen.append(ev)
            self._cv.notify_all()

    def wait(self, pred, timeout_s: float = HANG_S) -> RigEvent | None:
        with self._cv:
            ok = self._cv.wait_for(lambda: any(pred(e) for e in self.seen), timeout_s)
            return next(e for e in self.seen if pred(e)) if ok else None

    def kinds(self) -> list[str]:
        return [e.kind for e in self.seen if e.kind != "status"]


def test_the_monitor_publishes_state_faults_and_link_changes():
    drum = FakeDrum()
    mon = RigMonitor(drum, stop=lambda reason: True, period_s=0.01)
    events = Events()
    unsubscribe = mon.subscribe(events)
    mon.start()
    try:
        assert events.wait(lambda e: e.kind == "state" and "IDLE" in e.message)
        drum.status = replace(drum.status, state=DrumState.FAULT, faults=Fault.FORCE_LIMIT)
        ev = events.wait(lambda e: e.kind == "faults")
        assert ev is not None and "FORCE_LIMIT" in ev.message and ev.status.faults == Fault.FORCE_LIMIT
        drum.fail = True
        assert events.wait(lambda e: e.kind == "link" and "not answering" in e.message)
        assert not mon.ok and "port gone" in mon.error
        drum.fail = False
        drum.status = replace(drum.status, state=DrumState.IDLE, faults=Fault(0))
        assert events.wait(lambda e: e.kind == "faults" and e.message == "faults cleared")
        assert "answering again" in " ".join(e.message for e in events.seen if e.kind == "link")
        assert mon.ok and mon.latest.state == DrumState.IDLE and len(mon.history.snapshot()) == mon.reads
        # one event each, in order; a failing subscriber never stops the others or the monitor
        assert events.kinds() == ["state", "state", "faults", "link", "link", "state", "faults"]
        mon.subscribe(lambda e: 1 / 0)
        reads = mon.reads
        assert events.wait(lambda e: e.kind == "status" and mon.reads > reads + 3)
        unsubscribe()
        n = len(events.seen)
        mon.publish(RigEvent("progress", "trial 3 of 8", time.monotonic()))
        assert len(events.seen) == n
    finally:
        mon.close()
    assert not mon.running


def test_on_a_simulated_rigs_clock_the_poll_feeds_the_watchdog_in_the_rigs_time():
    """Issue 55 item 6: the simulated rigs keep the controller's 1 s watchdog. On a rig's shared clock a world may run
    up to 10x faster than real time (rigctl.core.shared_clock); the monitor polls every 0.1 s of the rig's time too,
    not only of the wall's: the longest gap between two polls in the world's time stays well inside 1 s (the old
    wall-clock wait let a 20x world run ~0.8 s of its time between polls). A fake world: as far as the clock grants,
    at 20x the wall."""
    from rigctl.core.shared_clock import SharedClock

    t0 = time.monotonic()
    clock = SharedClock(lambda: min(clock.horizon_s, 20.0 * (time.monotonic() - t0)))
    clock.start()
    drum = FakeDrum(state=DrumState.FORCE_SETTLED)
    drum.clock = clock
    polled: list[float] = []
    read = drum.read_status
    drum.read_status = lambda: (polled.append(clock.now()), read())[1]
    mon = RigMonitor(drum, lambda reason: True, period_s=0.1).start()
    try:
        deadline = time.monotonic() + HANG_S
        while clock.now() < 5.0 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        mon.close()
        clock.close()
    gaps = [b - a for a, b in zip(polled, polled[1:])]
    assert len(gaps) >= 20 and max(gaps) < 0.25, (len(gaps), max(gaps, default=None))


def test_a_silent_heartbeat_stops_a_moving_rig_and_says_why():
    drum = FakeDrum(DrumState.RUNNING, speed=80.0, target=80.0)
    stops: list[str] = []

    def stop(reason: str) -> bool:
        stops.append(reason)
        drum.status = replace(drum.status, state=DrumState.IDLE, speed_target_mm_s=0.0)
        return True

    mon = RigMonitor(drum, stop=stop, period_s=0.01)
    events = Events()
    mon.subscribe(events)
    hb = mon.heartbeat("GUI thread", timeout_s=0.2)  # then never beaten: a frozen face
    mon.start()
    try:
        ev = events.wait(lambda e: e.kind == "deadman")
        assert ev is not None, events.kinds()
        assert ev.message.startswith("the GUI thread did not answer for") and "while the rig turned" in ev.message
        assert "dead man's switch" in ev.message and mon.deadman == ev.message
        assert stops == [ev.message]  # stopped once: the rig no longer moves under a command
        hb.beat()  # the face wakes: said once, and the rig is not started again
        assert events.wait(lambda e: e.kind == "deadman" and "answers again" in e.message)
        assert len(stops) == 1 and drum.status.state == DrumState.IDLE
    finally:
        mon.close()


def test_no_heartbeat_no_trip_and_an_idle_rig_is_left_alone():
    """A face that owns its run in its own process (the CLI, the server) registers no heartbeat: nothing trips; a
    silent heartbeat over a rig at rest stops nothing."""
    drum = FakeDrum(DrumState.RUNNING, speed=80.0, target=80.0)
    stops: list[str] = []
    mon = RigMonitor(drum, stop=lambda r: stops.append(r) or True, period_s=0.01).start()
    idle = FakeDrum()
    mon2 = RigMonitor(idle, stop=lambda r: stops.append(r) or True, period_s=0.01)
    mon2.heartbeat("GUI thread", timeout_s=0.05)
    mon2.start()
    try:
        deadline = time.monotonic() + HANG_S
        while (drum.reads < 30 or idle.reads < 30) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert drum.reads >= 30 and idle.reads >= 30 and stops == []
    finally:
        mon.close()
        mon2.close()


def test_an_unacknowledged_stop_starves_the_controllers_watchdog():
    """When the dead man's STOP does not get through, no read feeds the watchdog while the face is silent: the
    controller stops the rig itself."""
    drum = FakeDrum(DrumState.RUNNING, speed=80.0, target=80.0)
    mon = RigMonitor(drum, stop=lambda reason: False, period_s=0.01)
    events = Events()
    mon.subscribe(events)
    hb = mon.heartbeat("GUI thread", timeout_s=0.1)
    mon.start()
    try:
        ev = events.wait(lambda e: e.kind == "deadman")
        assert ev is not None and "not acknowledged" in ev.message
        reads = drum.reads
        for _ in range(20):  # 20 periods of the monitor: not one read
            time.sleep(0.01)
        assert drum.reads == reads
        hb.beat()
        assert events.wait(lambda e: e.kind == "deadman" and "answers again" in e.message)
        assert events.wait(lambda e: e.kind == "status" and drum.reads > reads)
    finally:
        mon.close()


@pytest.fixture
def control(tmp_path):
    with open_control(RigSource("inprocess"), seed=5, host_config_path=tmp_path / "rig.json") as c:
        yield c


def test_rig_control_owns_the_monitor_and_its_dead_mans_switch_stops_the_drum(control):
    """On the in-process rig: the drum runs under a face's command, the face falls silent, the library stops the
    drum (RigControl.stop, its STOP listeners first) and says why."""
    heard: list[str] = []
    control.on_stop(heard.append)
    control.run_at(60.0, 300.0)
    mon = control.monitor
    assert mon is control.monitor and mon.running
    events = Events()
    mon.subscribe(events)
    assert events.wait(lambda e: e.kind == "status" and e.status.state == DrumState.RUNNING)
    hb = mon.heartbeat("GUI thread", timeout_s=0.3)
    ev = events.wait(lambda e: e.kind == "deadman")
    assert ev is not None and "GUI thread" in ev.message
    assert heard == [ev.message]
    st = control.status()
    assert st.state != DrumState.RUNNING and st.speed_target_mm_s == 0 and st.force_setpoint_active_g == 0
    hb.close()
    control.close()
    assert not mon.running


QUICK = """
name = "two_trials"
textures = ["A"]
speeds_mm_s = [100]
forces_g = [300]
trials_per_condition = 2
travel_mm = 60
"""


def test_one_event_stream_carries_the_run_and_the_latch_without_starting_the_poll(tmp_path):
    """What ``rigctl acquire`` listens to: a run's progress and trial events and the safety latch (tripped, then
    acknowledged) reach a subscriber of the rig's stream (RigControl.subscribe), and subscribing starts no poll of the
    controller (on the in-process rig a poll would also move its simulated clock)."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.core.faults import parse_fault
    from rigctl.operations import ProtocolRun

    with open_control(RigSource("inprocess", inject=(parse_fault("estop@60+1"),)), seed=5,
                      host_config_path=tmp_path / "rig.json") as c:
        events: list[RigEvent] = []
        c.subscribe(events.append)
        summary = ProtocolRun(c, parse_protocol(QUICK), tmp_path / "s.h5", on_latch="end").run()
        assert summary.ok
        kinds = {e.kind for e in events}
        assert {"progress", "run"} <= kinds and not kinds & {"status", "state"}  # nothing polled
        done = [e.progress.done for e in events if e.kind == "progress" and e.progress.total]
        assert done[-1] == 2
        assert [e.trial.kind for e in events if e.kind == "run"].count("complete") == 2
        c.drum.clock.sleep(61.0 - c.drum.clock.now())  # the e-stop, pressed while idle: the owner's check latches it
        c.status()
        latch = [e for e in events if e.kind == "latch"]
        assert len(latch) == 1 and "e-stop" in latch[0].message and latch[0].latch is c.latch
        c.drum.clock.sleep(1.5)
        c.acknowledge("released", by="pytest")
        assert [e.kind for e in events][-1] == "latch" and "acknowledged by pytest" in events[-1].message
        assert c._monitor is not None and not c._monitor.running  # the stream, never the poll
