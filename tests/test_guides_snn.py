"""The spiking-network guide's recipes for Tonic, snnTorch and SpikingJelly (docs/guides/spiking-networks.md section
3b; issue 79 item 4), run as a user runs them: the page's own blocks up to its exported events, then the recipes.

An optional tier (mark ``snn``): rigctl depends on none of these packages (Tonic is GPLv3; snnTorch and SpikingJelly
need PyTorch), and the default CI installs none of them, so the test skips, naming what is missing, unless they are
installed beside rigctl (``pip install tonic snntorch spikingjelly torch``).
"""

from __future__ import annotations

import importlib.util
import re

import pytest

from .guides import blocks, run_page

pytestmark = [pytest.mark.snn, pytest.mark.slow]

PAGE = "docs/guides/spiking-networks.md"
TEST = "tests/test_guides_snn.py::test_snn_recipes_run_as_written"
PACKAGES = ("tonic", "snntorch", "spikingjelly", "torch")


@pytest.mark.timeout(1200)
def test_snn_recipes_run_as_written(tmp_path):
    missing = [p for p in PACKAGES if importlib.util.find_spec(p) is None]
    if missing:
        pytest.skip(f"the optional snn tier needs {', '.join(missing)} beside rigctl (pip install tonic snntorch "
                    "spikingjelly torch); rigctl depends on none of them and its CI does not install them")
    recipes = [b.line for b in blocks(PAGE) if b.markers.get("run-by") == TEST]
    first = min(recipes)
    # the page's blocks before the recipes (its session, encoded and exported as events), then the recipes
    runs = run_page(PAGE, tmp_path / "work", preload=False,
                    select=lambda b: b.markers.get("run-by") == TEST or (b.runs_here and b.line < first))
    out = {r.block.text.strip(): r.output for r in runs if r.block.lang == "sh"}
    tonic = out["python tonic_frames.py"]
    grid = re.search(r"trial grid: \[\((\d+), 2, 2, 9\)\] frames, (\d+) of (\d+) spikes in a frame", tonic)
    assert grid and grid[2] == grid[3] and int(grid[1]) == 10, tonic  # one grid: 1 s trials, ten windows, all spikes
    default = re.search(r"ToFrame's defaults: \[([\d, ]+)\] frames, (\d+) of (\d+) spikes", tonic)
    assert default and int(default[2]) < int(default[3]), tonic  # the page's claim: the defaults drop spikes
    snn = re.search(r"snnTorch over 10 windows as time steps: ([\d.]+)% of (\d+) untrained-speed test trials \(chance "
                    r"([\d.]+)%\)", out["python snntorch_windows.py"])
    assert snn and float(snn[1]) > 2 * float(snn[3]), out["python snntorch_windows.py"]
    jelly = re.search(r"SpikingJelly: (\d+) trials as t, x, y, p; trial 0: frames \(10, 2, 2, 9\), (\d+) of (\d+) "
                      r"spikes", out["python spikingjelly_frames.py"])
    assert jelly and int(jelly[1]) == 256 and jelly[2] == jelly[3], out["python spikingjelly_frames.py"]
