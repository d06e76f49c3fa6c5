"""scikit-learn conventions: the classifier passes scikit-learn's estimator checks; the encoding steps clone and pass
the checks that apply to transformers of raw trials; the raw-trials-to-label pipeline round-trips through a model
file (`rigctl analyze --save-model`) that alone classifies new trials in the GUI's real-time view; the force leak is
reported (coefficients fitted on all trials vs per fold)."""

from __future__ import annotations

import json
import os
import zipfile
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.storage.model_file import ModelFileError, load_model, save_model

# scikit-learn, and the rigctl modules built on it, are imported by the tests, not at the module's top: every
# pytest-xdist worker collects every module, and ~2 CPU-s of scikit-learn + scipy.stats + pandas is then paid only by
# the workers that run these tests (so the parametrizations below name their cases instead of holding the objects)

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # the real-time view, in a real Qt window offscreen

PROTOCOL = """
name = "model"
textures = ["A", "L"]
speeds_mm_s = [80]
forces_g = [250, 500]
trials_per_condition = 4
duration_s = 0.3
"""


def test_texture_classifier_passes_the_estimator_checks():
    """Every check of scikit-learn's list for a classifier (``check_estimator``'s, as ``parametrize_with_checks``
    gives them: the legacy ones too), each run whatever the others did; the failures are named together."""
    from sklearn.utils.estimator_checks import check_estimator

    from rigctl.analysis.classify import TextureClassifier

    results = check_estimator(TextureClassifier(), on_skip=None, on_fail=None)
    failed = [f"{r['check_name']}: {type(r['exception']).__name__}: {r['exception']}"
              for r in results if r["status"] not in ("passed", "skipped")]
    assert not failed, "\n".join(failed)
    assert sum(r["status"] == "passed" for r in results) > len(results) // 2, results


#: scikit-learn's checks that take no data (names in sklearn.utils.estimator_checks). Every other check feeds 2-D
#: numeric arrays, which these steps refuse by design (their input is a list of raw trials, ragged: trials of different
#: lengths), so they are not run; the behaviour they check (fit/transform, clone, refitting) is checked on trials below.
DATA_FREE_CHECKS = ["check_estimator_cloneable", "check_estimator_repr", "check_no_attributes_set_in_init",
                    "check_get_params_invariance", "check_set_params", "check_parameters_default_constructible",
                    "check_do_not_raise_errors_in_init_or_set_params"]
#: the encoding steps (rigctl.encoding.estimators) as (class name, constructor arguments)
STEPS = [("TaxelNormaliser", (), {}), ("ForceScaler", (), {"label_free": True}), ("SpikeEncoder", ({"k_sa": 90.0},), {}),
         ("FeatureExtractor", ("original",), {})]


@pytest.mark.parametrize("check", DATA_FREE_CHECKS)
@pytest.mark.parametrize("step", STEPS, ids=lambda s: s[0])
def test_encoding_steps_pass_the_checks_that_apply(step, check):
    from sklearn.utils import estimator_checks

    from rigctl.encoding import estimators

    name, args, kwargs = step
    getattr(estimator_checks, check)(name, getattr(estimators, name)(*args, **kwargs))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.simulation.dataset import generate_dataset

    path = tmp_path_factory.mktemp("model") / "s.h5"
    generate_dataset(parse_protocol(PROTOCOL), path, workers=0, seed=2)
    return path


