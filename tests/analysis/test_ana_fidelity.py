"""The fidelity report (issue 13): the variance decomposition of the features, and the paper's ordering of the
variants checked row by row in the Table 1 printout."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.analysis.data import FeatureSet
from rigctl.cli import main

if TYPE_CHECKING:
    from rigctl.analysis.tasks import TaskResults


def _design(n_rep=4, textures=("A", "B", "C"), speeds=(40.0, 80.0), forces=(250.0, 500.0)):
    rows = [(t, s, f) for t in textures for s in speeds for f in forces for _ in range(n_rep)]
    tex, spd, frc = (np.array(c) for c in zip(*rows))
    return tex, spd.astype(float), frc.astype(float)


def _fs(x, tex, spd, frc, variant="original"):
    return FeatureSet(features={variant: np.asarray(x, dtype=np.float32)}, texture=tex, speed_mm_s=spd, force_g=frc)


def test_shares_of_a_constructed_design_are_recovered():
    """Features built from known effects: texture, condition, interaction and noise each in its own orthogonal
    column, so each share is the known sum of squares of its column over the total."""
    from rigctl.analysis.variance import decompose

    rng = np.random.default_rng(1)
    tex, spd, frc = _design(n_rep=6)
    n = tex.size
    t_eff = {"A": -1.0, "B": 0.0, "C": 1.0}
    c_eff = {(40.0, 250.0): -2.0, (40.0, 500.0): 0.0, (80.0, 250.0): 0.0, (80.0, 500.0): 2.0}
    col_t = np.array([t_eff[t] for t in tex])
    col_c = np.array([c_eff[(s, f)] for s, f in zip(spd, frc)])
    # interaction: texture effect flipped by speed, with zero texture and condition marginal means
    col_i = np.array([t_eff[t] * (1 if s == 40 else -1) for t, s in zip(tex, spd)])
    noise = rng.standard_normal(n)
    cells = [(t, s, f) for t, s, f in zip(tex, spd, frc)]
    for key in set(cells):  # noise with zero mean in every cell: purely within-cell
        m = np.array([c == key for c in cells])
        noise[m] -= noise[m].mean()
    x = np.stack([col_t, col_c, col_i, noise], axis=1)
    total = sum(float((c - c.mean()) @ (c - c.mean())) for c in x.T)
    r = decompose(_fs(x, tex, spd, frc), "original")
    assert r.balanced and (r.n_trials, r.n_textures, r.n_conditions, r.n_cells) == (n, 3, 4, 12)
    assert r.texture == pytest.approx(float(col_t @ col_t) / total, rel=1e-6)
    assert r.condition == pytest.approx(float(col_c @ col_c) / total, rel=1e-6)
    assert r.interaction == pytest.approx(float(col_i @ col_i) / total, rel=1e-6)
    assert r.residual == pytest.approx(float(noise @ noise) / total, rel=1e-6)
    assert r.texture + r.condition + r.interaction + r.residual == pytest.approx(1.0)


def test_features_that_only_carry_the_condition():
    from rigctl.analysis.variance import decompose

    tex, spd, frc = _design()
    x = np.stack([spd, frc], axis=1)
    r = decompose(_fs(x, tex, spd, frc), "original")
    assert r.condition == pytest.approx(1.0) and abs(r.texture) < 1e-9 and abs(r.residual) < 1e-9


def test_unbalanced_designs_say_so_and_bad_input_is_named():
    from rigctl.analysis.variance import decompose, format_variance

    tex, spd, frc = _design()
    x = np.random.default_rng(2).standard_normal((tex.size - 1, 3))
    r = decompose(_fs(x, tex[1:], spd[1:], frc[1:]), "original")
    assert not r.balanced
    assert "unbalanced" in format_variance([r])
    with pytest.raises(KeyError, match="speed_scaled"):
        decompose(_fs(x, tex[1:], spd[1:], frc[1:]), "speed_scaled")
    with pytest.raises(ValueError, match="do not vary"):
        decompose(_fs(np.ones((tex.size, 2)), tex, spd, frc), "original")


def _results(values: dict) -> TaskResults:
    """TaskResults whose every repetition gives ``values[task][variant]`` % at every PC count."""
    from rigctl.analysis.tasks import Curve, TaskResults

    res = TaskResults()
    for task, by_v in values.items():
        for v, pct in by_v.items():
            res.add(Curve(task=task, variant=v, acc=np.full((3, 5), pct / 100), n_tested=10, classes=["A"],
                          confusion=np.zeros((1, 1), int), confusion_pcs=5))
    return res


def test_the_papers_ordering_is_checked_pair_by_pair():
    from rigctl.analysis import report

    # untrained force, paper: Original 57.4, Speed Scaled 64.2, Force Scaled 89.4, Speed and Force Scaled 88.7
    good = {"original": 50.0, "speed_scaled": 60.0, "force_scaled": 80.0, "speed_force_scaled": 70.0}
    bad = dict(good, speed_scaled=45.0)  # Speed Scaled below Original: the row issue 13 measured
    for values, holds in ((good, True), (bad, False)):
        res = _results({"untrained_force": values})
        pairs = report.paper_ordering(res, 5)["untrained_force"]
        # FS vs SFS differ by 0.65 points in the paper: no ordering asked for; the other five pairs are checked
        assert {(p.first, p.second) for p in pairs} == {
            ("original", "speed_scaled"), ("original", "force_scaled"), ("original", "speed_force_scaled"),
            ("speed_scaled", "force_scaled"), ("speed_scaled", "speed_force_scaled")}
        assert all(p.holds for p in pairs) is holds
        text = report.format_ordering(res, 5)
        if holds:
            assert text.startswith("paper's ordering, Untrained Force") and text.endswith(": holds (5 pairs)")
        else:
            assert "NOT held: 1 of 5 pairs reversed: Speed Scaled > Original (paper +6.8, here -5.0)" in text
        assert report.to_dict(res, 5)["ordering"]["untrained_force"]["holds"] is holds


def test_ties_and_identical_variants_are_not_reversals():
    """Force Scaled with every coefficient C = 1 is Original (the same curves): named identical, not 'reversed';
    two variants at the same mean are tied; the rest of the row is still checked."""
    from rigctl.analysis import report

    values = {"original": 100.0, "speed_scaled": 100.0, "force_scaled": 100.0, "speed_force_scaled": 100.0}
    res = _results({"textures": values})
    text = report.format_ordering(res, 5)
    assert "NOT held" not in text and "reversed" not in text
    assert "Original and Force Scaled identical" in text
    assert report.to_dict(res, 5)["ordering"]["textures"]["holds"] is True
    res = _results({"untrained_force": {"original": 50.0, "speed_scaled": 45.0, "force_scaled": 50.0}})
    res.curves["untrained_force"]["force_scaled"].acc[0, 0] += 0.01  # equal means at 5 PCs, curves not identical
    text = report.format_ordering(res, 5)
    assert "NOT held: 1 of 2 pairs reversed: Speed Scaled > Original" in text
    assert "Original and Force Scaled tied" in text and "identical" not in text


def test_confusion_labels_are_whole(tmp_path):
    """Labels longer than six characters ('Bumps_fine', 'Bumps_coarse', ...) are drawn whole."""
    import matplotlib

    from rigctl.analysis import report
    from rigctl.analysis.tasks import Curve, TaskResults

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["Bumps_fine", "Bumps_coarse", "Bumps_mixed", "Denim"]
    res = TaskResults()
    res.add(Curve(task="textures", variant="original", acc=np.full((2, 3), 0.5), n_tested=8, classes=labels,
                  confusion=np.eye(4, dtype=int), confusion_pcs=3))
    shown = []
    real_savefig = plt.Figure.savefig

    def capture(fig, *a, **kw):
        shown.extend(t.get_text() for ax in fig.axes for t in ax.get_xticklabels() + ax.get_yticklabels())
        return real_savefig(fig, *a, **kw)

    plt.Figure.savefig = capture
    try:
        report.plot_confusions(res, tmp_path / "c.png", "textures")
    finally:
        plt.Figure.savefig = real_savefig
    assert sorted(set(shown)) == sorted(labels) and (tmp_path / "c.png").stat().st_size > 0


def test_analyze_prints_the_variance_and_the_ordering(tmp_path, write_schema1):
    from rigctl.analysis.synthetic import synthetic_features
    from rigctl.analysis.variance import decompose

    fs = synthetic_features(4, n_textures=4, n_channels=4, noise=0.8, seed=3)
    path = write_schema1(fs, tmp_path / "enc.h5", 2)
    r = CliRunner().invoke(main, ["analyze", str(path), "--task", "variance", "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)["variance"]
    assert [row["variant"] for row in rows] == ["original", "speed_scaled", "force_scaled", "speed_force_scaled"]
    for row in rows:
        assert sum(row[k] for k in ("texture", "condition", "interaction", "residual")) == pytest.approx(1.0)
        assert row["texture"] == pytest.approx(decompose(fs, row["variant"]).texture, rel=1e-4)
    r = CliRunner().invoke(main, ["analyze", str(path), "--task", "textures", "--variance", "--repeats", "2",
                                  "--pcs", "4", "--no-progress"])
    assert r.exit_code == 0, r.output
    assert r.stdout.startswith("Feature variance (% of the total sum of squares;")
    assert "paper's ordering, Individual Textures (Fig. 3A): " in r.stdout


def test_prediction_collapse_names_the_class_the_predictions_pile_on():
    """An extrapolation row whose classifier puts most test trials on one texture (what the simulated rig's
    unscaled variants do at untrained speeds, issue 13) is named with that texture and its share; an even spread
    reads as the even share, and rows the paper trains on are not reported."""
    from rigctl.analysis import report
    from rigctl.analysis.tasks import Curve, TaskResults

    classes = ["A", "B", "C", "D"]
    piled = np.array([[5, 0, 0, 0], [4, 1, 0, 0], [3, 0, 2, 0], [5, 0, 0, 0]])  # truth rows, predicted columns
    even = np.diag([5, 5, 5, 5])
    res = TaskResults()
    for task, v, cm in (("untrained_speed", "original", piled), ("untrained_speed", "force_scaled", even),
                        ("textures", "original", piled)):
        res.add(Curve(task=task, variant=v, acc=np.full((2, 3), 0.5), n_tested=20, classes=classes,
                      confusion=cm, confusion_pcs=3))
    got = report.prediction_collapse(res)
    assert set(got) == {"untrained_speed"}
    c = got["untrained_speed"]["original"]
    assert (c.top_class, c.top_share, c.even_share) == ("A", 17 / 20, 0.25) and c.ratio == pytest.approx(3.4)
    assert got["untrained_speed"]["force_scaled"].top_share == pytest.approx(0.25)
    text = report.format_collapse(res)
    assert text == ("most-predicted class, Untrained Speed (Fig. 3E) (even: 25 %): Original 85 % (A); "
                    "Force Scaled 25 % (A)")
    assert report.to_dict(res, 3)["collapse"]["untrained_speed"]["original"]["top_class"] == "A"


def test_a_small_table_says_what_it_cannot_show():
    """Issue 79 item 7: the paper guide's first-try size (2 trials per condition, 2 repetitions) printed 'NOT held'
    four times without saying why; a table far below the paper's size now says so first, and one at its size not."""
    from rigctl.analysis import report

    values = {"original": 50.0, "speed_scaled": 45.0, "force_scaled": 80.0, "speed_force_scaled": 70.0}
    res = _results({"untrained_force": values})
    res.counts.update(cv={"per_texture": 6, "repeats": 2}, extrapolation={"train_per_cell": 1, "repeats": 2})
    lines = report.format_ordering(res, 5).splitlines()
    assert lines[0].startswith("size: 6 trials per texture") and "(paper: 500)" in lines[0]
    assert "not expected to reproduce" in lines[0] and "NOT held" in lines[1]
    res.counts.update(cv={"per_texture": 500, "repeats": 20}, extrapolation={"train_per_cell": 75, "repeats": 20})
    assert report.size_note(res) is None
    assert report.format_ordering(res, 5).startswith("paper's ordering")
