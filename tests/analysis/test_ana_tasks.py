"""Task splits follow the Methods' counts; tasks find the planted answer on synthetic features."""

import numpy as np
import pytest

from rigctl.analysis.data import FeatureSet, remove_baseline
from rigctl.analysis.synthetic import synthetic_features


def _paper_layout(per_cell=100):
    """The paper's 16 textures x 5 speeds x 3 forces x 100 trials, with 2 dummy feature columns."""
    tex, spd, frc = np.meshgrid(np.array(list("ABCDEFGHIJKLMNOP")), [40.0, 60, 80, 100, 120], [250.0, 500, 1000],
                                indexing="ij")
    rep = lambda a: np.repeat(a.ravel(), per_cell)  # noqa: E731
    n = tex.size * per_cell
    return FeatureSet({"original": np.zeros((n, 2), np.float32)}, rep(tex), rep(spd), rep(frc))


def test_cv_split_matches_methods_counts():
    from rigctl.analysis.tasks import cv_split

    fs = _paper_layout()
    assert fs.n_trials == 24_000
    idx, folds = cv_split(fs.texture, 500, 4, seed=1, repeat=0)
    assert len(idx) == 8000 and len(np.unique(idx)) == 8000
    _, per_tex = np.unique(fs.texture[idx], return_counts=True)
    assert set(per_tex) == {500}
    assert len(folds) == 4
    tested = np.concatenate([te for _, te in folds])
    assert sorted(tested) == list(range(8000))  # every drawn trial tested exactly once
    for tr, te in folds:
        assert (len(tr), len(te)) == (6000, 2000)
        assert set(np.unique(fs.texture[idx[te]], return_counts=True)[1]) == {125}
    idx2, _ = cv_split(fs.texture, 500, 4, seed=1, repeat=1)
    assert not np.array_equal(np.sort(idx), np.sort(idx2))  # a new draw per repetition


def test_extrapolation_split_matches_methods_counts():
    from rigctl.analysis.tasks import extrapolation_split

    fs = _paper_layout()
    tr, te, cell = extrapolation_split(fs, seed=0, repeat=0)
    assert len(tr) == 7200  # 16 x 75 x 6
    assert not set(tr) & set(te)
    assert set(fs.speed_mm_s[tr]) == {40, 60, 80} and set(fs.force_g[tr]) == {250, 500}
    counts = {c: int((cell == c).sum()) for c in np.unique(cell)}
    # 16 textures x 25 trials x [2 3 4 6] speed-force combinations (Fig. 3C-F)
    assert counts == {"untrained_speed_force": 800, "untrained_force": 1200, "untrained_speed": 1600,
                      "trained": 2400}
    m = cell == "untrained_speed_force"
    assert set(fs.speed_mm_s[te[m]]) == {100, 120} and set(fs.force_g[te[m]]) == {1000}
    m = cell == "untrained_force"
    assert set(fs.speed_mm_s[te[m]]) == {40, 60, 80} and set(fs.force_g[te[m]]) == {1000}
    m = cell == "untrained_speed"
    assert set(fs.speed_mm_s[te[m]]) == {100, 120} and set(fs.force_g[te[m]]) == {250, 500}


@pytest.fixture(scope="module")
def small():
    return synthetic_features(6, n_textures=8, n_channels=6, noise=0.8, seed=2)


def test_planted_speed_confound_loses_on_untrained_speed(small):
    from rigctl.analysis.tasks import run_extrapolation

    with pytest.warns(UserWarning, match="extrapolation"):
        res = run_extrapolation(small, n_pcs=15, repeats=3, seed=0)
    assert set(res.curves) == {"untrained_speed_force", "untrained_force", "untrained_speed", "trained"}
    us = res.curves["untrained_speed"]
    assert us["speed_scaled"].at(15)[0] > us["original"].at(15)[0] + 0.3
    assert us["speed_force_scaled"].at(15)[0] > us["force_scaled"].at(15)[0] + 0.3
    c = res.counts["extrapolation"]
    # 6 trials per cell: 4-5 train + 1-2 test, the counts stated
    assert c["train_per_cell"] + c["test_per_trained_cell"] <= 6
    assert c["tested_per_repeat"]["untrained_speed"] == 8 * 4 * c["test_per_untrained_cell"]
    comp = {x.variant: x for x in res.comparisons("untrained_speed", 15)}
    assert comp["speed_scaled"].stars_d == "**"


