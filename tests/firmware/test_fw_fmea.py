"""The bill of materials' failure modes under simavr (issue 75 item 2, docs/safety.md "FMEA"): each one the harness
injects acts where the part fails (the cell's gain and zero, the home switch's wire, the HX711's RATE pin, the
drivers' EN input, the motor's lost steps, a wrong calibration saved); the controller's latches reported from its own
RAM (issue 80 item 3: the instant it latched, not a host's poll); a fault wired from power-on armed before the rig
starts, without any wait (the open of ``rigctl doctor --hil --inject reversed-cell@0`` timed out on a wall-clock wait
for telemetry the unstarted harness could not send)."""

from __future__ import annotations

import time

import pytest

from rigctl.core.faults import parse_fault
from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation import hil
from rigctl.simulation.model import MechanicsConfig, RigConfig

from .conftest import home
from .test_fw_force_path import Bench

pytestmark = pytest.mark.hil

HR, State, Fault, Flag = wire.HoldingRegister, wire.DrumState, wire.Fault, wire.StatusFlag


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path, sps=80, k=1000.0)
    yield b
    b.close()


def test_a_power_on_fault_is_armed_before_the_rig_starts_without_waiting(tmp_path, fw_build):
    """inject_faults(power_on=True) before start() returns at once (it waited 5 s of wall time for telemetry and
    failed); the harness applies the FAULT@0 at its time 0 and the Mega boots wired so."""
    rig = hil.HilRig(RigConfig(mechanics=MechanicsConfig(contact_gap_mm=1.0)), live=False, with_uno=False)
    t = time.monotonic()
    schedule = rig.inject_faults([parse_fault("reversed-cell@0"), parse_fault("estop@8")], power_on=True)
    assert time.monotonic() - t < 0.5 and not schedule.armed
    try:
        rig.start()
        assert schedule.armed and [(a, s.name) for a, s, _ in schedule.applied] == [(0.0, "reversed-cell")]
        drum = DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"), clock=rig.clock).open()
        try:
            st = drum.wait_hx711_rate(timeout_s=10)
            assert st.state == State.NOT_HOMED and rig.next_telemetry().t_s < 8.0, st
            end = 8.5  # the e-stop at 8 s of the Mega's clock, from its time 0
            while rig.next_telemetry().t_s < end:
                drum.read_status()
            assert Fault.ESTOP in drum.read_status().faults
        finally:
            drum.close()
    finally:
        rig.close()


def test_the_latch_is_the_controllers_own_from_its_ram(bench):
    """A push past FORCE_LIMIT latches: the harness reports the instant the controller's state byte became FAULT
    (0.1 ms), before any poll of the host saw it, and the truth log holds a row there."""
    home(bench.drum)
    bench.press_settled(600)
    assert bench.rig.latch_spans == []
    bench.rig.bump(1400.0)
    seen = None
    for _ in range(200):
        st = bench.drum.read_status()
        if st.state == State.FAULT:
            seen = bench.rig.next_telemetry().t_s - bench.rig.truth.t0_s
            break
    assert seen is not None and Fault.FORCE_LIMIT in st.faults
    (start, end), *_ = bench.rig.latch_spans
    assert end is None and start <= seen
    bench.rig.truth._file.flush()
    times = [float(line.split(",")[1]) for line in bench.truth_path.read_text().splitlines()[1:]]
    assert min(abs(t - start) for t in times) < 1e-3, "no truth row at the latch"
    bench.rig.bump(0.0)
    bench.wait(lambda s: s.actuator_mm < 0.05, 10)  # backed off home, the push gone
    bench.drum.clear_fault()
    bench.wait(lambda s: s.state != State.FAULT, 5)
    assert bench.rig.latch_spans[0][1] is not None  # acknowledged: the span ended


