"""``benchmarks/bench_force_loop.py --quick`` runs in CI (issue 39 item 8): it HOMEs each harness first (it failed at
once with DrumNotHomed before), makes the bring-up press (the contact probe measures 500 g/mm) and the firmware's
force loop settles at 80 and 10 SPS at 500 g/mm (~40 s: the 10 SPS probe takes ~10.5 s)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.hil

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_force_loop.py"


def test_bench_force_loop_quick(fw_build):
    run = subprocess.run([sys.executable, str(BENCH), "--quick", "--json"], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    rows = json.loads(run.stdout)
    assert sorted(r["rate_sps"] for r in rows) == [10, 80]
    for r in rows:
        assert r["settle_s"] is not None and r["overshoot_g"] < 100 and not r["oscillating"], r
        assert not r["refused"] and abs(r["stiffness_measured_g_per_mm"] - 500) <= 25, r  # the bring-up probe
