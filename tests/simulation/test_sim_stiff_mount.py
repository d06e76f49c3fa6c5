"""Issue 75: a stiff mount the probe accepts never latches FORCE_LIMIT on a fault-free press (docs/wire-protocol.md
2.11, the force loop's limit governor in controller.c). Before the governor, fault-free presses of 1,400-1,450 g on
2,000-2,400 g/mm mounts latched FORCE_LIMIT on the loop's own approach at both HX711 rates (at 80 SPS its clamp speed
raised the reading 150 g a period, which the trip extrapolates 3 periods ahead), the true force under 1,460 g."""

from __future__ import annotations

import pytest

from rigctl.core.drum import Fault
from rigctl.rigs import open_rig
from rigctl.simulation.campaign import FORCE_BOUND_G, ModelTruth
from rigctl.simulation.model import MechanicsConfig, RigConfig


@pytest.mark.parametrize("sps,k", [(80, 2200.0), (10, 2000.0)])
def test_a_fault_free_press_on_a_stiff_mount_settles_without_a_latch(tmp_path, monkeypatch, sps, k):
    """1,450 g (50 g under FORCE_LIMIT), twice, on a mount of ``k`` g/mm the probe accepts at ``sps``: both settle
    (no FORCE_LIMIT, no fault), the true force within 60 g of the setpoint."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    cfg = RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=k))
    with open_rig("inprocess", seed=5, host_config_path=tmp_path / "rig.json", hx711_rate_sps=sps, config=cfg) as rig:
        truth = ModelTruth(rig.backend.engine)
        for _ in range(2):
            rig.press(1450, timeout_s=30)
            status = rig.drum.read_status()
            assert status.faults == Fault(0), status
            assert status.contact_stiffness_g_per_mm == pytest.approx(k, rel=0.1)
            rig.release()
        peak = truth.array()[:, 1].max()
        assert peak <= 1450 + 60 and peak <= FORCE_BOUND_G, peak
