"""examples/*.py (percent-format scripts: run as scripts or cell by cell in Jupyter/VS Code) run in the suite: all of
them in one interpreter (the imports paid once), each in an empty folder of its own, and each prints what it says."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

_RUNNER = """
import os, runpy, sys, warnings
warnings.simplefilter("error")  # an example that warns is a broken example
for path, folder in zip(sys.argv[1::2], sys.argv[2::2]):
    os.makedirs(folder)
    os.chdir(folder)
    print(f"@@example {os.path.basename(path)}", flush=True)
    runpy.run_path(path, run_name="__main__")
"""


def test_every_example_runs(tmp_path):
    scripts = sorted(EXAMPLES.glob("*.py"))
    assert {p.name for p in scripts} == {"record_and_look.py", "paper_analysis.py", "import_recordings.py"}
    args = [a for p in scripts for a in (str(p), str(tmp_path / p.stem))]
    r = subprocess.run([sys.executable, "-c", _RUNNER, *args], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    out = dict(part.split("\n", 1) for part in r.stdout.split("@@example ")[1:])
    assert "trials complete: 6/6" in out["record_and_look.py"] and "plate L" in out["record_and_look.py"]
    assert "speed_scaled   5 PCs:" in out["paper_analysis.py"] and "chance 33 %" in out["paper_analysis.py"]
    assert "cork__R5.npy: trial count 8 is an outlier" in out["import_recordings.py"]
    assert "from cork__R2.npy samples" in out["import_recordings.py"]
