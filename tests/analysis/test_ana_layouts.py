"""Analyses follow the file: the sensor layout sets the spike-train count (9- and 16-channel sensors), the texture
set gives the groups (a set without groups is refused by the groups task, even when its labels look like the paper's
A-P) and the texture codes (the set's order, not the trials' order)."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.analysis.data import FeatureSet, GroupsError, load_features, remove_baseline
from rigctl.analysis.synthetic import synthetic_features
from rigctl.cli import main
from rigctl.core import PAPER_SENSOR, PAPER_TEXTURES, SensorLayout, TextureSet
from rigctl.storage.encoded import EncodedWriter, open_encoded


def write_encoded(path, fs: FeatureSet, layout: SensorLayout, textures: TextureSet):
    """An encoded file of ``fs`` written through the one writer (rigctl.storage.encoded)."""
    trials = {"trial_id": np.arange(fs.n_trials), "texture": fs.texture, "speed_mm_s": fs.speed_mm_s,
              "force_g": fs.force_g}
    with EncodedWriter(path, layout=layout, textures=textures, trials=trials) as w:
        for v, x in fs.features.items():
            w.write_features(v, 0, x)
        w.write_normalisation(np.zeros(layout.n_channels), np.full(layout.n_channels, layout.adc_max))
    return path


FINGER = SensorLayout.grid(3, 3, 1, sample_rate_hz=100.0, name="lab finger 3x3")  # 9 channels, 100 Hz
BOARD16 = SensorLayout.grid(4, 4, 1, name="4x4 board")  # 16 channels (FabricSlide-like)


@pytest.fixture(scope="module")
def finger_file(tmp_path_factory):
    fs = synthetic_features(4, n_textures=6, layout=FINGER, speeds=(40.0, 80.0, 120.0), forces=(250.0, 500.0),
                            noise=0.6, seed=3)
    # letters A-F, but this lab's own textures: a set WITHOUT groups (the paper's groups must not be applied)
    lab = TextureSet(list("ABCDEF"), name="lab letters")
    return write_encoded(tmp_path_factory.mktemp("finger") / "finger.encoded.h5", fs, FINGER, lab)


def test_nine_channel_file_carries_its_layout_through_the_analysis(finger_file):
    from rigctl.analysis.tasks import run_cv

    fs = load_features(finger_file)
    assert fs.layout.n_channels == 9 and fs.layout.sample_rate_hz == 100.0
    assert fs.n_spike_trains("original") == 18  # 9 taxels x SA/RA, not the paper's 36
    assert fs.features["original"].shape[1] == 18 * 60 and fs.features["speed_scaled"].shape[1] == 18 * 20
    with pytest.raises(ValueError, match="not a multiple of 36"):
        remove_baseline(fs.features["original"][:, :18 * 7], 36)  # the paper's count does not fit 7 windows of 18
    flat = fs.without_baseline()
    w = flat.features["speed_scaled"].reshape(fs.n_trials, 18, -1)
    assert np.allclose(w.mean(axis=2), 0, atol=1e-4)  # each spike train's level removed
    res = run_cv(fs, ("textures",), n_pcs=8, repeats=2, per_texture=20)
    assert res.curves["textures"]["original"].classes == list("ABCDEF")
    assert res.curves["textures"]["speed_scaled"].at(8)[0] > 0.5  # 6 classes: chance is 1/6


def test_groups_task_refuses_a_texture_set_without_groups(finger_file):
    from rigctl.analysis.tasks import run_cv

    fs = load_features(finger_file)
    assert fs.group is None and fs.textures.name == "lab letters"
    with pytest.raises(GroupsError, match="defines no texture groups"):
        run_cv(fs, ("textures", "groups"), n_pcs=4, repeats=1, per_texture=10)
    r = CliRunner().invoke(main, ["analyze", str(finger_file), "--task", "groups", "--repeats", "1", "--pcs", "4",
                                  "--no-progress"])
    assert r.exit_code != 0
    assert "defines no texture groups" in r.output and "Traceback" not in r.output
    assert "%" not in r.output  # no accuracy reported
    # --task all runs the textures task and says why groups was skipped
    r = CliRunner().invoke(main, ["analyze", str(finger_file), "--task", "all", "--repeats", "2", "--pcs", "4",
                                  "--json", "--no-progress", "--train-speeds", "40,80", "--train-forces", "250"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert "textures" in out["tasks"] and "groups" not in out["tasks"]
    assert any("defines no texture groups" in w for w in out["warnings"])


def test_groups_task_uses_the_files_own_groups(tmp_path):
    from rigctl.analysis.tasks import run_cv

    fs = synthetic_features(4, n_textures=6, layout=FINGER, speeds=(40.0, 80.0), forces=(500.0,), noise=0.6, seed=4)
    grouped = TextureSet.from_dict({"name": "lab grouped", "textures": list("ABCDEF"),
                                    "groups": {"soft": ["A", "C", "E"], "hard": ["B", "D", "F"]}})
    path = write_encoded(tmp_path / "g.encoded.h5", fs, FINGER, grouped)
    loaded = load_features(path)
    res = run_cv(loaded, ("groups",), n_pcs=4, repeats=1, per_texture=8)
    assert res.curves["groups"]["original"].classes == ["soft", "hard"]  # the file's groups, in the set's order
    assert set(loaded.group) == {"soft", "hard"}  # not the paper's smooth/circular/... for letters A-F


def test_sixteen_channel_speed_extrapolation_with_baseline_removed(tmp_path):
    from rigctl.analysis.tasks import run_extrapolation

    fs = synthetic_features(6, n_textures=4, layout=BOARD16, speeds=(10.0, 20.0, 50.0, 100.0, 150.0),
                            forces=(500.0,), distance_mm=500.0, noise=0.5, seed=6)
    fabrics = TextureSet(["Linen", "Denim", "Felt", "Silk"], name="fabrics")
    fs = FeatureSet(fs.features, np.array(["Linen", "Denim", "Felt", "Silk"])[
        np.searchsorted(np.array(list("ABCD")), fs.texture)], fs.speed_mm_s, fs.force_g, layout=BOARD16)
    path = write_encoded(tmp_path / "fabric.encoded.h5", fs, BOARD16, fabrics)
    with open_encoded(path) as ef:
        assert ef.layout.n_channels == 16
    r = CliRunner().invoke(main, ["analyze", str(path), "--task", "speed-extrapolation", "--train-speeds",
                                  "10,20,50", "--test-speeds", "100,150", "--baseline", "remove", "--repeats", "2",
                                  "--pcs", "5", "--json", "--no-progress", "--variants", "original,speed_scaled"])
    assert r.exit_code == 0, r.output
    tasks = json.loads(r.stdout)["tasks"]
    assert set(tasks) == {"baseline_removed:speed_untrained_speed", "baseline_removed:speed_trained"}
    cur = tasks["baseline_removed:speed_untrained_speed"]["variants"]["original"]
    assert cur["n_tested"] == 4 * 2 * 2  # 4 fabrics x 2 untrained speeds x 2 test trials per cell (6 per cell: 4 + 2)
    # confusion rows follow the texture set's order (stable codes), not alphabetical order
    loaded = load_features(path)
    assert loaded.texture_classes == ["Linen", "Denim", "Felt", "Silk"]
    assert list(loaded.texture_code[:1]) == [fabrics.code(loaded.texture[0])]
    res = run_extrapolation(loaded.without_baseline(), train_speeds=(10, 20, 50), train_forces=None,
                            test_speeds=(100, 150), n_pcs=5, repeats=1, n_train=4, n_test=2,
                            variants=["original"], prefix="speed_")
    assert res.curves["speed_untrained_speed"]["original"].classes == ["Linen", "Denim", "Felt", "Silk"]


def test_texture_codes_do_not_depend_on_trial_order():
    x = np.zeros((6, 4), np.float32)
    a = FeatureSet({"original": x}, ["HB3", "Linen", "A2", "HB3", "Linen", "A2"], np.ones(6), np.ones(6))
    b = FeatureSet({"original": x}, ["Linen", "A2", "HB3", "A2", "HB3", "Linen"], np.ones(6), np.ones(6))
    code_a = dict(zip(a.texture, a.texture_code))
    code_b = dict(zip(b.texture, b.texture_code))
    assert code_a == code_b and a.texture_classes == b.texture_classes
    assert a.group is None  # no groups invented for these labels


def test_paper_defaults_unchanged():
    fs = synthetic_features(2, n_textures=16, seed=1)
    assert fs.layout is PAPER_SENSOR and fs.n_spike_trains("original") == 36
    assert fs.features["original"].shape[1] == 2160 and fs.features["speed_scaled"].shape[1] == 720
    assert fs.textures is PAPER_TEXTURES and fs.group_classes == list(PAPER_TEXTURES.groups)


def test_speed_extrapolation_without_force_labels(tmp_path):
    """Imported recordings often have speeds but no force (NaN): the trials of one speed form one cell, not none."""
    from rigctl.analysis.tasks import run_extrapolation

    fs = synthetic_features(6, n_textures=4, layout=FINGER, speeds=(20.0, 40.0, 80.0), forces=(500.0,), seed=7)
    fs = FeatureSet(fs.features, fs.texture, fs.speed_mm_s, np.full(fs.n_trials, np.nan), layout=FINGER)
    res = run_extrapolation(fs, train_speeds=(20, 40), train_forces=None, test_speeds=(80,), n_pcs=5, repeats=1,
                            n_train=4, n_test=2, variants=["original"])
    assert res.counts["extrapolation"]["tested_per_repeat"]["untrained_speed"] == 4 * 2  # 4 textures x 2 trials
    with pytest.raises(ValueError, match=r"speeds 10 mm/s and forces none g \(the file has speeds 20, 40, 80"):
        run_extrapolation(fs, train_speeds=(10,), train_forces=None, n_pcs=5, repeats=1)
