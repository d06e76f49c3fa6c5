"""Issue 22 items 2-3 on both drum controllers (the virtual Mega and the firmware under simavr), each on a rig built
for the case: the HX711's rate timed at boot and refused when it is not the configured one, the retuned force loop
at high contact stiffness with the HX711's conversion delay modelled, and the drum index sensor measuring the real
drum with a driver at another microstep setting (both simulators model the HX711 and the index sensor from the
physics: rigctl.simulation.model, arduino/simavr/rigctl_simavr.c)."""

from __future__ import annotations

import pytest

from rigctl.devices.drum import DrumClient, default_force_loop
from rigctl.devices.errors import ModbusExceptionError
from rigctl.devices.wire import DrumState, Fault, HoldingRegister as HR
from rigctl.simulation.model import DrumConfig, MechanicsConfig, RigConfig

from .conftest import QUIET_WATCHDOG_MS, _open_client, _start_hil, _start_sim, home

TOL_G = 15  # FORCE_TOLERANCE_G default


@pytest.fixture(params=["sim", pytest.param("hil", marks=pytest.mark.hil)])
def make_rig(request):
    """``make_rig(config) -> (controller, DrumClient)`` on a fresh controller of each backend built with ``config``."""
    opened = []

    def make(config: RigConfig):
        rig, ctl = (_start_sim if request.param == "sim" else _start_hil)(config)
        opened.append(rig)
        drum = _open_client(ctl)
        opened.append(drum)
        drum.write_holding(HR.WATCHDOG_MS, QUIET_WATCHDOG_MS)  # a host starved on a loaded machine: not a fault here
        home(drum)  # powered up NOT_HOMED: a rig homes when it opens (a controller in FAULT stays so)
        return ctl, drum

    yield make
    for obj in reversed(opened):
        obj.close()


def _forces(ctl, drum: DrumClient, seconds: float) -> list[float]:
    """The force on the load cell (the model's / the harness's spring) over ``seconds`` of the controller's time,
    polling the controller meanwhile (the host watchdog)."""
    out, end = [], ctl.clock_s() + seconds
    while ctl.clock_s() < end:
        drum.read_status()
        out.append(ctl.load_g())
        drum.clock.sleep(0.02)
    return out


def test_80sps_step_at_2kg_per_mm_settles_without_oscillation(make_rig):
    """With the HX711's delay modelled, the gains before issue 22 (0.05 (mm/s)/g) oscillated +-220 g at 2 kg/mm; the
    defaults now settle and hold within FORCE_TOLERANCE_G."""
    ctl, drum = make_rig(RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=2000.0)))
    st = drum.read_status()
    assert st.hx711_rate_sps == pytest.approx(80.0, rel=0.02) and st.faults == Fault(0)
    drum.set_force(1000)
    drum.press()
    drum.wait_state(DrumState.FORCE_SETTLED, timeout_s=10)
    forces = _forces(ctl, drum, 1.0)
    assert max(forces) - min(forces) <= 2 * TOL_G, forces  # no sustained oscillation beyond the tolerance
    assert abs(sum(forces) / len(forces) - 1000) <= TOL_G
    drum.stop()


def test_a_10sps_hx711_is_refused_with_a_fault_then_runs_with_its_own_gains(make_rig):
    # the contact 1 mm from home: the first press's contact probe approaches at 0.33 mm/s at 10 SPS (spec 2.10)
    ctl, drum = make_rig(RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=10.0, contact_stiffness_g_per_mm=500.0,
                                                             contact_gap_mm=1.0)))
    st = drum.read_status()
    assert st.hx711_rate_sps == pytest.approx(10.0, rel=0.02)
    assert st.state == DrumState.FAULT and Fault.HX711_RATE in st.faults
    drum.set_force(500)
    with pytest.raises(ModbusExceptionError):
        drum.press()
    with pytest.raises(ModbusExceptionError):
        drum.clear_fault()  # refused while the rate is not HX711_RATE_SPS
    drum.set_hx711_rate(10)  # accept the 10 SPS board: its own, slower gains
    assert drum.force_loop() == default_force_loop(10)
    drum.clear_fault()
    home(drum)  # it never was homed: the rate fault came first
    drum.press()
    drum.wait_state(DrumState.FORCE_SETTLED, timeout_s=40)
    forces = _forces(ctl, drum, 1.0)
    assert max(forces) - min(forces) <= 2 * TOL_G and abs(sum(forces) / len(forces) - 500) <= TOL_G
    drum.stop()


def test_an_hx711_with_a_slow_oscillator_is_measured_as_such(make_rig):
    """The rate is measured, not assumed: a 10 % slow on-chip oscillator reads ~72 SPS (within the 20 % that
    HX711_RATE_SPS = 80 accepts). The firmware times the first HX711_RATE_PERIODS = 4 periods (~56 ms) by micros() at
    the loop() pass that sees DOUT low: a pass busy with a Modbus request at either end adds up to ~1 ms (a CI run
    under load read 71.25 SPS: 0.6 ms late), so the tolerance is 1.5 SPS, still 6.5 SPS short of an assumed 80."""
    _, drum = make_rig(RigConfig(mechanics=MechanicsConfig(hx711_clock_error=-0.1)))
    st = drum.read_status()
    assert st.hx711_rate_sps == pytest.approx(72.0, abs=1.5) and st.faults == Fault(0)


def test_index_sensor_measures_the_real_drum_speed_with_a_wrong_microstep_setting(make_rig):
    """The driver at 8 microsteps, the controller assuming 16: the drum turns twice as fast as the step count says;
    only the index sensor shows it (INDEX_STEPS 1600, the index period gives 120 mm/s at a 60 mm/s setpoint)."""
    ctl, drum = make_rig(RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=500.0),
                                   drum=DrumConfig(driver_microsteps=8)))
    drum.set_force(250)
    drum.set_speed(60)
    drum.run()
    deadline = ctl.clock_s() + 20
    st = drum.read_status()
    while st.index_count < 3:
        assert ctl.clock_s() < deadline, st
        drum.clock.sleep(0.1)
        st = drum.read_status()
    d = DrumConfig()
    assert st.index_source == "sensor"
    assert st.index_steps == pytest.approx(d.steps_per_rev * 8, abs=2)  # not the 3200 the controller assumes
    assert st.index_speed_mm_s(d.diameter_mm) == pytest.approx(120.0, rel=0.03)
    assert st.speed_mm_s == pytest.approx(60.0, abs=0.5)  # what the step count says
    drum.stop()


def test_without_an_index_sensor_the_step_count_marks_the_index(make_rig):
    _, drum = make_rig(RigConfig(drum=DrumConfig(index_sensor=False)))
    drum.set_force(250)
    drum.set_speed(120)
    drum.run()
    rev0 = drum.read_status().revolutions
    st = drum.read_status()
    deadline = drum.clock.now() + 30  # the controller's own time: simavr falls behind real time on a loaded host
    while (st.revolutions - rev0) % 65536 < 2:
        assert drum.clock.now() < deadline
        drum.clock.sleep(0.1)
        st = drum.read_status()
    assert st.index_source == "steps" and st.index_count == 0 and st.index_period_s == 0
    drum.stop()
