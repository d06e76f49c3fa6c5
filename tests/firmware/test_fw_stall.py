"""The simavr harness's stall current option (``--actuator-stall-g``, ``MechanicsConfig.actuator_stall_g``; issue 55
item 6, docs/hardware/wiring.md's Vref setting): the actuator's steps towards the sensor are lost once the spring's
force reaches it, as a driver set to stall near 1.5 x the largest force does. Off in every safety test
(tests/simulation/test_sim_stall.py)."""

from __future__ import annotations

import pytest

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation import hil
from rigctl.simulation.model import MechanicsConfig, RigConfig

from .conftest import home

pytestmark = pytest.mark.hil

HR = wire.HoldingRegister


def test_the_harness_stall_current_limits_the_force(fw_build):
    """PRESS 1000 g onto a 1000 g/mm contact with the stall at 600 g: the true force (the harness's spring) levels
    off at 600 g while the firmware's step count goes on (its POSITION_LIMIT then stops it)."""
    mech = MechanicsConfig(contact_stiffness_g_per_mm=1000.0, contact_gap_mm=1.0, actuator_stall_g=600.0)
    rig = hil.HilRig(RigConfig(mechanics=mech), live=False, with_uno=False, tel_ms=5.0).start()
    try:
        drum = DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"), clock=rig.clock).open()
        try:
            drum.write_holding(HR.WATCHDOG_MS, 10000)
            home(drum)
            drum.set_force(1000)
            drum.press()
            end, peak = rig.next_telemetry().t_s + 4.0, 0.0
            while (tel := rig.next_telemetry()).t_s < end:
                peak = max(peak, tel.force_g)
                drum.read_status()
        finally:
            drum.close()
    finally:
        rig.close()
    assert 590.0 <= peak <= 602.0, peak
