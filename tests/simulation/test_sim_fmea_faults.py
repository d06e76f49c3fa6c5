"""The bill of materials' failure modes (issue 75 item 2, docs/safety.md "FMEA") as the model rig's physics injects
them: the load cell's gain and zero, the actuator's coupling slip (caught up when the motor holds still) and lost
steps, bit errors on the HX711's DOUT, the home switch stuck closed or open, a wrong calibration saved with a valid
checksum; their spec forms; and the campaign's one list of faults, which both rigs model."""

from __future__ import annotations

import math

import pytest

from rigctl.core.drum import DrumState
from rigctl.core.faults import FAULTS, FaultSpec, FaultSpecError, parse_fault
from rigctl.simulation.model import ACTUATOR_CATCHUP_MS, RigModel


def test_the_bom_faults_parse_with_their_values():
    assert parse_fault("home-switch=closed@1") == FaultSpec("home-switch", 1.0, math.inf, 1.0)
    assert parse_fault("home-switch=open@0+2") == FaultSpec("home-switch", 0.0, 2.0, 0.0)
    assert str(parse_fault("home-switch=closed@1+2")) == "home-switch=closed@1+2"
    assert parse_fault("cell-gain=0.5@2").value == 0.5
    assert parse_fault("cell-offset=-250@2").value == -250.0
    assert str(parse_fault("coupling-slip=20%@1")) == "coupling-slip=20%@1"
    assert parse_fault("steps-lost=10@1").value == 10.0
    assert parse_fault("hx711-dout-noise=0.01@1").value == 0.01
    assert parse_fault("driver-enable-stuck@3") == FaultSpec("driver-enable-stuck", 3.0)
    assert parse_fault("calibration-scale=0.5@1+4") == FaultSpec("calibration-scale", 1.0, 0.0, 0.5)  # an instant
    for bad, words in (("home-switch=ajar@1", "one of open, closed"), ("cell-gain=5@1", "0.3 to 3"),
                       ("cell-offset=x@1", "not a number"), ("coupling-slip=120%@1", "0 to 100"),
                       ("hx711-dout-noise=2@1", "0 to 1"), ("driver-enable-stuck=1@1", "takes no value")):
        with pytest.raises(FaultSpecError, match=words):
            parse_fault(bad)


def _settle(model: RigModel, ms: int = 400) -> None:
    model.advance(ms, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)


