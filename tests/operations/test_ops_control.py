"""The operator layer (rigctl.operations) on the in-process rig (controller logic + physical model in this process,
simulated clock): opening moves nothing whatever the policy (the first start HOMEs), the setpoint policy against the
controller's own limits, run at a speed and force (the drum never turns before the force has settled), stop, plates,
and the typed status."""

from __future__ import annotations

import pytest

from rigctl.core.drum import MAX_FORCE_G, MAX_SPEED_MM_S, DrumLimits, DrumState, Fault, SetpointRangeError
from rigctl.core.faults import parse_fault
from rigctl.devices.wire import HoldingRegister
from rigctl.operations import Home, RigSource, open_control, setpoint_refusals
from rigctl.operations._control import rig_of


@pytest.fixture
def control(tmp_path):
    with open_control(RigSource("inprocess"), seed=3, host_config_path=tmp_path / "rig.json") as c:
        yield c


def test_rig_sources_use_the_composition_roots_kinds():
    assert RigSource("serial", drum_port="a", taxel_port="b") == RigSource("hardware", drum_port="a", taxel_port="b")
    assert RigSource.from_flags(drum_port="a", taxel_port="b").kind == "hardware"
    assert RigSource.from_flags(replay="x.h5").open_options() == {"kind": "replay", "source": "x.h5"}
    assert RigSource.from_flags(hil=True).kind == "hil" and RigSource.from_flags().kind == "sim"
    with pytest.raises(ValueError, match="unknown rig kind 'usb'"):
        RigSource("usb")
    # the firmware under simavr with the boards' real bootloaders (--hil-bootloaders): an option of "hil" only
    boot = RigSource.from_flags(bootloaders=True)
    assert boot.open_options() == {"kind": "hil", "bootloaders": True} and "bootloaders" in boot.label()
    assert RigSource.from_flags(hil=True).open_options() == {"kind": "hil"}
    with pytest.raises(ValueError, match="bootloaders"):
        RigSource("sim", bootloaders=True)


def test_refusals_name_the_binding_limit():
    wide = DrumLimits(speed_mm_s=200.0, force_g=2000.0)
    (r,) = setpoint_refusals(wide, speed_mm_s=151.0)
    assert r.short == "speed 151 mm/s refused: max 150 mm/s"
    assert r.full == "speed 151 mm/s refused: above the rig's protocol range of 150 mm/s"
    narrow = DrumLimits(speed_mm_s=90.0, force_g=800.0)
    assert [x.full for x in setpoint_refusals(narrow, speed_mm_s=95.0, force_g=900.0)] == [
        "speed 95 mm/s refused: above the controller's hard limit of 90 mm/s",
        "force 900 g refused: above the controller's hard limit of 800 g"]
    (z,) = setpoint_refusals(narrow, force_g=0.0)
    assert z.full.startswith("force 0 g refused: it must be above 0 g")
    assert setpoint_refusals(narrow, speed_mm_s=90.0, force_g=800.0) == []
    assert setpoint_refusals(wide, speed_mm_s=float("nan"))  # NaN is never sent
    assert wide.speed_range().high == MAX_SPEED_MM_S and wide.force_range().high == MAX_FORCE_G


def test_run_at_presses_to_a_settled_force_before_the_drum_turns(control):
    assert isinstance(control.status().state, DrumState) and control.status().state == DrumState.NOT_HOMED
    started = control.run_at(70.0, 300.0)
    assert started.settle_s > 0
    st = control.drum.wait_speed_steady(timeout_s=20.0, tol_mm_s=1.0)
    assert st.state == DrumState.RUNNING and abs(st.speed_mm_s - 70.0) <= 1.0
    assert abs(st.force_g - 300.0) < 30 and st.force_setpoint_active_g == 300
    assert control.stop() is True
    st = control.drum.wait_released(timeout_s=20.0)
    assert st.state == DrumState.IDLE and st.force_setpoint_active_g == 0


def test_setpoints_outside_the_controllers_limits_send_nothing(control):
    drum = rig_of(control).drum  # the test sets the controller's own limit (a face cannot)
    drum.set_limits(speed_mm_s=90.0)  # the controller's own limit, below the protocol range
    assert control.limits() == DrumLimits(speed_mm_s=90.0, force_g=1500.0)
    before = drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS)
    with pytest.raises(SetpointRangeError, match="controller's hard limit"):
        control.run_at(100.0, 300.0)
    with pytest.raises(SetpointRangeError):
        control.apply_setpoints(50.0, 0.0)
    assert drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == before
    assert control.status().state == DrumState.NOT_HOMED  # nothing homed, pressed or turned
    control.apply_setpoints(80.0, 400.0)
    assert drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 800
    assert drum.read_holding(HoldingRegister.FORCE_SETPOINT_G) == 400


