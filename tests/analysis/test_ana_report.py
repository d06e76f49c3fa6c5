"""Plots and tables a reader trusts (issue 38 part 4): chance level and n on the accuracy plots, the error bars named,
the paper's values drawn with --compare-paper, significance marks with a direction, human row names, no NaN in text,
a plot with nothing to show refused before any work. Built on hand-made results (no analysis runs: < 1 s each but
the PNG ones, ~1 s)."""

from __future__ import annotations

import pickle
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner


def _results(n_pcs=6, repeats=5, n_classes=4, tasks=("textures", "baseline_removed:speed_untrained_speed")):
    from rigctl.analysis.results import Curve, TaskResults

    rng = np.random.default_rng(0)
    res = TaskResults()
    classes = [f"T{i}" for i in range(n_classes)]
    for task in tasks:
        for v, level in (("original", 0.5), ("speed_scaled", 0.9), ("force_scaled", 0.3)):
            acc = np.clip(level + rng.normal(0, 0.02, (repeats, n_pcs)), 0, 1)
            res.add(Curve(task, v, acc, 40, classes, np.eye(n_classes, dtype=np.int64) * 10, n_pcs))
    res.counts = {"cv": {"per_texture": 10, "groups": None, "ratio": float("nan"), "speeds": [40.0, 60.0]}}
    return res


_SHOW = """
import pickle, sys
from rigctl.analysis import report
from rigctl.analysis.data import variant_title
from rigctl.analysis.results import task_title
res = pickle.loads(sys.stdin.buffer.read())
task = next(iter(res.curves))
report.table1(res, 3), report.chance_pct(res, task), report.n_text(res, task), report.to_csv(res)
task_title(task), variant_title("original"), res.curves[task]["original"].at(3)
print(" ".join(m for m in ("sklearn", "scipy.stats", "scipy.linalg", "rigctl.analysis.tasks") if m in sys.modules))
"""


def test_results_reach_a_face_without_the_classifiers():
    """What the GUI's Analysis tab does on its own thread when a job's results arrive: unpickle the
    :class:`TaskResults` (its class's module is imported), name the rows and variants, fill Table 1, the chance line,
    the n text, the CSV export. None of it may import scikit-learn or scipy (seconds of imports on a cold machine, the
    GUI frozen meanwhile): a fresh interpreter does it and lists what came in."""
    run = subprocess.run([sys.executable, "-c", _SHOW], input=pickle.dumps(_results()), capture_output=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    assert run.stdout.decode().split() == [], f"showing results imported {run.stdout.decode().strip()}"


def test_row_names_are_human():
    from rigctl.analysis.results import task_title

    assert task_title("baseline_removed:speed_untrained_speed") == (
        "Untrained Speed, speed-only extrapolation, baseline removed")
    assert task_title("speed_trained") == "Trained Speed and Force, speed-only extrapolation"
    assert task_title("textures") == "Individual Textures (Fig. 3A)"
    assert task_title("something_else") == "something_else"


def test_table_marks_say_which_variant_is_higher_and_text_has_no_nan():
    from rigctl.analysis import report

    text = report.format_table1(_results(), 6)
    assert "baseline_removed:" not in text and "speed_untrained_speed" not in text
    assert "Untrained Speed, speed-only extrapolation, baseline removed" in text
    row = next(ln for ln in text.splitlines() if ln.startswith("Individual Textures"))
    assert "**^" in row and "**v" in row  # speed_scaled 90 % > Original 50 % > force_scaled 30 %
    assert row.index("**^") < row.index("**v")  # Speed Scaled's column comes before Force Scaled's
    assert "^ this variant higher, v lower" in text
    assert "mean and sample SD over 5 repetitions" in text
    assert "nan" not in text.lower() and "{" not in text  # the counts line is text, not JSON with NaN
    assert "counts, cv: per_texture 10, groups none, ratio n/a, speeds 40,60" in text


def test_a_nan_accuracy_reads_as_a_dash():
    from rigctl.analysis import report

    res = _results(tasks=("textures",))
    res.curves["textures"]["force_scaled"].acc[:] = np.nan
    text = report.format_table1(res, 6, stars=False)
    assert "nan" not in text.lower()


def test_the_figure_names_error_bars_chance_n_and_the_papers_values(tmp_path, monkeypatch):
    import matplotlib.axes

    from rigctl.analysis import report

    drawn: dict[str, list] = {"errorbar": [], "axhline": [], "title": [], "suptitle": []}
    orig_eb, orig_hl = matplotlib.axes.Axes.errorbar, matplotlib.axes.Axes.axhline
    monkeypatch.setattr(matplotlib.axes.Axes, "errorbar",
                        lambda self, x, y, *a, **k: drawn["errorbar"].append((list(x), k.get("label")))
                        or orig_eb(self, x, y, *a, **k))
    monkeypatch.setattr(matplotlib.axes.Axes, "axhline",
                        lambda self, y=0, *a, **k: drawn["axhline"].append(y) or orig_hl(self, y, *a, **k))
    png = tmp_path / "fig.png"
    res = _results(tasks=("textures", "groups"))
    report.plot_curves(res, png, title="enc.h5", compare_paper=True)
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert drawn["axhline"] == [25.0, 25.0]  # chance: 1 / 4 classes in each panel
    paper = [x for x, label in drawn["errorbar"] if x == [50]]
    assert len(paper) == 6  # 3 variants x 2 panels, at the paper's 50 PCs
    assert ("paper (Table 1, 50 PCs)" in [lab for _, lab in drawn["errorbar"]])
    assert report.n_text(res, "textures") == "n = 40 test trials x 5 repetitions, 4 classes"
    assert "SD over repetitions" in report.ERROR_BARS


def test_nothing_to_plot_is_refused(tmp_path):
    from rigctl.analysis import report

    res = _results(n_pcs=1, tasks=("textures",))
    assert report.plottable(res) == []
    with pytest.raises(ValueError, match="--pcs 1-N"):
        report.plot_curves(res, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize(("args", "needle"), [(["--pcs", "1"], "--pcs 1-N"),
                                              (["--task", "variance"], "--task variance has no accuracy curves")])
def test_cli_refuses_a_plot_with_nothing_to_show_before_any_work(tmp_path, args, needle):
    from rigctl.cli import main

    enc = tmp_path / "d.enc.h5"
    enc.write_bytes(b"not read: refused before any work")
    r = CliRunner().invoke(main, ["analyze", str(enc), "--plot", str(tmp_path / "fig.png"), *args])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.output
    assert not (tmp_path / "fig.png").exists()
