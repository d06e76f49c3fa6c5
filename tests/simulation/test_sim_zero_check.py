"""Issue 75 item 5, plausibility over time (docs/wire-protocol.md 2.13): a reading that moves with no step. The load
cell's zero moving between trials, with the actuator at home (a cell knocked or overloaded, a pulled cable, something
resting on the sensor), made the next press's probe take the offset for the contact: fresh campaign seed 775401
(+302 g, a setpoint of 307 g, 442 g/mm, 10 SPS) recorded a trial with no contact on firmware 1.6. The press's start now
judges its settled reading against the tare (LOADCELL_ZERO), and the probe's steps against the stored stiffness. The
model rig: controller.c through cffi, the model's physics, judged on the truth (the model's contact force)."""

from __future__ import annotations

import pytest

from rigctl.acquisition.rigconfig import update_rig_config
from rigctl.acquisition.safety import LatchedFault
from rigctl.core.drum import Fault
from rigctl.core.faults import FaultSpec
from rigctl.devices import wire
from rigctl.devices.drum import default_force_loop
from rigctl.rigs import open_rig
from rigctl.simulation.campaign import CONTACT_G, ModelTruth
from rigctl.simulation.model import MechanicsConfig, RigConfig


def _rig(tmp_path, monkeypatch, k_g_per_mm: float, rate_sps: int, seed: int):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    host = tmp_path / "rig.json"
    if rate_sps != 80:  # the lab's rig config for its 10 SPS board (as the campaign's)
        update_rig_config(host, force_loop=default_force_loop(rate_sps).to_dict())
    cfg = RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=k_g_per_mm, hx711_rate_sps=float(rate_sps)))
    return open_rig("inprocess", seed=seed, host_config_path=host, config=cfg)


@pytest.mark.parametrize("offset_g,setpoint_g,k_g_per_mm,rate_sps", [
    (302.4, 307.0, 442.0, 10),   # 775401's case
    (150.0, 120.0, 2000.0, 80),  # an offset past the setpoint on a stiff mount
    (-300.0, 800.0, 300.0, 10),  # a zero fallen (a reading the direction watch would take for a reversed motor)
    (12.0, 100.0, 1000.0, 80),   # just past PRESS_DIR_G
    (900.0, 1400.0, 250.0, 80),  # a large one under the force limit
])
def test_an_offset_between_trials_never_records_a_trial_without_contact(tmp_path, monkeypatch, offset_g, setpoint_g,
                                                                        k_g_per_mm, rate_sps):
    """A trial, the cell's zero moves by ``offset_g`` with the actuator at home, the next press: LOADCELL_ZERO before
    any step (the true force stays 0: nothing pressed on a reading that is not the contact's), advice naming the
    cell's zero first; acknowledged, the start HOMEs and tares again and the press holds the true setpoint."""
    with _rig(tmp_path, monkeypatch, k_g_per_mm, rate_sps, seed=int(abs(offset_g))) as rig:
        truth = ModelTruth(rig.backend.engine)
        rig.press(setpoint_g, timeout_s=60)
        rig.release()
        rig.drum.clock.sleep(2.0)
        rig.backend.inject_faults([FaultSpec("cell-offset", 0.0, value=offset_g)])
        rig.drum.clock.sleep(1.0)
        n0 = len(truth.rows)
        with pytest.raises(LatchedFault, match="read a force with nothing pressing") as exc:
            rig.press(setpoint_g, timeout_s=60)
        assert "resting on the sensor" in str(exc.value)
        st = rig.drum.read_status()
        assert st.faults == Fault.LOADCELL_ZERO, st
        assert max(row[1] for row in truth.rows[n0:]) < CONTACT_G  # nothing pressed
        rig.acknowledge("test: nothing found resting on the sensor; the cell's zero moved", by="test")
        n0 = len(truth.rows)
        rig.press(setpoint_g, timeout_s=60)  # the start HOMEs (tared again at home), probes, holds
        assert rig.drum.read_status().faults == Fault(0)
        rig.drum.clock.sleep(1.0)
        held = [row[1] for row in truth.rows[-20:]]
        assert min(held) > setpoint_g - 60 and max(held) < setpoint_g + 60, held
        rig.release()