def test_mount_plate_takes_the_sets_spelling(control):
    assert control.mount_plate("l") == "L" and control.plate == "L"
    with pytest.raises(ValueError):
        control.mount_plate("not a plate")


def _fault(control) -> None:
    """Latch a fault on the controller: hold 300 g, then lower its force limit below the measured force. The
    controller's second channel sees it first (controller.c: its 1 kHz tick finds the actuator past where the probed
    contact carries the new limit, POSITION_LIMIT, before the next reading's FORCE_LIMIT; the old Python copy of the
    rules checked the force first)."""
    control.press(300.0)
    rig_of(control).drum.set_limits(force_g=100.0)
    control.drum.wait_state([DrumState.FAULT], timeout_s=5.0)
    rig_of(control).drum.set_limits(force_g=1500.0)


def test_home_is_refused_while_latched_and_is_the_start_after_the_acknowledgement(control):
    from rigctl.acquisition.safety import LatchedFault

    _fault(control)
    with pytest.raises(LatchedFault):
        control.home()
    st = control.status()
    # not cleared behind the operator's back
    assert st.state == DrumState.FAULT and st.faults & (Fault.FORCE_LIMIT | Fault.POSITION_LIMIT), st
    control.clear_fault()
    assert control.status().state != DrumState.HOMING  # the acknowledgement moved nothing
    control.home()  # the start: backs off, HOMEs, TAREs
    st = control.status()
    assert st.state == DrumState.IDLE and st.homed and not st.faulted


def _at_rest(c, seconds: float = 3.0) -> tuple[float, float]:
    """The model's actuator position and drum speed after ``seconds`` of the rig's clock with nobody asking."""
    from rigctl.operations._control import rig_of

    rig = rig_of(c)
    rig.drum.clock.sleep(seconds)
    rig.drum.read_status()
    model = rig.backend.model
    return float(model.actuator_mm), float(getattr(model, "drum_speed_mm_s", 0.0))


def test_open_with_each_home_policy_moves_nothing(tmp_path):
    for policy in Home:
        with open_control(RigSource("inprocess"), home=policy, host_config_path=tmp_path / "r.json") as c:
            assert c.mode == "inprocess" and c.places_mass and c.bench is not None  # the simulated bench's hand
            assert c.bench.fault_refusal(parse_fault("taxel-ohm=100@1")) is None  # the model's taxel front end
            assert c.layout.n_channels == 18
            st = c.status()
            assert st.state == DrumState.NOT_HOMED and not st.homed, policy  # opening is not starting
            assert _at_rest(c) == (0.0, 0.0), policy
    with open_control(RigSource("inprocess"), home="unless_faulted", host_config_path=tmp_path / "r.json") as c:
        c.home()  # the start
        assert c.status().state == DrumState.IDLE


_MOVES = ("press", "run", "home", "run_at", "set_speed", "set_force", "set_profile", "set_ramp", "clear_fault",
          "stop_drum", "write_register", "write_holding")


def test_under_a_host_only_latch_no_public_attribute_presses_or_turns(control):
    """Issue 76: with a latch the controller does not know of (a stall the host saw, a latch restored from the
    queue file: ``keep_latch``), `control.drum.press()` pressed the sensor to ~200 g and `control.drum.run()` turned
    the drum. Now no public attribute of the control object (nor of its parts) is a drum client that moves: the
    drum is a read-only view, the commands are the owner's and refused; a refused run_at writes no setpoint; the
    simulated controller saw not one write while it was held."""
    from rigctl.acquisition.safety import Latch, LatchedFault

    control.keep_latch(Latch("stall", "the host saw the drum stall"))
    mega = rig_of(control).backend.engine.controller
    writes0 = mega.write_requests
    # every public attribute (bench: the simulated world's own hand, not a face's) and their public attributes
    reach = {name: getattr(control, name) for name in dir(control) if not name.startswith("_") and name != "bench"}
    for name in ("drum", "monitor", "taxels"):
        reach.update({f"{name}.{n}": getattr(reach[name], n) for n in dir(reach[name]) if not n.startswith("_")})
    for name, part in reach.items():
        if "." not in name or callable(part):
            continue
        movers = [verb for verb in _MOVES if callable(getattr(part, verb, None))]
        assert not movers, f"control.{name} can {movers}"
    for verb in _MOVES:
        assert not callable(getattr(control.drum, verb, None)), f"control.drum.{verb}"
        assert not callable(getattr(control.monitor, verb, None)), f"control.monitor.{verb}"
    for call in (lambda: control.press(300.0), lambda: control.run_at(60.0, 300.0), control.home):
        with pytest.raises(LatchedFault):
            call()
    assert mega.write_requests == writes0, "a refused command wrote to the controller"  # run_at's speed setpoint
    st = control.status()
    assert st.state == DrumState.NOT_HOMED and abs(st.speed_mm_s) < 0.5 and st.force_g < 5.0