def test_cv_tasks_scale_down_and_shapes(small):
    from rigctl.analysis.tasks import run_cv

    # every texture as short as the others (the session is small): the advice is --per-texture, not to drop one
    with pytest.warns(UserWarning, match=r"fewer than 500 trials for A \(90\), B \(90\).*\(\+2 more\); drawing 90 "
                      r"per texture.*the session holds 90 trials for most textures: set --per-texture 90") as got:
        res = run_cv(small, ("textures", "groups"), n_pcs=12, repeats=2, per_texture=500)
    assert not any("--textures" in str(w.message) for w in got)
    # one texture short of the others (issue 77 item 7): every trial is used, each texture weighted equally, said
    # with the numbers; the smallest count drawn from every texture (the former rule) would have used 320 of 670
    keep = np.flatnonzero((small.texture != "A") | (np.cumsum(small.texture == "A") <= 40))
    with pytest.warns(UserWarning, match=r"the textures hold 40-90 trials \(fewest: A \(40\)\); using every trial up "
                      r"to --per-texture 90 \(670 of 670 trials per repetition, 40-90 per texture\), each texture "
                      r"weighted equally.*balanced accuracy.*would use 320; .*leave it out with --textures"):
        short = run_cv(small.subset(keep), ("textures", "groups"), n_pcs=6, repeats=2, per_texture=90)
    cv = short.counts["cv"]
    assert cv["weighting"] == "balanced" and cv["trials_per_repeat"] == 670 and cv["drawn_per_texture"]["A"] == 40
    c = short.curves["textures"]["speed_force_scaled"]
    assert c.n_tested == 670 and c.confusion.sum() == 2 * 670  # every trial tested once a repetition
    recall = np.diag(c.confusion) / c.confusion.sum(axis=1)  # the accuracy is the mean of the textures' accuracies
    assert c.acc[:, -1].mean() == pytest.approx(recall.mean(), abs=1e-12)
    assert np.trace(c.confusion) / c.confusion.sum() != pytest.approx(recall.mean(), abs=1e-6)  # not the pooled one
    assert res.counts["cv"]["per_texture"] == 90
    for task, n_cls in (("textures", 8), ("groups", 3)):  # A smooth, B-F circular, G-H rectangular
        c = res.curves[task]["speed_force_scaled"]
        assert c.acc.shape == (2, 12) and c.n_tested == 720
        assert c.confusion.shape == (n_cls, n_cls) and c.confusion.sum() == 2 * 720
        assert np.trace(c.confusion) / c.confusion.sum() == pytest.approx(c.acc[:, -1].mean())
    t = res.curves["textures"]
    assert t["speed_force_scaled"].at(12)[0] > t["original"].at(12)[0]


def test_realtime_profiles_and_calibration():
    from rigctl.analysis.tasks import run_realtime

    base = synthetic_features(8, n_textures=5, n_channels=4, speeds=(40.0, 80.0, 120.0), forces=(500.0,), seed=4,
                              noise=0.6)
    names = {40.0: "slow", 80.0: "medium", 120.0: "fast"}
    fs = base.subset(np.arange(base.n_trials))
    fs.profile = np.array([names[s] for s in fs.speed_mm_s])
    fs.features = {"realtime_" + k: fs.features[k] for k in ("original", "speed_scaled")}
    other = fs.subset(np.arange(fs.n_trials))
    other.features = {k: v + 2.0 for k, v in fs.features.items()}  # session-to-session offset
    events = []
    res = run_realtime(fs, new_session=other, n_pcs=10, repeats=2, seed=1, progress=events.append)
    assert set(res.curves) == {"rt_offline", "rt_trained", "rt_untrained", "rt_new_session"}
    # progress events: one per repetition and variant
    assert [(e.stage, e.done, e.total) for e in events] == [("realtime", k, 4) for k in range(5)]
    un = res.curves["rt_untrained"]
    assert un["realtime_speed_scaled"].at(10)[0] > un["realtime_original"].at(10)[0] + 0.2
    assert res.curves["rt_untrained"]["realtime_original"].n_tested == 5 * 8  # all fast trials
    assert res.curves["rt_trained"]["realtime_original"].n_tested == 5 * 16 - 5 * 12  # the 25 % held out
    # calibration removes the offset: the new session classifies like the offline data
    assert res.curves["rt_new_session"]["realtime_speed_scaled"].at(10)[0] > 0.8
    with pytest.raises(ValueError, match="profile"):
        run_realtime(base, n_pcs=5, repeats=1)


def test_remove_baseline_keeps_padding_and_modulation():
    rng = np.random.default_rng(0)
    mod = rng.standard_normal((3, 2, 5)).astype(np.float32)
    x = mod + np.array([10.0, -3.0], np.float32)[None, :, None]
    x[:, :, 4] = 0  # padded window
    out = remove_baseline(x.reshape(3, -1), 2).reshape(3, 2, 5)
    np.testing.assert_allclose(out[:, :, :4].mean(axis=2), 0, atol=1e-5)
    np.testing.assert_array_equal(out[:, :, 4], 0)
    np.testing.assert_allclose(out[:, :, :4], mod[:, :, :4] - mod[:, :, :4].mean(axis=2, keepdims=True), atol=1e-5)
    with pytest.raises(ValueError):
        remove_baseline(x.reshape(3, -1), 3)


