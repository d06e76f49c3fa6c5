"""A fixed-seed slice of the fault campaign on the real firmware under simavr (issue 55 item 7; the model rig's:
tests/simulation/test_sim_fault_campaign.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.simulation.campaign import FORCE_BOUND_G

pytestmark = pytest.mark.hil

#: cases under simavr (the Mega alone for its faults, both boards for the Uno's: benchmarks/bench_fault_campaign.py
#: HIL_UNO_FAULTS)
HIL_SLICE = 2
SLICE_SEED = 5500
BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_fault_campaign.py"


@pytest.mark.timeout(1200)  # ~40 CPU-s; 2 min of wall time at load 20
def test_a_fixed_seed_slice_of_the_campaign_under_simavr(fw_build):
    """HIL_SLICE cases on the real firmware under simavr (both boards; the truth log the harness's): no violation."""
    proc = subprocess.run([sys.executable, str(BENCH), "--cases", str(HIL_SLICE), "--seed", str(SLICE_SEED), "--rig",
                           "hil", "--json"], capture_output=True, text=True, timeout=900)
    assert proc.returncode in (0, 1), proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert out["cases"] == HIL_SLICE
    assert out["violations"] == [], json.dumps(out["violations"], indent=1)
    assert out["worst_true_force_g"] <= FORCE_BOUND_G