def test_an_offset_within_the_noise_band_presses_at_the_force_less_the_offset(tmp_path, monkeypatch):
    """An offset of PRESS_DIR_G or less is not judged a fault (the model's noise is 0.8 g a reading, a real HX711's
    ~0.1 g): the press holds, the true force off by the offset, the contact kept."""
    assert wire.PRESS_DIR_G == 8
    with _rig(tmp_path, monkeypatch, 800.0, 80, seed=5) as rig:
        truth = ModelTruth(rig.backend.engine)
        rig.press(300.0, timeout_s=60)
        rig.release()
        rig.drum.clock.sleep(2.0)
        rig.backend.inject_faults([FaultSpec("cell-offset", 0.0, value=4.0)])
        rig.drum.clock.sleep(1.0)
        rig.press(300.0, timeout_s=60)
        assert rig.drum.read_status().faults == Fault(0)
        rig.drum.clock.sleep(1.0)
        held = [row[1] for row in truth.rows[-20:]]
        assert min(held) > 250 and max(held) < 340, held
        rig.release()


def test_an_offset_during_the_approach_latches_at_the_probe(tmp_path, monkeypatch):
    """The zero moves while the actuator approaches, before the contact: the probe takes the load for the contact and
    its steps raise none where the stored stiffness says they press: LOADCELL_ZERO at the probe, nothing pressed."""
    with _rig(tmp_path, monkeypatch, 442.0, 80, seed=7) as rig:
        truth = ModelTruth(rig.backend.engine)
        rig.press(307.0, timeout_s=60)
        rig.release()
        rig.drum.clock.sleep(2.0)
        n0 = len(truth.rows)
        rig.backend.inject_faults([FaultSpec("cell-offset", 0.3, value=302.0)])  # 0.3 s into the next press
        with pytest.raises(LatchedFault, match="read a force with nothing pressing"):
            rig.press(307.0, timeout_s=60)
        assert rig.drum.read_status().faults & Fault.LOADCELL_ZERO
        assert max(row[1] for row in truth.rows[n0:]) < CONTACT_G


@pytest.mark.parametrize("how", ["cell-dead", "coupling-slip", "steps-lost", "reversed-actuator"])
def test_a_press_with_no_force_rise_within_its_travel_latches_contact_missing(tmp_path, monkeypatch, how):
    """Issue 75 item 5's other half (spec 2.13, firmware 1.9): a trial locates the contact; then the cell reads
    nothing (an excitation lead broken: 2 % of the signal left), or the coupling slips 50 % of the motor's travel, or
    the motor loses 50 % of its steps, or a coil pair is swapped. The next press's approach passes the located
    contact by PROBE_LOCATED_MARGIN_UM plus the probe's contact load's travel with no force read: CONTACT_MISSING,
    standing where it latched (no longer homed). The true force stays under the probe's contact load plus
    k x 0.3 mm (a wound coupling's catch-up included: it brings the screw to where the steps put the motor), and the
    motor takes no step towards the sensor after the latch (the campaign's judge). CLEAR_FAULT: NOT_HOMED."""
    from rigctl.simulation.campaign import check_invariants

    k = 800.0
    with _rig(tmp_path, monkeypatch, k, 80, seed=3) as rig:
        truth = ModelTruth(rig.backend.engine)
        rig.press(300.0, timeout_s=60)
        rig.release()
        rig.drum.clock.sleep(2.0)
        if how == "cell-dead":
            rig.backend.engine.model.loadcell_gain = 0.02
        else:
            rig.backend.inject_faults([FaultSpec(how, 0.0, value=None if how == "reversed-actuator" else 50.0)])
        rig.drum.clock.sleep(0.5)
        n0 = len(truth.rows)
        with pytest.raises(LatchedFault, match="no force where the contact was"):
            rig.press(300.0, timeout_s=60)
        rig.drum.clock.sleep(3.0)
        st = rig.drum.read_status()
        assert st.faults == Fault.CONTACT_MISSING, st
        rows = truth.rows[n0:]
        assert max(row[1] for row in rows) < 50 + 0.3 * k + 60
        (latch,) = truth.latch_spans
        assert check_invariants(truth.array(), latches=[latch]) == []
        rig.drum.clear_fault()
        assert rig.drum.read_status().state == wire.DrumState.NOT_HOMED