def test_the_load_cells_gain_and_zero_and_the_drivers_enable(bench):
    """cell-gain=0.5 halves the reading of a mass on the cell, cell-offset=300 adds 300 g; driver-enable-stuck: the
    drivers drive while the controller's EN output says off."""
    home(bench.drum)
    bench.rig.bump(800.0)
    bench.sim_wait(0.3)
    assert abs(bench.drum.read_status().force_g - 800.0) < 15
    bench.inject("cell-gain=0.5@0")
    bench.sim_wait(0.3)
    assert abs(bench.drum.read_status().force_g - 400.0) < 15
    bench.rig.faults.apply_fault(parse_fault("cell-gain=0.5@0"), False)
    bench.inject("cell-offset=300@0")
    bench.sim_wait(0.3)
    assert abs(bench.drum.read_status().force_g - 1100.0) < 15
    bench.rig.faults.apply_fault(parse_fault("cell-offset=300@0"), False)
    bench.rig.bump(0.0)
    st = bench.drum.read_status()
    assert Flag.DRIVERS_ENABLED not in st.flags and not bench.rig.next_telemetry().drivers_enabled
    bench.inject("driver-enable-stuck@0")
    # the harness applies it between its cycles: a telemetry line already on its way may predate it (a loaded CI run
    # read one at t = 1.18 s, before it); 0.1 s of the Mega's time is many cycles later
    bench.sim_wait(0.1)
    assert bench.rig.next_telemetry().drivers_enabled


def test_the_home_switch_stuck_closed_and_lost_steps(bench):
    """home-switch=closed reads closed wherever the actuator is; steps-lost=50%: the actuator is where half the
    firmware's count says (the count is not the position)."""
    home(bench.drum)
    bench.inject("steps-lost=50%@0")
    bench.drum.set_force(300)
    bench.drum.press()
    bench.wait(lambda s: s.actuator_mm > 0.6 or s.state == State.FAULT, 10)
    st, tel = bench.drum.read_status(), bench.rig.next_telemetry()
    assert tel.act_mm < 0.6 * st.actuator_mm, (tel.act_mm, st.actuator_mm)
    bench.inject("home-switch=closed@0")
    bench.sim_wait(0.05)
    assert Flag.HOME_SWITCH in bench.drum.read_status().flags and bench.rig.next_telemetry().act_mm > 0.2


def test_a_wrong_calibration_saved_and_the_rate_pin(bench):
    """calibration-scale=0.5: a record with half the scale, its checksum valid, and a power cycle: the firmware boots
    with it and nothing says so; hx711-10sps: the board powers on at 10 SPS and measures it."""
    home(bench.drum)
    before = wire.join_s32(*bench.drum.read_holdings(HR.LOADCELL_SCALE_X100_HI, 2))
    bench.inject("calibration-scale=0.5@0")
    bench.sim_wait(0.5)
    st = bench.drum.wait_hx711_rate(timeout_s=10)
    assert st.state == State.NOT_HOMED and Flag.CALIBRATION_DEFAULTS not in st.flags
    assert wire.join_s32(*bench.drum.read_holdings(HR.LOADCELL_SCALE_X100_HI, 2)) == round(before * 0.5)
    bench.inject("hx711-10sps@0")
    bench.sim_wait(0.5)
    st = bench.drum.wait_hx711_rate(timeout_s=20)
    assert abs(st.hx711_rate_sps - 10.0) < 1.0, st


def test_a_wrong_calibration_saved_latches_loadcell_scale_at_the_probe(bench):
    """Issue 75 items 3 and 6 on the firmware (docs/wire-protocol.md 2.12): the factory's record carries the plate's
    stiffness (1,000 g/mm); a wrong calibration saved with a valid checksum (half the scale: the reading twice the
    force) and a power cycle keep it, and the next press's probe latches LOADCELL_SCALE (FAULT_BITS_HI) before any
    press past the probe's force; the truth stays at the probe's. Without the check the press went to 1,000 g read."""
    home(bench.drum)
    assert bench.drum.calibration_stiffness() == 1000
    bench.inject("calibration-scale=0.5@0")
    bench.sim_wait(0.5)
    bench.drum.wait_hx711_rate(timeout_s=10)
    assert bench.drum.calibration_stiffness() == 1000  # the reset kept it (EEPROM)
    home(bench.drum)
    bench.drum.set_force(1000)
    bench.drum.press()
    st = bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 30)
    assert st.faults == Fault.LOADCELL_SCALE, st
    assert bench.drum.read_input(wire.InputRegister.FAULT_BITS_HI) == 2  # bit 17
    assert st.contact_stiffness_g_per_mm == pytest.approx(2000, rel=0.08)
    bench.wait(lambda s: s.actuator_mm < 0.05, 10)  # backed off home: the probe's step proved the way
    assert bench.peak_g() < 300, bench.peak_g()  # the probe's 150 g read, 75 g true: never the 1,000 g asked


