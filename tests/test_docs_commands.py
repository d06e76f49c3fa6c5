"""The documents' commands run as written (at a small size): docs/results.md section 2a (FabricSlide speed
extrapolation with whole trials). The guides and docs/my-sensor.md run in tests/test_guides.py."""

from __future__ import annotations

import glob
import json
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner

from rigctl.cli import main

DOCS = Path(__file__).resolve().parents[1] / "docs"


def section(page: str, heading: str) -> str:
    """The text of ``page`` from the heading that starts with ``heading`` to the next heading of any level."""
    text = (DOCS / page).read_text()
    start = text.index(heading)
    rest = text[start + len(heading):]
    ends = [i for i in (rest.find("\n## "), rest.find("\n### ")) if i >= 0]
    return rest[:min(ends)] if ends else rest


def rigctl(line: str, cwd: Path):
    """Run one documented ``rigctl ...`` command line in-process in ``cwd`` (shell globs expanded there)."""
    args = []
    for word in shlex.split(line)[1:]:
        hits = sorted(glob.glob(str(cwd / word))) if any(c in word for c in "*?[") else []
        args += [str(Path(h).relative_to(cwd)) for h in hits] or [word]
    return CliRunner().invoke(main, args)


@pytest.mark.slow
def test_results_2a_commands_at_a_small_size(tmp_path, monkeypatch, fabricslide_dir):
    """2a's seven commands, on two fabrics' F120 recordings of the first repeat, 2 repetitions, 5 PCs."""
    lines = [line.strip() for line in section("results.md", "### 2a.").splitlines() if line.startswith("    rigctl ")]
    assert [line.split()[1] for line in lines] == ["import-fabricslide", "encode", "encode"] + ["analyze"] * 4
    monkeypatch.chdir(tmp_path)
    small = {"../shared/data/fabricslide": f"{fabricslide_dir} --pattern [CL]*_F120_*_0.csv",
             "--repeats 20": "--repeats 2 --pcs 1-5 --no-progress"}
    results = []
    for line in lines:
        for a, b in small.items():
            line = line.replace(a, b)
        r = rigctl(line, tmp_path)
        assert r.exit_code == 0, (line, r.output[-2000:])
        if "--json" in line:
            results.append(json.loads(r.stdout))
    rows = ("speed_untrained_speed", "speed_trained", "baseline_removed:speed_untrained_speed",
            "baseline_removed:speed_trained")
    for res in results:  # every row of the table, for each variant asked for
        assert set(res["tasks"]) == set(rows)
    slow_to_fast = results[0]["tasks"]["speed_untrained_speed"]["variants"]
    assert slow_to_fast["speed_scaled"]["table"]["mu_pct"] > slow_to_fast["original"]["table"]["mu_pct"] + 10
