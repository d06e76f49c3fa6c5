"""Advice never worse than the fault (issue 75 item 4): on the model rig (controller.c through cffi), each fault of
the campaign's list (the FMEA's rows, docs/safety.md) in one case of its own, then an operator who follows the latched
fault's advice literally, three rounds of "do what it says, acknowledge, start"
(``benchmarks/bench_fault_campaign.py --walk-advice``: AdviceWalk). Judged on the truth: the campaign's invariants
(the true force <= 1.1 x FORCE_LIMIT, no step towards the sensor while latched) and no part the advice had rewired
the wrong way that was right before (a coil pair of a good motor, A+/A- of a good cell)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from rigctl.simulation.campaign import CAMPAIGN_FAULTS, draw_case

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_fault_campaign.py"
#: each fault's case: seed WALK_SEED + its index in the campaign's list, drawn from that fault alone
WALK_SEED = 7100


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_fault_campaign", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("fault", CAMPAIGN_FAULTS)
def test_following_the_advice_is_never_worse_than_the_fault(bench, fault, tmp_path):
    case = draw_case(WALK_SEED + CAMPAIGN_FAULTS.index(fault), [fault])
    out = bench.run_model_case(case, tmp_path, walk_advice=True)
    said = f"{case.describe()}: walk {out['advice_walk']}"
    assert out["not_run"] is None, said
    assert out["violations"] == [], (out["violations"], said)
    assert out["advice_miswired"] == [], (out["advice_miswired"], said)


def test_the_walker_does_what_the_advice_says(bench, tmp_path):
    """The walker itself: an e-stop held through the walk has its acknowledgement refused each round (nothing
    moves); a reversed actuator from power-on is told from a reversed cell by the hand press and its coils swapped,
    and the rig then presses and releases."""
    from rigctl.simulation.campaign import Case

    estop = Case(seed=1, fault="estop", value=None, moment="settled", moment_fraction=0.1, duration_s=1e3,
                 stiffness_g_per_mm=1000.0, hx711_rate_sps=80, forces_g=(800.0, 800.0), speed_mm_s=80.0)
    out = bench.run_model_case(estop, tmp_path, walk_advice=True)
    assert out["advice_walk"].count("acknowledge refused: LatchedFault") == bench.WALK_ROUNDS, out["advice_walk"]
    reversed_ = Case(seed=2, fault="reversed-actuator", value=None, moment="power-on", moment_fraction=0.0,
                     duration_s=1e3, stiffness_g_per_mm=1000.0, hx711_rate_sps=80, forces_g=(800.0, 800.0),
                     speed_mm_s=80.0)
    out = bench.run_model_case(reversed_, tmp_path, walk_advice=True)
    walk = out["advice_walk"]
    assert any("saw the screw close the gap: swapped a coil pair" in step for step in walk), walk
    assert any(step.startswith("pressed") for step in walk), walk
    assert out["violations"] == [] and out["advice_miswired"] == [], out