def test_pipeline_clones_fits_refits_and_round_trips(session, tmp_path):
    from sklearn.base import clone

    from rigctl.analysis.model import texture_pipeline, trials_of_session

    trials, texture = trials_of_session(session)
    pipe = texture_pipeline("speed_force_scaled", 3)
    assert [n for n, _ in pipe.steps] == ["normalise", "force", "encode", "features", "classify"]
    fitted = clone(pipe).fit(trials, texture)
    assert fitted[-1].n_pcs_ == 3 and list(fitted.classes_) == ["A", "L"]
    twin = clone(pipe)  # unfitted, same parameters
    assert twin.get_params(deep=True).keys() == pipe.get_params(deep=True).keys() and not hasattr(twin[-1], "lda_")
    assert (fitted.predict(trials) == texture).mean() > 0.8
    # the force step is fit(X, y): condition labels from the trials, textures from y
    force = fitted.named_steps["force"]
    assert {tuple(k[1:]) for k in force.keys_} == {(80.0, 250.0), (80.0, 500.0)} and force.textures_ == ["A", "L"]
    # saved and loaded: the same predictions, versions recorded
    path = save_model(fitted, tmp_path / "m.skops", info={"variant": "speed_force_scaled"})
    back = load_model(path)
    np.testing.assert_array_equal(back.predict(trials), fitted.predict(trials))
    # a file made with another scikit-learn is refused with a clear error (and loads when asked to)
    old = tmp_path / "old.skops"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(old, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "rigctl_model.json":
                meta = json.loads(data)
                meta["versions"]["scikit-learn"] = "0.24.2"
                data = json.dumps(meta).encode()
            dst.writestr(item, data)
    with pytest.raises(ModelFileError, match=r"made with scikit-learn 0.24.2 \(running"):
        load_model(old)
    assert load_model(old, check_versions=False)[-1].n_pcs_ == 3
    # a file holding a type outside rigctl / scikit-learn / numpy / scipy is refused by name
    odd = save_model({"where": __import__("fractions").Fraction(1, 3)}, tmp_path / "odd.skops")
    with pytest.raises(ModelFileError, match="fractions.Fraction"):
        load_model(odd)


def test_saved_model_alone_classifies_new_trials_in_the_realtime_view(session, tmp_path, qapp):
    """`rigctl analyze --save-model` writes the pipeline; the real-time view loads only that file and classifies
    finished trials (the trials' textures are not given to the model); --force-leak reports both fits."""
    from rigctl.cli import main
    from rigctl.storage.session import open_session
    from rigctl_gui.classify_view import ClassifyView
    from rigctl_gui.events import wait_for

    model = tmp_path / "m.skops"
    r = CliRunner().invoke(main, ["analyze", str(session), "--encode", "--task", "textures", "--repeats", "1",
                                  "--pcs", "1-3", "--per-texture", "4", "--json", "--no-progress",
                                  "--save-model", str(model), "--model-pcs", "3",
                                  "--force-leak", "speed_force_scaled"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    leak = out["force_leak"]
    assert leak["variant"] == "speed_force_scaled" and leak["folds"] == 4
    assert 0 <= leak["per_fold"] <= 1 and leak["leak"] == pytest.approx(leak["fitted_on_all"] - leak["per_fold"])
    view = ClassifyView(SimpleNamespace())
    view.load_model(str(model))  # in a worker thread; the view's refresh (the window's clock) puts it in use

    def loaded():
        view.refresh()
        return view.model is not None

    assert wait_for(qapp, loaded, 60), view.model_label.text()
    assert "speed_scaled" in view.model_label.text()
    with open_session(session) as s:
        records = [(s.plan[i], s.trial(i)) for i in range(0, 16, 2)]
    for row, data in records:
        view.on_trial(SimpleNamespace(trial_id=int(row["trial_id"]), texture=str(row["texture"]),
                                      speed_mm_s=float(row["speed_mm_s"]), force_g=float(row["force_g"])), data)

    def step():
        view.refresh()
        return len(view.results) == len(records)

    assert wait_for(qapp, step, 60), view.model_label.text()
    assert sum(t == p for _, t, p in view.results) >= 6
    assert [tid for tid, _, _ in view.results] == list(range(0, 16, 2))


def test_force_leak_report_is_the_operator_layers_face_of_force_leak(session):
    """``rigctl analyze --force-leak`` goes through rigctl.operations.force_leak_report (the CLI holds no analysis
    logic): on a session file it is force_leak on the session's raw trials; a variant without a force step is a
    ValueError naming it."""
    from rigctl.analysis.model import force_leak, trials_of_session
    from rigctl.operations import force_leak_report

    with pytest.raises(ValueError, match="original"):
        force_leak_report(session, "original", n_pcs=2, repeats=1)
    trials, texture = trials_of_session(session)
    direct = force_leak(trials, texture, variant="speed_force_scaled", n_pcs=2, repeats=1, seed=3)
    assert force_leak_report(session, "speed_force_scaled", n_pcs=2, repeats=1, seed=3) == direct
