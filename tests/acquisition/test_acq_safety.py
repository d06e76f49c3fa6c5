"""The safety policy (docs/safety.md) on the in-process rig, on simulated time: a latched fault pauses the run, its
release moves nothing, only an operator's acknowledgement goes on; the same for a Python protocol (a plan); the
CLI ends such a run with why and how to acknowledge, and ``--resume`` acknowledges it and completes the plan."""

from __future__ import annotations

import shlex
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.safety import LatchedFault
from rigctl.cli import main as cli
from rigctl.core.drum import DrumState, Fault
from rigctl.core.faults import parse_fault
from rigctl.operations import ProtocolRun, RigSource, open_control
from rigctl.operations._control import rig_of
from rigctl.storage.session import open_session

EXAMPLE_PLAN = Path(__file__).resolve().parents[2] / "rigctl" / "protocols" / "example_script.py"


def _until(cond, what: str, timeout_s: float = 120.0) -> None:
    """Wait (wall time, generous: a loaded machine) until ``cond()``; the run thread moves the simulated clock."""
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def _estop_held_then_acknowledged(tmp_path: Path, protocol, n_trials: int) -> None:
    control = open_control(RigSource("inprocess", inject=(parse_fault("estop@3+2"),)))
    with control:
        backend = rig_of(control).backend
        engine, model, mega = backend.engine, backend.model, backend.controller
        t0 = engine.schedule._t0
        run = ProtocolRun(control, protocol, tmp_path / "s.h5").start()  # on_latch="wait": the GUI's and server's
        _until(lambda: run.state == "latched" or run.state == "done", "the latch")
        assert run.state == "latched" and control.latch is not None and control.latch.cause == "estop"
        _until(lambda: engine.time_s > t0 + 5.2, "the e-stop's release")
        assert not mega.estop_open  # released ...
        pos, act = model.position_mm, model.actuator_mm
        _until(lambda: engine.time_s > t0 + 15.3, "10 s after the release")
        # ... and nothing moved for 10 s of simulated time: the run waits for the operator
        assert model.position_mm == pos and model.actuator_mm == act and model.drum_speed_mm_s == 0.0
        st = control.drum.read_status()
        assert st.state == DrumState.FAULT and Fault.ESTOP in st.faults and not mega.drivers_enabled
        assert run.state == "latched"
        with pytest.raises(LatchedFault, match="resume refused: e-stop"):
            run.resume()  # no start while latched
        ack = control.acknowledge("e-stop released, bench checked", by="pytest")
        assert ack.latch.cause == "estop" and control.latch is None
        # acknowledging is not starting: the run pauses, and nothing moves for 10 s of simulated time (the
        # actuator the e-stop stranded stays where it stopped, the drum still)
        _until(lambda: run.state == "paused", "the pause after the acknowledgement")
        control.drum.clock.sleep(10.0)  # the paused run reads nothing: the test moves the rig's clock
        assert model.position_mm == pos and model.actuator_mm == act and model.drum_speed_mm_s == 0.0
        assert run.state == "paused" and run.summary is None

        def logged() -> list[str]:
            with open_session(tmp_path / "s.h5") as s:
                return [e["kind"] for e in s.events]

        # both in the session while the run is paused (the paused run writes them every 50 ms of wall time; the
        # 10 s above were the in-process rig's, which may pass in less)
        _until(lambda: logged() == ["latched", "acknowledged"], "the acknowledgement in the session", 30.0)
        assert run.state == "paused"
        run.resume()  # the start: HOME, TARE, and the trial recorded again
        summary = run.wait(120)
    assert summary is not None and summary.ok and summary.complete == n_trials
    with open_session(tmp_path / "s.h5") as s:
        events = s.events
    assert [e["kind"] for e in events] == ["latched", "acknowledged"]
    assert events[1]["by"] == "pytest" and events[1]["clears"]["cause"] == "estop"


def test_estop_held_mid_run_pauses_until_acknowledged(tmp_path):
    _estop_held_then_acknowledged(tmp_path, load_protocol(find_protocol("quick_check")), 6)


def test_estop_held_mid_python_plan_pauses_until_acknowledged(tmp_path):
    _estop_held_then_acknowledged(tmp_path, load_protocol(EXAMPLE_PLAN), 6)


def test_acknowledgement_refused_while_the_estop_is_pressed():
    with open_control(RigSource("inprocess", inject=(parse_fault("estop@0.1"),))) as control:
        with pytest.raises(LatchedFault, match="PRESS refused"):
            clock = control.drum.clock
            clock.sleep(0.2)
            control.status()  # the owner's poll latches what the controller latched
            control.press(300.0)
        assert control.latch is not None and control.latch.cause == "estop"
        with pytest.raises(LatchedFault, match="still pressed"):
            control.acknowledge("trying", by="pytest")
        with pytest.raises(LatchedFault):
            control.run_at(50.0, 300.0)  # nothing moves while latched
        assert control.latch is not None


