"""The analyses as the operator layer runs them (rigctl.operations.run_analyses), the one path of `rigctl analyze`
and the GUI's analysis tab: a plan's tasks and parameter objects reach the analyses, keyword overrides equal the
objects, groups are skipped (with the reason) only where the plan allows it, and the GUI's skip policy keeps going
where the CLI's raise policy stops."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rigctl.analysis.params import CVParams, ExtrapolationParams, Repetitions
from rigctl.analysis.synthetic import synthetic_features
from rigctl.operations import AnalysisPlan, BaselineError, run_analyses


@pytest.fixture(scope="module")
def fs():
    return synthetic_features(6, n_textures=8, n_channels=6, noise=0.8, seed=2)


def test_parameter_objects_and_keywords_run_the_same_analysis(fs):
    from rigctl.analysis import tasks

    by_kw = tasks.run_cv(fs, ("textures",), n_pcs=5, repeats=2, per_texture=20, seed=3, variants=["original"])
    by_obj = tasks.run_cv(fs, ("textures",), CVParams(per_texture=20),
                          reps=Repetitions(n_pcs=5, repeats=2, seed=3, variants=["original"]))
    a, b = by_kw.curves["textures"]["original"], by_obj.curves["textures"]["original"]
    assert np.array_equal(a.acc, b.acc) and a.acc.shape == (2, 5)
    with pytest.raises(TypeError, match="n_pc"):
        tasks.run_cv(fs, ("textures",), n_pc=5)  # a misspelt keyword is refused, as Python refuses one


def test_a_plan_runs_its_tasks_with_its_parameters(fs):
    from rigctl.analysis import tasks

    plan = AnalysisPlan.for_task("all", reps=Repetitions(n_pcs=4, repeats=2, seed=1, variants=["original"]),
                                 cv=CVParams(per_texture=20))
    res = run_analyses(fs, plan)
    assert {"textures", "groups"} <= set(res.curves) and any("untrained" in t for t in res.curves)
    assert res.counts["cv"]["per_texture"] == 20 and res.counts["cv"]["repeats"] == 2
    assert res.curves["textures"]["original"].acc.shape == (2, 4)
    # the same analysis called directly gives the same numbers: the plan adds nothing of its own
    direct = tasks.run_cv(fs, ("textures", "groups"), CVParams(per_texture=20), reps=plan.reps)
    assert np.array_equal(direct.curves["textures"]["original"].acc, res.curves["textures"]["original"].acc)


def test_groups_of_a_set_without_groups_skipped_or_refused(fs):
    # labels of a lab's own set (not A-P: those would bring the paper's groups), no groups given
    no_groups = dataclasses.replace(fs, texture=np.char.add("lab", fs.texture.astype(str)), group=None, textures=None)
    assert no_groups.group is None and not no_groups.textures.groups
    reps = Repetitions(n_pcs=3, repeats=1, variants=["original"])
    res = run_analyses(no_groups, AnalysisPlan(("textures", "groups"), groups_optional=True, reps=reps,
                                               cv=CVParams(per_texture=20)))
    assert "groups" not in res.curves and any("groups task skipped" in w for w in res.warnings)
    with pytest.raises(ValueError):
        run_analyses(no_groups, AnalysisPlan(("groups",), groups_optional=False, reps=reps))


def test_skip_policy_keeps_what_the_data_supports(fs):
    """Extrapolation trained on a speed the data lacks: the CLI's plan stops with the error, the GUI's plan keeps
    the other tasks and says why it skipped it."""
    reps = Repetitions(n_pcs=3, repeats=1, variants=["original"])
    bad = ExtrapolationParams(train_speeds=(999.0,))
    with pytest.raises((ValueError, KeyError)):
        run_analyses(fs, AnalysisPlan(("textures", "extrapolation"), reps=reps, extrapolation=bad,
                                      cv=CVParams(per_texture=20)))
    res = run_analyses(fs, AnalysisPlan(("textures", "extrapolation"), reps=reps, extrapolation=bad,
                                        cv=CVParams(per_texture=20), on_error="skip"))
    assert "textures" in res.curves and any(w.startswith("extrapolation skipped:") for w in res.warnings)


def test_baseline_both_prefixes_the_baseline_removed_tasks(fs):
    reps = Repetitions(n_pcs=3, repeats=1, variants=["original"])
    res = run_analyses(fs, AnalysisPlan(("textures",), reps=reps, cv=CVParams(per_texture=20), baseline="both"))
    assert {"textures", "baseline_removed:textures"} <= set(res.curves)
    with pytest.raises(BaselineError):
        run_analyses(fs, AnalysisPlan(("textures",), reps=reps, baseline="remove", channels=7))


def test_unknown_tasks_and_policies_are_refused():
    with pytest.raises(ValueError, match="unknown analysis"):
        AnalysisPlan(("textures", "speed"))
    with pytest.raises(ValueError):
        AnalysisPlan.for_task("variance")
    with pytest.raises(ValueError):
        AnalysisPlan(on_error="ignore")
