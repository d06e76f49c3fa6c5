"""Issue 75 items 3 and 6: the reading's scale checked against something other than the reading (docs/wire-protocol.md
2.12, docs/safety.md "Common causes"). A load cell's gain, or a wrong calibration saved with a valid checksum, scales
the reading and the probed stiffness together (both firmware channels allowed 1/X of the true force: 2,825 g for a
gain of 0.5 under simavr, issue 75's table); the contact's stiffness stored with the calibration is not the reading's,
so the next probe latches LOADCELL_SCALE before any press past the probe's force. The model rig: controller.c through
cffi, the model's physics, judged on the truth (the model's contact force)."""

from __future__ import annotations

import pytest

from rigctl.acquisition import calibration
from rigctl.acquisition.safety import LatchedFault
from rigctl.core.drum import Fault
from rigctl.core.faults import FaultSpec
from rigctl.rigs import open_rig
from rigctl.simulation.campaign import ModelTruth
from rigctl.simulation.model import MechanicsConfig, RigConfig

K_G_PER_MM = 800.0
SETPOINT_G = 1000.0


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    cfg = RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=K_G_PER_MM))
    with open_rig("inprocess", seed=11, host_config_path=tmp_path / "rig.json", config=cfg) as r:
        yield r


def _press_latches(rig, truth: ModelTruth) -> float:
    """A press of SETPOINT_G that must latch LOADCELL_SCALE at its probe; returns the largest true force, g."""
    n0 = len(truth.rows)
    with pytest.raises(LatchedFault, match="stiffness stored at calibration"):
        rig.press(SETPOINT_G, timeout_s=60)
    st = rig.drum.read_status()
    assert st.faults == Fault.LOADCELL_SCALE, st
    rig.drum.clock.sleep(3.0)  # the back-off (the probe's step proved the way)
    assert rig.drum.read_status().force_g < 5
    return max(row[1] for row in truth.rows[n0:])


def test_a_scale_error_latches_at_the_next_probe_and_the_reference_mass_mends_it(rig):
    truth = ModelTruth(rig.backend.engine)
    assert rig.drum.calibration_stiffness() == K_G_PER_MM  # the factory's calibration stored the rig's own plate
    rig.press(SETPOINT_G, timeout_s=60)  # fault-free: the probe agrees
    assert rig.drum.read_status().contact_stiffness_g_per_mm == pytest.approx(K_G_PER_MM, rel=0.06)
    rig.release()

    # the cell's gain halves (an excitation lead's joint): the loop would press 2,000 g read as 1,000 g
    rig.backend.inject_faults([FaultSpec("cell-gain", 0.0, value=0.5)])
    peak = _press_latches(rig, truth)
    assert peak < 400, peak  # the probe's 150 g read, 300 g true: never the setpoint's 2,000 g
    # acknowledged, the next start probes again and latches again: no start presses on the wrong scale
    rig.acknowledge("test: the cell not yet mended", by="test")
    assert _press_latches(rig, truth) < 400
    rig.acknowledge("test: recalibrating with the reference mass", by="test")

    # a reset keeps the stored stiffness (EEPROM): it does not defeat the check
    rig.backend.inject_faults([FaultSpec("reset", 0.0)])
    rig.drum.clock.sleep(0.5)
    assert rig.drum.calibration_stiffness() == K_G_PER_MM

    # the cell's scale verified with the reference mass: the calibration stores the contact again; presses agree
    rig.home_if_pending()
    place, remove = calibration.simulated_mass(rig)
    result = calibration.calibrate_loadcell(rig.drum, 500.0, place_mass=place, remove_mass=remove, config_file=False)
    assert result.contact_stiffness_g_per_mm == pytest.approx(K_G_PER_MM, rel=0.06)
    n0 = len(truth.rows)
    rig.press(SETPOINT_G, timeout_s=60)
    assert rig.drum.read_status().faults == Fault(0)
    assert max(row[1] for row in truth.rows[n0:]) == pytest.approx(SETPOINT_G, abs=60)  # the true force right
    rig.release()


@pytest.mark.parametrize("spec", [FaultSpec("calibration-scale", 0.0, 0.0, 2.0),
                                  FaultSpec("calibration-scale", 0.0, 0.0, 0.6),
                                  FaultSpec("contact-stiffness", 0.0, value=2.0 * K_G_PER_MM)])
def test_a_wrong_calibration_saved_or_another_plate_latches_before_any_press(rig, spec):
    """A wrong calibration saved with a valid checksum (then a power cycle: HOME first), or a plate twice as stiff
    swapped in (another material): LOADCELL_SCALE at the probe, never the setpoint's force."""
    truth = ModelTruth(rig.backend.engine)
    rig.backend.inject_faults([spec])
    rig.drum.clock.sleep(0.5)
    if spec.name == "calibration-scale":  # then a power cycle: the rig latches the reset at its next start
        with pytest.raises(LatchedFault, match="reset"):
            rig.press(SETPOINT_G, timeout_s=60)
        rig.acknowledge("test: the power cycle", by="test")
    peak = _press_latches(rig, truth)
    assert peak < 400, peak


def test_no_stiffness_stored_no_check(rig):
    """None stored (a record of firmware 1.5 or older, a board never calibrated by this rigctl): the check does not run; the
    press goes on at the gain's force (the stall bounds it as built), and the doctor says so (test_doctor)."""
    rig.drum.set_calibration_stiffness(0)
    rig.backend.inject_faults([FaultSpec("cell-gain", 0.0, value=0.8)])
    rig.press(SETPOINT_G, timeout_s=60)
    assert rig.drum.read_status().faults == Fault(0)
    rig.release()