def _safety_doc_commands() -> list[list[str]]:
    """The two commands of docs/safety.md's e-stop example, as argument lists."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "safety.md").read_text()
    block = text.split("An e-stop held for 2 s", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    lines = [shlex.split(line) for line in block.strip().splitlines()]
    assert [line[:2] for line in lines] == [["rigctl", "acquire"]] * 2 and "--resume" in lines[1]
    return [line[1:] for line in lines]


@pytest.mark.parametrize("protocol", ["quick_check", str(EXAMPLE_PLAN)])
def test_cli_ends_on_estop_and_resume_acknowledges_it(tmp_path, monkeypatch, protocol):
    """docs/safety.md's commands as written (and with the Python plan): the run ends on the e-stop saying why and
    how to acknowledge; --resume acknowledges it (logged with the fault it clears) and completes the plan."""
    monkeypatch.chdir(tmp_path)
    first_args, second_args = ([protocol if a == "quick_check" else a for a in args] + ["--quiet"]
                               for args in _safety_doc_commands())
    runner = CliRunner()
    first = runner.invoke(cli, first_args)
    out = tmp_path / "a.h5"
    assert first.exit_code == 1, first.output
    assert "e-stop" in first.output and "--resume" in first.output and "acknowledge" in first.output
    with open_session(out) as s:
        assert len(s.completed_ids()) < 6 and [e["kind"] for e in s.events] == ["latched"]
    second = runner.invoke(cli, second_args)
    assert second.exit_code == 0, second.output
    with open_session(out) as s:
        assert len(s.completed_ids()) == 6
        assert [e["kind"] for e in s.events] == ["latched", "acknowledged"]
        assert s.events[1]["reason"] == "rigctl acquire --resume" and s.events[1]["clears"]["cause"] == "estop"


def test_stop_discards_the_trial_and_pauses_until_resumed(tmp_path):
    """STOP (RigControl.stop) is not an abort: the trial in progress is discarded, the rig stopped, the run paused;
    resume records that trial again and the plan completes."""
    import threading

    started, stopped = threading.Event(), threading.Event()
    kinds: list[tuple[str, int | None]] = []

    def on_trial(ev):
        kinds.append((ev.kind, None if ev.planned is None else ev.planned.trial_id))
        if ev.kind == "start" and ev.planned.trial_id == 1 and not started.is_set():
            started.set()
            stopped.wait(60)  # the operator hits STOP as trial 1 starts

    with open_control(RigSource("inprocess")) as control:
        run = ProtocolRun(control, load_protocol(find_protocol("quick_check")), tmp_path / "s.h5",
                          on_trial=on_trial).start()
        assert started.wait(120)
        control.stop("pytest STOP")
        stopped.set()
        _until(lambda: run.state == "paused", "the pause after STOP")
        assert control.status().state in (DrumState.IDLE, DrumState.NOT_HOMED) and run.summary is None
        run.resume()
        summary = run.wait(120)
    assert summary is not None and summary.ok and summary.complete == 6
    assert ("halted", 1) in kinds and kinds.count(("complete", 1)) == 1


def test_a_stalled_drum_latches(tmp_path):
    from rigctl.acquisition.runner import run_protocol

    with open_control(RigSource("inprocess", inject=(parse_fault("stall@0+60"),))) as control:
        summary = run_protocol(load_protocol(find_protocol("quick_check")), tmp_path / "s.h5", rig=rig_of(control),
                               progress=False)
        assert summary.stopped and summary.complete == 0 and "drum stalled" in summary.latched
        assert control.latch is not None and control.latch.cause == "stall"
        assert rig_of(control).backend.model.drum_speed_mm_s == 0.0


def test_a_fault_latched_while_idle_is_acknowledged_too():
    """A fault the controller latched while no command asked the rig to move (the GUI's manual drum, a monitor that
    only reads): the acknowledgement finds it and clears the controller without moving anything (NOT_HOMED: the
    e-stop forgot the position); the next command is the start, which homes and tares first."""
    with open_control(RigSource("inprocess", inject=(parse_fault("estop@0.1+0.1"),))) as control:
        model = rig_of(control).backend.model
        control.drum.clock.sleep(0.5)
        assert control.drum.read_status().state == DrumState.FAULT and control.latch is None
        act = model.actuator_mm
        ack = control.acknowledge("released", by="pytest")
        assert ack.latch.cause == "estop" and control.latch is None
        control.drum.clock.sleep(5.0)
        st = control.drum.read_status()
        assert st.state == DrumState.NOT_HOMED and not int(st.faults) and model.actuator_mm == act
        with pytest.raises(ValueError, match="nothing is latched"):
            control.acknowledge("again", by="pytest")
        control.press(200.0)  # the start: HOME, TARE, then the press
        st = control.drum.read_status()
        assert st.homed and st.state == DrumState.FORCE_SETTLED and abs(model.force_g - 200.0) < 30.0


def test_opening_never_acknowledges_a_fault_the_controller_still_holds():
    """A fault the controller still holds from before (an e-stop pressed and released while no run was going) is
    shown and kept when the rig is opened to move (HOME): the opening fails naming it, the rig latched, nothing
    moved. (The acknowledgement at open, ``--ack``: tests/acquisition/test_acq_ack_open.py.)"""
    from rigctl.acquisition.rig import FaultAtOpen
    from rigctl.rigs import open_rig

    with open_rig("inprocess", refuse_fault=False) as rig:
        mega, model = rig.backend.controller, rig.backend.model
        mega.set_estop(True)
        rig.drum.read_status()  # the controller runs its ESTOP path on the simulated clock
        mega.set_estop(False)
        st = rig.drum.read_status()
        assert st.state == DrumState.FAULT and Fault.ESTOP in st.faults  # latched, released, not cleared
        act = model.actuator_mm
        with pytest.raises(FaultAtOpen, match="e-stop"):
            rig._prepare(refuse_fault=True)  # what opening to record does
        assert rig.safety.latch is not None and rig.safety.latch.cause == "estop"
        assert rig.drum.read_status().state == DrumState.FAULT and model.actuator_mm == act


def test_a_reversed_actuator_latches_instead_of_retrying(tmp_path):
    """``--inject reversed-actuator`` on the in-process rig does what the firmware under simavr does (the model counts
    the steps it sends, as the firmware does, whether the actuator moves with them or not): the press drives the
    actuator into its rear stop while its step count reaches the end of travel, ACTUATOR_TRAVEL latches and the run
    ends at once (no trial recorded again); acknowledged with the coil pair still swapped, HOME's direction proof
    latches ACTUATOR_DIRECTION and the latch holds; mended, the acknowledgement homes the rig."""
    # (swapped once the rig has homed: a coil pair swapped from power-on is HOME's direction proof's, at the start)
    with open_control(RigSource("inprocess")) as control:
        protocol = load_protocol(find_protocol("quick_check"))
        control.mount_plate(protocol.plan()[0].texture)  # the run's first plate, so its first trial presses at once
        control.home()  # the start: HOME proves the direction
        clock = control.drum.clock
        t0 = clock.now()
        control.bench.inject_faults([parse_fault("reversed-actuator@0.01+30")])
        run = ProtocolRun(control, protocol, tmp_path / "s.h5", on_latch="end")
        summary = run.run()
        assert summary.stopped and summary.complete == 0 and summary.retried == 0 and summary.failed == 0
        assert control.latch is not None and control.latch.cause == "actuator-travel", control.latch
        assert "end of travel" in summary.latched
        assert clock.now() < t0 + 25.0  # still reversed
        ack = control.acknowledge("plate mounted", by="pytest")  # clears the controller, moves nothing
        assert ack.latch.cause == "actuator-travel" and control.latch is None
        with pytest.raises(LatchedFault, match="ACTUATOR_DIRECTION"):
            control.press(200.0)  # the start homes first: HOME's direction proof latches
        st = control.drum.read_status()
        assert control.latch is not None and Fault.ACTUATOR_DIRECTION in st.faults and not st.homed
        clock.sleep(t0 + 31.0 - clock.now())  # the coil pair mended
        ack = control.acknowledge("coil pair swapped back", by="pytest")
        assert ack.latch.cause == "actuator-direction" and control.latch is None
        control.press(200.0)  # the start: HOME proves the direction, TARE, press
        assert control.drum.read_status().state == DrumState.FORCE_SETTLED
    with open_session(tmp_path / "s.h5") as s:
        assert [e["kind"] for e in s.events] == ["latched"] and s.events[0]["cause"] == "actuator-travel"


def test_paused_is_reported_only_once_the_sensor_is_released(tmp_path):
    """STOP mid-trial: the run's ``paused`` comes once the actuator is back home and the sensor free (the model's
    true actuator position and force when the event is emitted), not while it still retracts (the old code reported
    it at IDLE, which STOP sets at once while the actuator backs off)."""
    import threading

    seen: dict[str, float] = {}
    started = threading.Event()

    with open_control(RigSource("inprocess")) as control:
        model = rig_of(control).backend.model

        def on_trial(ev):
            if ev.kind == "start" and ev.planned.trial_id == 1:
                started.set()
            if ev.kind == "paused" and not seen:
                seen.update(actuator_mm=model.actuator_mm, force_g=model.force_g)

        run = ProtocolRun(control, load_protocol(find_protocol("quick_check")), tmp_path / "s.h5",
                          on_trial=on_trial).start()
        assert started.wait(120)
        _until(lambda: model.force_g > 100.0, "the press of trial 1")
        control.stop("pytest STOP")
        _until(lambda: run.state == "paused", "the pause after STOP")
        run.abort()
        run.wait(120)
    assert seen["actuator_mm"] <= 0.05 and abs(seen["force_g"]) < 5.0, seen
