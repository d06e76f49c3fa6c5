"""The actuator driver's stall current as a rig option (issue 55 item 6; docs/hardware/wiring.md, "Driver current"):
the motor skips instead of pressing further once the contact force reaches ``MechanicsConfig.actuator_stall_g``, on the
model rig and in the simavr harness (``--actuator-stall-g``). Off by default and in every firmware safety test: the
firmware's protection must hold without it wherever it can (a bench whose Vref is set high, or a driver swapped, has
none); the fault campaign runs the rig as built (issue 75: the stall bounds the rows no firmware channel can)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from rigctl.simulation.campaign import draw_case
from rigctl.simulation.hil import HilRig
from rigctl.simulation.model import MechanicsConfig, RigConfig, RigModel

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_fault_campaign.py"


def _push(stall_g: float) -> float:
    """The model pushed forward at 5 mm/s for 2 s onto a 1000 g/mm contact 1 mm away: the peak contact force, g."""
    model = RigModel(RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=1000.0, contact_gap_mm=1.0,
                                                         actuator_stall_g=stall_g)))
    peak = 0.0
    for _ in range(200):
        model.advance(10, drum_step_rate_hz=0.0, actuator_velocity_mm_s=5.0, render=False)
        peak = max(peak, model.contact_force_g)
    return peak


def test_the_drivers_stall_current_limits_the_force_when_modelled():
    """With the stall at 600 g the force levels off near it (the motor skips: the steps sent go on); without it the
    same drive presses on to the end of the spring's travel."""
    assert 550.0 <= _push(600.0) <= 620.0  # (the runout and texture ripple aside: the model stalls at the spring)
    assert _push(0.0) > 5000.0


def test_the_stall_is_off_in_every_safety_test_and_as_built_in_the_campaign(tmp_path):
    """The default rig and a default HilRig's harness model no stall (the firmware's safety tests judge the firmware
    alone); the fault campaign runs the rig as built (issue 75: docs/hardware's stall, above the largest setpoint and
    FORCE_LIMIT_G, at most 1.1 x FORCE_LIMIT_G), and without it with --firmware-only."""
    from rigctl.simulation.campaign import FORCE_BOUND_G

    assert MechanicsConfig().actuator_stall_g == 0.0
    spec = importlib.util.spec_from_file_location("bench_fault_campaign", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_fault_campaign", bench)
    spec.loader.exec_module(bench)
    assert 1500.0 < bench.AS_BUILT_STALL_G <= FORCE_BOUND_G
    for seed in range(5500, 5540):
        cfg, _ = bench._rig_files(draw_case(seed), tmp_path)
        assert cfg.mechanics.actuator_stall_g == bench.AS_BUILT_STALL_G, seed
        cfg, _ = bench._rig_files(draw_case(seed), tmp_path, as_built=False)
        assert cfg.mechanics.actuator_stall_g == 0.0, seed
    assert "--actuator-stall-g" not in HilRig(RigConfig(), live=False, with_uno=False)._hardware_args()
    on = HilRig(RigConfig(mechanics=MechanicsConfig(actuator_stall_g=1500.0)), live=False, with_uno=False)
    assert on._hardware_args()[-2:] == ["--actuator-stall-g", "1500.0"]