def test_load_cell_gain_offset_and_dout_bit_errors_act_on_the_raw_reading():
    model = RigModel(seed=1)
    model.place_mass(1000.0)
    _settle(model)
    m = model.config.mechanics
    grams = (model.loadcell_raw - m.loadcell_offset_counts) / m.loadcell_counts_per_g
    assert abs(grams - 1000.0) < 5.0
    model.loadcell_gain = 0.5
    assert abs((model.loadcell_raw - m.loadcell_offset_counts) / m.loadcell_counts_per_g - 500.0) < 5.0
    model.loadcell_gain, model.loadcell_offset_g = 1.0, -250.0
    assert abs((model.loadcell_raw - m.loadcell_offset_counts) / m.loadcell_counts_per_g - 750.0) < 5.0
    model.loadcell_offset_g = 0.0
    clean = model.loadcell_raw
    model.hx711_dout_noise = 1.0  # every bit flips: the 24 bits inverted (two's complement: -raw - 1)
    model.advance(20, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
    assert abs(model.loadcell_raw - (-clean - 1)) < 1000  # (a new conversion: its noise)
    model.hx711_dout_noise = 0.0
    model.advance(20, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
    assert abs(model.loadcell_raw - clean) < 1000


def test_a_slipping_coupling_catches_up_when_the_motor_holds_still_and_lost_steps_never_return():
    model = RigModel(seed=1)
    model.actuator_slip = 0.5
    model.advance(200, drum_step_rate_hz=0.0, actuator_velocity_mm_s=2.0)  # 0.4 mm commanded
    assert abs(model.actuator_mm - 0.2) < 1e-6
    model.advance(ACTUATOR_CATCHUP_MS - 1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
    assert abs(model.actuator_mm - 0.2) < 1e-6  # still wound up
    model.advance(2, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
    assert abs(model.actuator_mm - 0.4) < 1e-6  # caught up: the screw jumped
    model.actuator_slip, model.actuator_lost = 0.0, 0.25
    model.advance(200, drum_step_rate_hz=0.0, actuator_velocity_mm_s=2.0)
    _settle(model, 100)
    assert abs(model.actuator_mm - 0.7) < 1e-6


def test_the_home_switch_stuck_is_what_the_controller_reads():
    from rigctl.rigs import open_rig

    with open_rig("inprocess") as rig:
        rig.home_if_pending()
        engine = rig.backend.engine  # type: ignore[attr-defined]
        model, controller = engine.model, engine.controller
        assert model.home_switch_closed
        engine.faults.apply_fault(parse_fault("home-switch=open@0"), True)
        assert not model.home_switch_closed and not controller._home_switch()
        engine.faults.apply_fault(parse_fault("home-switch=open@0"), False)
        assert controller._home_switch()
        engine.faults.apply_fault(parse_fault("home-switch=closed@0"), True)
        model.advance(1, drum_step_rate_hz=0.0, actuator_velocity_mm_s=3.0)  # off home: the switch still reads closed
        assert model.actuator_mm > 0 and controller._home_switch()


def test_a_wrong_calibration_saved_is_what_the_controller_boots_with():
    from rigctl.core.drum import StatusFlag
    from rigctl.rigs import open_rig

    with open_rig("inprocess") as rig:
        engine = rig.backend.engine  # type: ignore[attr-defined]
        before = engine.controller.scale_x100
        engine.faults.apply_fault(parse_fault("calibration-scale=0.5@0"), True)
        st = rig.drum.read_status()
        assert engine.controller.scale_x100 == round(before * 0.5)
        assert StatusFlag.CALIBRATION_DEFAULTS not in st.flags  # its checksum is valid: nothing tells


def test_the_campaign_draws_one_list_that_both_rigs_model():
    """Issue 80 item 3: one list (every fault of FAULTS) on every rig; neither rig refuses one of it, so a seed is
    the same case on both (a fault a rig cannot model would be an error before any case runs, never a redraw)."""
    import importlib.util
    from pathlib import Path

    from rigctl.simulation.campaign import CAMPAIGN_FAULTS, draw_case

    spec = importlib.util.spec_from_file_location(
        "bench_fault_campaign", Path(__file__).resolve().parents[2] / "benchmarks" / "bench_fault_campaign.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert set(CAMPAIGN_FAULTS) == set(FAULTS)
    assert bench.refusals("model", list(CAMPAIGN_FAULTS)) == {}
    assert bench.refusals("hil", list(CAMPAIGN_FAULTS)) == {}
    drawn = {draw_case(s).fault for s in range(600)}
    assert drawn == set(FAULTS)
    stiff = [draw_case(s).value for s in range(2000) if draw_case(s).fault == "contact-stiffness"]
    assert min(stiff) < 500 and max(stiff) > 3_000  # the rig config's whole range (<= 5,000 g/mm)


def test_a_drivers_enable_line_stuck_active_reads_enabled_in_the_status(tmp_path, monkeypatch):
    """driver-enable-stuck on the model rig: STATUS_FLAGS' DRIVERS_ENABLED is the EN line read back on its pin
    (mega_drum.cpp: PINH), so an idle rig that asked for its drivers off reads them enabled while the line is stuck
    active, and disabled once it is mended (before issue 75 it reported the output latch: "disabled" whatever the
    line did, and the fault had no effect on the model rig)."""
    from rigctl.rigs import open_rig

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    with open_rig("inprocess", seed=2, host_config_path=tmp_path / "rig.json") as rig:
        rig.drum.home()
        rig.drum.wait_state([DrumState.IDLE], timeout_s=30.0)
        assert not rig.drum.read_status().drivers_enabled
        rig.backend.inject_faults([parse_fault("driver-enable-stuck@0")])
        rig.drum.clock.sleep(0.1)
        assert rig.drum.read_status().drivers_enabled
        rig.backend.inject_faults([parse_fault("driver-enable-stuck@0+0.05")])
        rig.drum.clock.sleep(0.2)
        assert not rig.drum.read_status().drivers_enabled
