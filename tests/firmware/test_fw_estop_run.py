"""The safety policy on the real firmware under simavr (issue 35's done-when): an e-stop held mid-run (``--inject
estop@T+D`` through the harness's e-stop contact) latches the run; after its release nothing moves for 10 s of the
Mega's simulated time (the harness's reports: actuator steps, drum steps, the spring's force); the operator's
acknowledgement moves nothing for 10 s more (the run paused), and only Resume (the start) goes on: the plan
completes. The in-process twin: tests/acquisition/test_acq_safety.py."""

from __future__ import annotations

import time

import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.core.drum import DrumState, Fault
from rigctl.core.faults import parse_fault
from rigctl.operations import ProtocolRun, RigSource, open_control
from rigctl.operations._control import rig_of
from rigctl.storage.session import open_session

pytestmark = pytest.mark.hil

#: two short trials on one plate: the e-stop comes 3 s after the rig opens, inside the first trial or its press; the
#: second runs only after the acknowledgement (each trial costs ~8 s of the Mega's time: press, settle, run, release)
PROTOCOL = ('name = "estop_hil"\ntextures = ["A"]\nspeeds_mm_s = [80]\nforces_g = [300]\n'
            'trials_per_condition = 2\nduration_s = 1.0\n')


def _until(cond, what: str, timeout_s: float = 180.0) -> None:
    """Wait (host time, a bound on a hang only: simavr falls behind real time on a loaded machine)."""
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def test_estop_held_mid_run_on_the_firmware_pauses_until_acknowledged(fw_build, tmp_path):
    control = open_control(RigSource("hil", inject=(parse_fault("estop@3+2"),)))
    with control:
        hil = rig_of(control).backend.sim
        run = ProtocolRun(control, parse_protocol(PROTOCOL), tmp_path / "s.h5").start()
        _until(lambda: run.state in ("latched", "done", "failed"), "the latch")
        assert run.state == "latched" and control.latch is not None and control.latch.cause == "estop"
        _until(lambda: "estop" not in hil.faults.active and hil.schedule.pending == 0, "the e-stop's release")
        released = hil.next_telemetry()
        # 10 s of the Mega's own time after the release: no step of either motor, the drivers still off, the force
        # where the e-stop left it (a stop of category 0: the actuator's drivers lose power where they are; the load
        # on the sensor does not rise)
        later = hil._wait_telemetry(released.t_s + 10.0, timeout_s=60.0)
        assert (later.act_steps, later.drum_steps) == (released.act_steps, released.drum_steps)
        assert not later.drivers_enabled and later.steps_disabled == released.steps_disabled
        assert later.force_g <= released.force_g + 5.0
        st = control.drum.read_status()
        assert st.state == DrumState.FAULT and Fault.ESTOP in st.faults and run.state == "latched"
        ack = control.acknowledge("e-stop released, bench checked", by="pytest")
        assert ack.latch.cause == "estop" and control.latch is None
        # acknowledging is not starting: the run pauses and nothing moves for 10 s more of the Mega's time
        _until(lambda: run.state == "paused", "the pause after the acknowledgement")
        acked = hil.next_telemetry()
        later = hil._wait_telemetry(acked.t_s + 10.0, timeout_s=60.0)
        assert (later.act_steps, later.drum_steps) == (acked.act_steps, acked.drum_steps)
        assert run.state == "paused" and run.summary is None
        run.resume()  # the start: HOME, TARE, the trial recorded again
        summary = run.wait(300)
    assert summary is not None and summary.ok and summary.complete == 2
    with open_session(tmp_path / "s.h5") as s:
        kinds = [e["kind"] for e in s.events]
    assert kinds == ["latched", "acknowledged"]
