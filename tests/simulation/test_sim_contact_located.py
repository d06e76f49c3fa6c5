"""Issue 55 item 4 on the model rig: a contact one press probed is located for the next (kept across a release until
HOME, a fault or a reset, docs/wire-protocol.md 2.11): the next press approaches it at the loop's clamp speed up to
PROBE_LOCATED_MARGIN_UM before it and probes from there, so a protocol of many presses is not ~10 s slower each at
10 SPS, and the stiffness is still measured at every press (a plate swapped for a stiffer one is refused)."""

from __future__ import annotations

import pytest

from rigctl.core.drum import Fault
from rigctl.core.faults import parse_fault
from rigctl.rigs import open_rig
from rigctl.simulation.campaign import FORCE_BOUND_G, ModelTruth
from rigctl.simulation.model import MechanicsConfig, RigConfig


def test_a_located_contact_is_approached_fast_and_its_stiffness_measured_again(tmp_path, monkeypatch):
    """10 SPS, 1 kg/mm, 3 mm gap, 500 g: the first press locates the contact (13.3 s of simulated time, most of it
    the probe's 0.33 mm/s approach), the second, after a release, takes less than 60 % of that (5.7 s) and measures
    the stiffness again; the plate then swapped at rest for a 4 kg/mm one (above the 2.5 kg/mm the 10 SPS gains
    hold) is refused at the next press (CONTACT_STIFFNESS), the true force never past 1650 g. With every press
    probing from home (firmware 1.2) both presses took ~13 s."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    cfg = RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=1000.0))
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json", hx711_rate_sps=10, config=cfg) as rig:
        truth = ModelTruth(rig.backend.engine)
        clock = rig.drum.clock
        spans = []
        for _ in range(2):
            t0 = clock.now()
            rig.press(500, timeout_s=20)
            spans.append(clock.now() - t0)
            assert rig.drum.read_status().contact_stiffness_g_per_mm == pytest.approx(1000, rel=0.1)
            rig.release()
        assert spans[1] < 0.6 * spans[0], spans
        rig.backend.inject_faults([parse_fault("contact-stiffness=4000@0")])
        with pytest.raises(Exception, match="CONTACT_STIFFNESS|too stiff"):
            rig.press(500, timeout_s=20)
        assert Fault.CONTACT_STIFFNESS in rig.drum.read_status().faults
        assert truth.array()[:, 1].max() <= FORCE_BOUND_G
