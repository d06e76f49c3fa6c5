"""``benchmarks/bench_force_loop.py --quick`` runs in CI (issue 39 item 8): it HOMEs each harness first (it failed at
once with DrumNotHomed before), makes the bring-up press (the contact probe measures 500 g/mm) and the firmware's
force loop settles at 80 and 10 SPS at 500 g/mm. The two rates run as two benchmark processes side by side (each
its own pair of harnesses; ~20 s instead of ~40 s one after the other: the 10 SPS probe takes ~10.5 s)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.hil

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_force_loop.py"


def test_bench_force_loop_quick(fw_build):
    runs = [subprocess.Popen([sys.executable, str(BENCH), "--quick", "--json", "--rates", rate],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for rate in ("80", "10")]
    rows = []
    for run in runs:
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, err[-2000:]
        rows += json.loads(out)
    assert sorted(r["rate_sps"] for r in rows) == [10, 80]
    for r in rows:
        assert r["settle_s"] is not None and r["overshoot_g"] < 100 and not r["oscillating"], r
        assert not r["refused"] and abs(r["stiffness_measured_g_per_mm"] - 500) <= 25, r  # the bring-up probe