def test_a_reading_that_moves_with_no_step_latches_loadcell_zero(tmp_path):
    """Issue 75 item 5 on the firmware (docs/wire-protocol.md 2.13), fresh campaign seed 775401's case: 442 g/mm at
    10 SPS, a trial at 307 g, then the cell's zero moves by +302 g with the actuator at home. The next press judges its
    settled reading against the tare and latches LOADCELL_ZERO (FAULT_BITS_HI bit 2) before any step: the truth stays
    at 0 g (firmware 1.6 recorded that trial with no contact). CLEAR_FAULT leaves NOT_HOMED; HOME tares again and the
    press holds the true setpoint. Then the zero moves during a press's approach, before the contact: the probe's steps
    raise less than a quarter of the load the stored stiffness says they press: LOADCELL_ZERO at the probe, nothing pressed (its
    steps may just touch the contact: under the probe's contact load)."""
    bench = Bench(tmp_path, sps=10, k=442.0)
    try:
        home(bench.drum)
        bench.drum.set_force(307)
        bench.drum.press()
        assert bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 40).state == State.FORCE_SETTLED
        bench.drum.stop()
        bench.wait(lambda s: s.actuator_mm < 0.05 and s.state == State.IDLE, 10)
        bench.inject("cell-offset=302.4@0")
        bench.sim_wait(1.0)
        bench.drum.press()
        st = bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 20)
        assert st.faults == Fault.LOADCELL_ZERO, st
        assert bench.drum.read_input(wire.InputRegister.FAULT_BITS_HI) == 4  # bit 18
        tel = bench.rig.next_telemetry()
        assert tel.act_mm < 0.05 and tel.force_g == 0.0, tel  # nothing moved, nothing pressed
        bench.drum.clear_fault()
        assert bench.drum.read_status().state == State.NOT_HOMED
        home(bench.drum)  # proves the switch, tares again at home
        bench.drum.press()
        assert bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 40).state == State.FORCE_SETTLED
        bench.sim_wait(0.5)
        assert abs(bench.true_force_g() - 307) < 40, bench.true_force_g()
        bench.drum.stop()
        bench.wait(lambda s: s.actuator_mm < 0.05 and s.state == State.IDLE, 10)
        bench.sim_wait(1.0)
        bench.drum.press()
        bench.wait(lambda s: s.actuator_mm > 0.3 or s.state == State.FAULT, 20)  # approaching, 1 mm from the contact
        bench.inject("cell-offset=602.4@0")  # the zero moves by 300 g more on the way
        st = bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 30)
        assert st.faults == Fault.LOADCELL_ZERO, st
        assert bench.true_force_g() < 50.0  # the probe's steps may touch the contact (6.6 g here), never press it
    finally:
        bench.close()


@pytest.mark.parametrize("fault", ["steps-lost=60%@0", "coupling-slip=50%@0"])
def test_a_press_with_no_force_rise_within_its_travel_latches_contact_missing(bench, fault):
    """Issue 75 item 5's other half on the firmware (spec 2.13, firmware 1.9): a trial locates the contact (1 kg/mm);
    the motor then loses 60 % of its steps, or its coupling slips 50 % of them. The next press's approach passes the
    located contact by 0.3 mm plus the probe's contact load's travel, in steps, with no force read: CONTACT_MISSING
    (FAULT_BITS_HI bit 3), standing where it latched: the true force stays under the probe's contact load plus
    k x 0.3 mm (a slipping coupling's catch-up included) and the motor takes no step towards the sensor after the
    latch (the campaign's judge on the harness's truth log). CLEAR_FAULT: NOT_HOMED."""
    from rigctl.simulation.campaign import check_invariants, read_truth_log

    home(bench.drum)
    bench.drum.set_force(300)
    bench.drum.press()
    assert bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 30).state == State.FORCE_SETTLED
    bench.drum.stop()
    bench.wait(lambda s: s.actuator_mm < 0.05 and s.state == State.IDLE, 10)
    bench.inject(fault)
    bench.drum.press()
    st = bench.wait(lambda s: s.state in (State.FAULT, State.FORCE_SETTLED), 30)
    assert st.faults == Fault.CONTACT_MISSING, st
    assert bench.drum.read_input(wire.InputRegister.FAULT_BITS_HI) == 8  # bit 19
    bench.sim_wait(1.0)  # a wound coupling catches up once the motor holds (20 ms)
    assert bench.peak_g() < 50 + 0.3 * 1000.0 + 30
    (latch,) = bench.rig.latch_spans
    assert check_invariants(read_truth_log(bench.truth_path), latches=[latch]) == []
    bench.drum.clear_fault()
    assert bench.drum.read_status().state == State.NOT_HOMED