def test_the_repetitions_count_on_label_codes_what_they_count_on_the_labels(small):
    """The CV repetition on integer label codes (what run_cv passes it since they sort as the labels do) predicts and
    counts exactly as on the texture / group names: the same correct counts per PC and the same confusion matrices,
    in the classes' order (codes by first appearance would reorder the classes and break the ties otherwise)."""
    from rigctl.analysis.tasks import _cv_repeat, _label_codes

    names = np.array(["zeta", "alpha", "mu", "beta"])
    classes = ["mu", "zeta", "alpha", "beta", "omega"]  # not sorted; one class no trial has
    codes, class_codes = _label_codes(names, classes)
    assert list(np.argsort(codes, kind="stable")) == list(np.argsort(names, kind="stable"))
    assert list(codes[[1, 0]]) == list(class_codes[[2, 1]])  # alpha, zeta
    tex_classes = list(np.unique(small.texture))[::-1]
    common = {"features": {"original": small.features["original"]}, "n_draw": 20, "k": 4, "n_pcs": 10, "seed": 3,
              "confusion_pcs": 10}
    by_name = _cv_repeat(1, texture=small.texture, labels={"textures": small.texture},
                         classes={"textures": tex_classes}, **common)
    tex_codes, tex_class_codes = _label_codes(small.texture, tex_classes)
    by_code = _cv_repeat(1, texture=tex_codes, labels={"textures": tex_codes}, classes={"textures": tex_class_codes},
                         **common)
    assert by_name.keys() == by_code.keys()
    for key, (correct, confusion) in by_name.items():
        np.testing.assert_array_equal(np.array(correct), np.array(by_code[key][0]))
        np.testing.assert_array_equal(confusion, by_code[key][1])
        assert confusion.sum() == 20 * len(tex_classes) * 1  # every drawn trial tested once


def test_weighted_priors_give_each_texture_an_equal_share():
    """The unequal draw's LDA priors (issue 77 item 7): trials weighted by the inverse of their texture's count give
    every texture an equal prior, and a group the share of its textures."""
    from rigctl.analysis.tasks import _weighted_priors, cv_draw_counts

    drawn = cv_draw_counts([40, 90, 700], 500)
    assert drawn.tolist() == [40, 90, 500]
    texture = np.repeat(np.array(["A", "B", "C"]), drawn)
    w = (drawn.sum() / (3 * drawn))[np.searchsorted(["A", "B", "C"], texture)]
    assert _weighted_priors(texture, w) == pytest.approx([1 / 3] * 3)
    group = np.where(texture == "C", "coarse", "fine")
    assert _weighted_priors(group, w) == pytest.approx([1 / 3, 2 / 3])  # coarse (C), fine (A, B)


def test_one_trial_per_cell_gets_a_speed_extrapolation_by_held_out_cells():
    """Issue 77 item 7: a design of one trial per speed-force cell got no speed extrapolation (a cell of one trial
    cannot be split into train and test). Whole trained cells are now held out: per repetition and texture, a quarter
    of the trained cells (3 of 12) test and the others train; a held-out cell's trial is never trained on, the warning
    and the counts say which split was used. A texture with one trained cell is still refused in one line."""
    from rigctl.analysis.report import format_counts
    from rigctl.analysis.tasks import _cells, extrapolation_split, run_extrapolation

    fs = synthetic_features(1, n_textures=4, n_channels=4, speeds=(20.0, 40.0, 60.0, 80.0, 100.0),
                            forces=(100.0, 200.0, 300.0, 400.0), seed=4, noise=0.6)
    assert fs.n_trials == 80
    with pytest.warns(UserWarning, match=r"speed_extrapolation: a trained cell holds 1 trial\(s\).*whole cells held "
                      r"out instead: each repetition tests 3 of each texture's 12 trained cells"):
        res = run_extrapolation(fs, train_speeds=(20, 40, 60), train_forces=None, prefix="speed_", n_pcs=6,
                                repeats=2)
    counts = res.counts["speed_extrapolation"]
    assert counts["split"] == "held-out cells" and counts["held_out_cells_per_texture"] == 3
    assert counts["tested_per_repeat"] == {"speed_untrained_speed": 32, "speed_trained": 12}
    assert any("split held-out cells" in line for line in format_counts(res.counts))  # on the terminal
    assert set(res.curves) == {"speed_untrained_speed", "speed_trained"}
    spd, frc = _cells(fs)
    key = np.char.add(np.char.add(fs.texture.astype(str), spd.astype(str)), frc.astype(str))
    for repeat in range(3):
        train, test, cat = extrapolation_split(fs, train_speeds=(20, 40, 60), train_forces=None, repeat=repeat)
        held = test[cat == "trained"]
        assert len(train) == 36 and len(held) == 12 and not set(key[held]) & set(key[train])
        assert all((fs.texture[held] == t).sum() == 3 for t in np.unique(fs.texture))
    with pytest.raises(ValueError, match="has one trained cell: cannot split into train and test, by trials or by "
                       "whole cells"):  # one trained speed and force: one trained cell a texture
        run_extrapolation(fs, train_speeds=(20,), train_forces=(100,), n_pcs=4, repeats=1)
