"""Opening never acknowledges, and one acknowledgement path (issue 51 items 2 and 3): a fault the drum controller
still latches when a rig opens is shown and kept (``rigctl acquire`` exits 1 naming it, nothing moved) unless the
operator acknowledges at open (``--ack REASON``: logged with the login name and the reason, in the rig's own log and
the session, then the run records); every acknowledgement is in the rig's own log at once; two faults at once latch
and are named and logged both. The controller outlives the face: the simulated rig on ptys (paced by the wall
clock), driven by the CLI as hardware (``--drum-port``/``--taxel-port``); what is judged is the model's true
actuator position, force and drum speed, not the firmware's belief."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from click.testing import CliRunner

from rigctl.acquisition.safety import operator_name, safety_log_path
from rigctl.cli import main as cli
from rigctl.core.drum import DrumState, Fault
from rigctl.operations import RigSource, open_control
from rigctl.operations._control import rig_of
from rigctl.storage.session import open_session

PROTOCOL = ('name = "ack_open"\ntextures = ["A"]\nspeeds_mm_s = [80]\nforces_g = [200]\n'
            'trials_per_condition = 1\nduration_s = 0.3\n[settle]\nsettle_time_ms = 50\n')


@contextmanager
def _rig(tmp_path: Path, monkeypatch, state: str) -> Iterator[tuple]:
    """A simulated rig on ptys (its controller outlives the faces), the rig config and the rig log (``state``: the
    XDG state folder) in ``tmp_path``, and :data:`PROTOCOL`'s file: ``(sim, its RigSource, the protocol's path)``."""
    from rigctl.simulation.rig import SimulatedRig

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / state))
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    proto = tmp_path / "p.toml"
    proto.write_text(PROTOCOL)
    with SimulatedRig(port_dir=tmp_path / "ports") as sim:
        yield sim, RigSource("hardware", drum_port=sim.drum_port, taxel_port=sim.taxel_port), proto


def _face(source: RigSource, tmp_path: Path):
    """A face opening the rig as every face does here: HOME unless a fault is latched, the rig config in tmp_path."""
    return open_control(source, home="unless_faulted", host_config_path=tmp_path / "rig.json")


def _acquire(sim, proto: Path, out: Path):
    """`rigctl acquire` of ``proto`` on the simulated rig's ports into ``out`` (click's runner: its exit code and
    output)."""
    args = ["acquire", str(proto), "--drum-port", sim.drum_port, "--taxel-port", sim.taxel_port, "--plates", "auto",
            "--out", str(out), "--quiet"]
    return CliRunner().invoke(cli, args)


def _until(cond, what: str, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def _log_lines() -> list[dict]:
    path = safety_log_path()
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_plain_acquire_on_a_latched_controller_exits_1_naming_it_and_ack_runs(tmp_path, monkeypatch):
    from rigctl.simulation.rig import SimulatedRig

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    proto = tmp_path / "p.toml"
    proto.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with SimulatedRig(port_dir=tmp_path / "ports") as sim:
        mega, model = sim.mega, sim.model
        mega.set_estop(True)  # pressed and released while no face was open: the controller keeps ESTOP latched
        _until(lambda: mega.state == DrumState.FAULT, "the e-stop's latch")
        mega.set_estop(False)
        args = ["acquire", str(proto), "--drum-port", sim.drum_port, "--taxel-port", sim.taxel_port, "--plates",
                "auto", "--out", str(out), "--quiet"]
        act, drum = model.actuator_mm, model.drum_speed_mm_s
        first = CliRunner().invoke(cli, args)
        assert first.exit_code == 1, first.output
        lines = [line for line in first.output.splitlines() if line.strip()]
        assert len(lines) == 1 and "e-stop" in lines[0] and "--ack" in lines[0], first.output
        assert "Traceback" not in first.output and not out.exists()
        # kept: still latched in the controller, and nothing moved
        assert mega.state == DrumState.FAULT and Fault.ESTOP in mega.faults
        assert model.actuator_mm == act and model.drum_speed_mm_s == drum == 0.0
        assert [e["kind"] for e in _log_lines()] == ["latched"]  # shown (the rig's log), nothing acknowledged
        second = CliRunner().invoke(cli, [*args, "--ack", "e-stop released, bench checked"])
        assert second.exit_code == 0, second.output
    with open_session(out) as s:
        assert len(s.completed_ids()) == 1
        (event,) = s.events
    assert event["kind"] == "acknowledged" and event["reason"] == "e-stop released, bench checked"
    assert event["by"] == operator_name() and event["clears"]["cause"] == "estop"
    logged = _log_lines()  # the rig's own log: the latch found at open, then its acknowledgement
    assert [e["kind"] for e in logged] == ["latched", "latched", "acknowledged"]
    assert logged[-1]["reason"] == "e-stop released, bench checked" and logged[-1]["by"] == operator_name()
    assert logged[-1]["rig"]["mode"] == "hardware" and logged[-1]["clears"]["cause"] == "estop"


def test_every_acknowledgement_goes_into_the_rigs_own_log_at_once(tmp_path, monkeypatch):
    """An acknowledgement from any face (here the library's RigControl, with no run) is in
    $XDG_STATE_HOME/rigctl/safety.jsonl when the call returns, after the latch it clears."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    with open_control(RigSource("inprocess")) as control:
        mega = rig_of(control).backend.controller
        mega.set_estop(True)
        control.drum.clock.sleep(0.2)
        control.status()  # the owner's poll latches what the controller latched
        assert [e["kind"] for e in _log_lines()] == ["latched"]
        mega.set_estop(False)
        control.acknowledge("released", by="ana")
        logged = _log_lines()
    assert safety_log_path() == tmp_path / "state" / "rigctl" / "safety.jsonl"
    assert [e["kind"] for e in logged] == ["latched", "acknowledged"]
    assert logged[1]["by"] == "ana" and logged[1]["reason"] == "released" and logged[1]["clears"]["cause"] == "estop"
    assert logged[0]["rig"]["mode"] == "inprocess"


def test_two_faults_at_once_latch_and_are_named_and_logged_both(tmp_path, monkeypatch):
    """The load cell silent and the e-stop pressed before the host reads the controller: one latch naming both
    (shown, in the rig's log and the acknowledgement; the old code named the e-stop alone); a second fault that
    joins a held latch is logged when it comes."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    with open_control(RigSource("inprocess")) as control:
        mega = rig_of(control).backend.controller
        mega.set_loadcell_alive(False)
        control.drum.clock.sleep(0.5)
        mega.set_estop(True)
        control.drum.clock.sleep(0.2)
        st = control.status()
        assert Fault.ESTOP in st.faults and Fault.LOADCELL_TIMEOUT in st.faults
        latch = control.latch
        assert latch is not None and set(latch.causes) == {"estop", "loadcell-timeout"}, latch
        assert "e-stop" in latch.describe() and "load cell not responding" in latch.describe()
        assert "release the e-stop" in latch.describe() and "HX711" in latch.describe()
        mega.set_estop(False)
        mega.set_loadcell_alive(True)
        control.drum.clock.sleep(0.5)
        ack = control.acknowledge("both mended", by="pytest")
        assert set(ack.latch.causes) == {"estop", "loadcell-timeout"} and control.latch is None
        # one held, a second one later: it joins the latch and is logged
        mega.set_loadcell_alive(False)
        control.drum.clock.sleep(0.5)
        control.status()
        mega.set_estop(True)
        control.drum.clock.sleep(0.2)
        control.status()
        assert set(control.latch.causes) == {"estop", "loadcell-timeout"}
    logged = _log_lines()
    assert [e["kind"] for e in logged] == ["latched", "acknowledged", "latched", "latched"]
    assert set([logged[0]["cause"], *logged[0]["also"]]) == {"estop", "loadcell-timeout"}
    assert logged[2]["cause"] == "loadcell-timeout" and logged[2]["also"] == [] and logged[3]["also"] == ["estop"]


def test_a_reset_one_face_saw_is_latched_for_the_next_until_acknowledged(tmp_path, monkeypatch):
    """Issue 76: a controller reset under load was latched by the face that saw it only; the next `rigctl acquire`
    on that controller opened and ran without anyone acknowledging it. The latch is the rig's now (its own log):
    a face that closes without acknowledging leaves it for every later face (held, nothing moves; `acquire` exits 1
    naming it), until one acknowledges; the face after that opens unlatched."""
    from rigctl.acquisition.safety import LatchedFault

    with _rig(tmp_path, monkeypatch, "state") as (sim, source, proto):
        with _face(source, tmp_path) as first:
            first.press(200.0)
            sim.mega.reset()  # a reset pulse under load (brown-out, the reset line)
            _until(lambda: first.status() is not None and first.latch is not None, "the first face's reset latch")
            assert first.latch.cause == "reset"
        # the next face: NOT_HOMED, nothing latched in the controller, and still the reset latch
        with _face(source, tmp_path) as second:
            assert second.latch is not None and second.latch.cause == "reset", second.latch
            try:
                second.press(200.0)
                raise AssertionError("pressed under a latch")
            except LatchedFault:
                pass
        act = sim.model.actuator_mm
        refused = _acquire(sim, proto, tmp_path / "s.h5")
        assert refused.exit_code == 1 and "reset" in refused.output, refused.output
        assert sim.model.actuator_mm == act and not (tmp_path / "s.h5").exists()
        with _face(source, tmp_path) as third:
            third.acknowledge("reset checked: power and reset line", by="tester")
        with _face(source, tmp_path) as fourth:
            assert fourth.latch is None


def test_a_reset_under_load_no_face_saw_is_latched_by_the_controller_for_the_next(tmp_path, monkeypatch):
    """Issue 76 item 5: the controller latches a reset under load itself (its warm-boot record: RESET in
    FAULT_BITS_HI), so a face that never saw the reset finds the latch: here the next face runs with a rig log of its
    own (another computer; the face that pressed is gone), and `rigctl acquire` there exits 1 naming it, nothing
    moved. Its acknowledgement moves nothing (reset is not start); the face after it opens unlatched."""
    with _rig(tmp_path, monkeypatch, "state-a") as (sim, source, proto):
        with _face(source, tmp_path) as first:
            first.press(200.0)
            sim.mega.reset()  # a reset pulse under load (brown-out, the reset line, the next port opening's DTR)
            pressed_mm, pressed_g = sim.model.actuator_mm, sim.model.contact_force_g
        assert pressed_g > 100.0  # still pressing: the reset left the actuator where it stood
        assert Fault.RESET in sim.mega.faults and sim.mega.state == DrumState.FAULT
        monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state-b"))  # a face whose rig log never saw it
        refused = _acquire(sim, proto, tmp_path / "s.h5")
        assert refused.exit_code == 1 and "reset" in refused.output, refused.output
        assert "Traceback" not in refused.output and not (tmp_path / "s.h5").exists()
        assert sim.model.actuator_mm == pressed_mm
        with _face(source, tmp_path) as second:
            assert second.latch is not None and second.latch.cause == "reset", second.latch
            assert Fault.RESET in Fault(second.latch.faults)
            second.acknowledge("reset checked: the sensor is free", by="tester")
            second.drum.clock.sleep(1.0)
            assert sim.model.actuator_mm == pressed_mm  # the acknowledgement moved nothing
            assert sim.mega.state == DrumState.NOT_HOMED
        with _face(source, tmp_path) as third:
            assert third.latch is None
