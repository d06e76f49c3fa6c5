"""Spike trains where spiking-network labs load them (rigctl.storage.spike_export, `rigctl export events|trials`):
events in Tonic's layout give back the encoded file's spike times; the per-trial CSV layout imports back into a
session that encodes to the same features; the SpikeTrains npz hold the same spikes; splits.json holds the paper's
hold-outs as the analyses draw them; folder outputs replace only rigctl's own and leave nothing on failure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.encoding.pipeline import encode_session
from rigctl.storage.encoded import open_encoded
from rigctl.storage.spike_export import read_events

PROTOCOL = """
name = "spikes_test"
textures = ["A", "B", "L"]
speeds_mm_s = [40, 60, 120]
forces_g = [500, 1000]
trials_per_condition = 4
duration_s = 0.5
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("spikes_ds")
    (d / "p.toml").write_text(PROTOCOL)
    generate_dataset(load_protocol(d / "p.toml"), d / "ds.h5", seed=7, workers=0, progress=False)
    encode_session(d / "ds.h5", d / "ds.enc.h5", progress=False)
    return d / "ds.h5", d / "ds.enc.h5"


def _run(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def _trains_from_events(ev: np.ndarray, n_ch: int) -> list[np.ndarray]:
    """Per train (SA of channels 0..n-1 then RA), the spike times in us: what a user rebuilds from the events."""
    ch = ev["y"] * 9 + ev["x"]  # the paper's 3x3 layers
    return [np.sort(ev["t"][(ch == c) & (ev["p"] == p)]) for p in (0, 1) for c in range(n_ch)]


def test_events_give_back_the_encoded_spike_times(dataset, tmp_path):
    _, enc_path = dataset
    out = tmp_path / "ev"
    r = _run("export", "events", enc_path, "--out", out)
    assert r.exit_code == 0, r.output
    with open_encoded(enc_path) as enc:
        n_trials, n_ch = enc.n_trials, enc.layout.n_channels
        trials = enc.trials
        files = sorted(out.glob("trial_*.npz"))
        assert len(files) == n_trials
        total = 0
        for i in range(n_trials):
            st = enc.spikes("original", slice(i, i + 1))
            ev, meta = read_events(out / f"trial_{int(trials['trial_id'][i]):06d}.npz")
            assert ev.dtype.names == ("x", "y", "t", "p")
            assert meta["sensor_size"] == (9, 2, 2)
            assert meta["texture"] == trials["texture"][i] and meta["variant"] == "original"
            assert meta["speed_mm_s"] == pytest.approx(trials["speed_mm_s"][i])
            assert meta["force_g"] == pytest.approx(trials["force_g"][i])
            assert np.all(np.diff(ev["t"]) >= 0)
            got = _trains_from_events(ev, n_ch)
            ends = st.spike_times_index
            starts = np.concatenate([[0], ends[:-1]])
            for k in range(2 * n_ch):
                want = np.rint(np.sort(st.spike_times[starts[k]:ends[k]]) * 1e6).astype(np.int64)
                np.testing.assert_array_equal(got[k], want)
            total += ev.size
        assert total > 1000  # the trials do spike
    manifest = json.loads((out / "rigctl_export.json").read_text())
    assert manifest["kind"] == "rigctl spike events" and manifest["t_rounding_max_us"] < 1.0
    # repeats are each condition's 0..n-1
    reps = {}
    for f in files:
        _, m = read_events(f)
        reps.setdefault((m["texture"], m["speed_mm_s"], m["force_g"]), []).append(m["repeat"])
    assert all(sorted(v) == list(range(4)) for v in reps.values())


def test_splits_are_the_analyses_draws_of_the_paper_tasks(dataset, tmp_path):
    from rigctl.analysis.data import load_features
    from rigctl.analysis.tasks import cv_split, extrapolation_split

    _, enc_path = dataset
    out = tmp_path / "ev"
    assert _run("export", "events", enc_path, "--out", out, "--seed", "3").exit_code == 0
    doc = json.loads((out / "splits.json").read_text())
    fs = load_features(enc_path, ["original"])
    ids = fs.trial_id
    # untrained speed: trained on 40/60 mm/s x 500 g (the paper's 40/60/80 x 250/500 that the data hold)
    train_idx, test_idx, test_cell = extrapolation_split(fs, seed=3)
    assert doc["tasks"]["untrained_speed"]["folds"][0]["train"] == sorted(ids[train_idx].tolist())
    for cell in ("untrained_speed", "untrained_force", "untrained_speed_force", "trained"):
        assert doc["tasks"][cell]["folds"][0]["test"] == sorted(ids[test_idx[test_cell == cell]].tolist())
    spd = dict(zip(ids.tolist(), fs.speed_mm_s.tolist()))
    frc = dict(zip(ids.tolist(), fs.force_g.tolist()))
    us = doc["tasks"]["untrained_speed"]["folds"][0]
    assert {spd[i] for i in us["train"]} <= {40.0, 60.0} and {frc[i] for i in us["train"]} == {500.0}
    assert {spd[i] for i in us["test"]} == {120.0} and {frc[i] for i in us["test"]} == {500.0}
    assert not set(us["train"]) & set(us["test"])
    # 4-fold CV: the analyses' draw, folds disjoint, each test fold a quarter of it
    idx, folds = cv_split(fs.texture, 24, 4, seed=3)
    cv = doc["tasks"]["cv"]["folds"]
    assert len(cv) == 4
    assert [f["test"] for f in cv] == [sorted(ids[idx[te]].tolist()) for _, te in folds]
    tests = [set(f["test"]) for f in cv]
    assert set().union(*tests) == set(ids[idx].tolist()) and sum(map(len, tests)) == idx.size
    assert all(not (set(f["train"]) & set(f["test"])) for f in cv)


def test_the_per_trial_layout_imports_back_to_the_same_features(dataset, tmp_path):
    ses_path, enc_path = dataset
    out = tmp_path / "peer"
    r = _run("export", "trials", ses_path, "--encoded", enc_path, "--layout", "per-trial-csv",
             "--layout", "per-trial-npz", "--out", out)
    assert r.exit_code == 0, r.output
    csvs = sorted(out.glob("Data*.csv"))
    assert len(csvs) == 72 and (out / "Data[Texture(000)][Speed(40)][Force(500)][Trial(0)].csv").exists()
    assert len(list(out.glob("SpikeTrains*.npz"))) == 72
    back = tmp_path / "back.h5"
    r = _run("import", *csvs, "--mapping", out / "rigctl_import.toml", "--out", back)
    assert r.exit_code == 0, r.output
    encode_session(back, tmp_path / "back.enc.h5", progress=False)

    def by_label(path: Path) -> dict:
        with open_encoded(path) as e:
            t = e.trials
            feats = e.features("original")
            key = [(str(t["texture"][i]), float(t["speed_mm_s"][i]), float(t["force_g"][i])) for i in
                   range(e.n_trials)]
        rows: dict = {}
        for i, k in enumerate(key):
            rows.setdefault(k, []).append(feats[i])
        return rows

    a, b = by_label(enc_path), by_label(tmp_path / "back.enc.h5")
    assert a.keys() == b.keys()
    worst = max(float(np.max(np.abs(np.asarray(a[k]) - np.asarray(b[k])))) for k in a)
    scale = max(float(np.max(np.abs(np.asarray(v)))) for v in a.values())
    assert worst <= 1e-5 * scale, worst
    # the SpikeTrains files hold the encoded spikes, train by train
    with open_encoded(enc_path) as enc:
        t = enc.trials
        i = 5
        st = enc.spikes("original", slice(i, i + 1))
        z = np.load(next(out.glob(f"SpikeTrains[[]Texture({enc.textures.labels.index(t['texture'][i]):03d})]"
                                  f"[[]Speed({t['speed_mm_s'][i]:g})][[]Force({t['force_g'][i]:g})]*.npz")))
        assert z["spikes"].dtype == np.uint8 and z["spikes"].shape[1] == 36
        # trial i's repeat is its rank in its cell; compare the one with the same trial id
        zz = [np.load(p) for p in out.glob("SpikeTrains*.npz")]
        mine = next(x for x in zz if int(x["trial_id"]) == int(t["trial_id"][i]))
        np.testing.assert_array_equal(mine["spikes"].sum(axis=0).astype(np.int64), np.diff(
            np.concatenate([[0], st.spike_times_index])))
        assert z["spikes"].shape[0] >= 500


def test_folder_outputs_replace_only_their_own_and_leave_nothing_on_failure(dataset, tmp_path, monkeypatch):
    ses_path, enc_path = dataset
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's notes")
    r = _run("export", "events", enc_path, "--out", mine, "--overwrite")
    assert r.exit_code == 2 and "not a folder rigctl wrote" in r.output
    assert (mine / "notes.txt").read_text() == "a user's notes"
    out = tmp_path / "ev"
    assert _run("export", "events", enc_path, "--out", out).exit_code == 0
    r = _run("export", "events", enc_path, "--out", out)
    assert r.exit_code == 2 and "exists" in r.output
    r = _run("export", "trials", ses_path, "--layout", "per-trial-csv", "--out", out, "--overwrite")
    assert r.exit_code == 2 and "another kind" in r.output
    (out / "added.txt").write_text("x")
    r = _run("export", "events", enc_path, "--out", out, "--overwrite")
    assert r.exit_code == 2 and "did not write" in r.output
    (out / "added.txt").unlink()
    before = sorted(p.name for p in out.iterdir())
    assert _run("export", "events", enc_path, "--out", out, "--overwrite", "--no-splits").exit_code == 0
    assert sorted(p.name for p in out.iterdir()) == [n for n in before if n != "splits.json"]
    # a failure mid-way: nothing new, the old folder as it was, no part folder
    import rigctl.storage.spike_export as se

    calls = {"n": 0}
    real = np.savez

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(28, "No space left on device")
        return real(*a, **k)

    monkeypatch.setattr(se.np, "savez", failing)
    fresh = tmp_path / "fresh"
    with pytest.raises(OSError):
        se.export_events(enc_path, fresh)
    assert not fresh.exists()
    assert sorted(p.name for p in tmp_path.iterdir() if ".part-" in p.name) == []


def test_usage_errors_are_one_line(dataset, tmp_path):
    ses_path, enc_path = dataset
    r = _run("export", "events", enc_path, "--out", tmp_path / "x", "--variant", "nope")
    assert r.exit_code == 2 and "nope" in r.output and "Traceback" not in r.output
    r = _run("export", "trials", ses_path, "--layout", "per-trial-npz", "--out", tmp_path / "y")
    assert r.exit_code == 2 and "--encoded" in r.output
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


PROFILE_PROTOCOL = """
name = "profiles_test"
textures = ["A", "D", "L"]
forces_g = [500]
trials_per_condition = 4
travel_mm = 60
order = "blocked"

[[profiles]]
name = "slow"
kind = "constant"
speed_mm_s = 40

[[profiles]]
name = "medium"
kind = "constant"
speed_mm_s = 80

[[profiles]]
name = "fast"
kind = "constant"
speed_mm_s = 120

[[profiles]]
name = "slow-to-fast"
kind = "ramp"
start_mm_s = 40
end_mm_s = 120
"""


@pytest.fixture(scope="module")
def profile_dataset(tmp_path_factory):
    """A velocity-profile session (Fig. 4's kind: the ramp's speed label, 80, is the medium profile's too)."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("profiles_ds")
    generate_dataset(parse_protocol(PROFILE_PROTOCOL), d / "p.h5", seed=3, workers=0, progress=False)
    encode_session(d / "p.h5", d / "p.enc.h5", progress=False)
    return d / "p.h5", d / "p.enc.h5"


def test_a_profile_sessions_events_carry_the_profile_and_fig4s_splits(profile_dataset, tmp_path):
    """Issue 79 item 2: each event file names its profile, and splits.json holds Fig. 4C's profile hold-out as
    ``analyze --task realtime`` draws it, not speed cells that mix the ramps into the trained ones."""
    from rigctl.analysis.tasks import realtime_draw, realtime_rng

    _, enc_path = profile_dataset
    out = tmp_path / "ev"
    r = _run("export", "events", enc_path, "--out", out, "--seed", 4)
    assert r.exit_code == 0, r.output
    with open_encoded(enc_path) as enc:
        t = enc.trials
        ids, profile, texture = np.asarray(t["trial_id"]), np.asarray(t["profile"]).astype(str), np.asarray(t["texture"])
    for tid, prof in zip(ids, profile):
        _, meta = read_events(out / f"trial_{int(tid):06d}.npz")
        assert meta["profile"] == prof
    assert set(profile) == {"slow", "medium", "fast", "slow-to-fast"}
    splits = json.loads((out / "splits.json").read_text())
    tasks = splits["tasks"]
    assert {"rt_offline", "rt_trained", "rt_untrained"} <= set(tasks) and "untrained_speed" not in tasks
    trained = set(ids[np.isin(profile, ["slow", "medium"])].tolist())
    (untr,) = tasks["rt_untrained"]["folds"]
    (held,) = tasks["rt_trained"]["folds"]
    assert set(untr["test"]) == set(ids.tolist()) - trained  # fast and the ramp: the untrained profiles
    assert set(held["train"]) | set(held["test"]) == trained and not set(held["train"]) & set(held["test"])
    # the draw is the analysis' own (its repetition 0 at the same seed)
    folds, train, held_rows, _ = realtime_draw(texture, np.isin(profile, ["slow", "medium"]), 4, 0.75,
                                               realtime_rng(4, 0))
    assert held["train"] == sorted(ids[train].tolist()) and held["test"] == sorted(ids[held_rows].tolist())
    assert [f["test"] for f in tasks["rt_offline"]["folds"]] == [sorted(ids[te].tolist()) for _, te in folds]


def test_a_profile_session_exports_per_trial_and_imports_back(profile_dataset, tmp_path):
    """``export trials`` of a profile session: every trial named with its profile (it was refused: two trials
    shared a name), and the import mapping reads the profile back."""
    from rigctl.storage.session import open_session

    session, _ = profile_dataset
    out = tmp_path / "peer"
    r = _run("export", "trials", session, "--layout", "per-trial-csv", "--out", out)
    assert r.exit_code == 0, r.output
    names = sorted(p.name for p in out.glob("Data*.csv"))
    assert len(names) == 48 and all("[Profile(" in n for n in names)
    r = _run("import", *sorted(str(p) for p in out.glob("Data*.csv")), "--mapping", out / "rigctl_import.toml",
             "--out", tmp_path / "back.h5")
    assert r.exit_code == 0, r.output
    with open_session(session) as a, open_session(tmp_path / "back.h5") as b:
        want = sorted((str(x["texture"]), str(x["profile"])) for x in a.plan)
        got = sorted((str(x["texture"]), str(x["profile"])) for x in b.plan)
    assert got == want


def test_speed_scaled_events_name_their_time_base(dataset, tmp_path):
    """Issue 79 item 3: a speed-scaled variant's events say ``time_base = speed-scaled`` and give the trial's
    duration in that base (a 40 mm/s trial of 0.5 s lasts 0.167 s there), its spikes inside it; real-time ones say
    so."""
    _, enc_path = dataset
    for variant, base in (("speed_scaled", "speed-scaled"), ("original", "real time")):
        out = tmp_path / variant
        assert _run("export", "events", enc_path, "--out", out, "--variant", variant, "--no-splits").exit_code == 0
        manifest = json.loads((out / "rigctl_export.json").read_text())
        assert manifest["time_base"] == base
        for f in sorted(out.glob("trial_*.npz")):
            ev, meta = read_events(f)
            assert meta["time_base"] == base
            factor = meta["speed_mm_s"] / 120.0 if variant == "speed_scaled" else 1.0
            assert meta["duration_s"] == pytest.approx(meta["duration_real_s"] * factor, rel=1e-6)
            assert ev.size == 0 or ev["t"].max() <= meta["duration_s"] * 1e6 + 1000  # within the trial (1 ms step)


def test_the_splits_take_the_trained_cells_of_any_session(dataset, tmp_path):
    """Issue 79 item 5: ``--train-speeds/--train-forces`` give an off-grid session its extrapolation splits (this
    one has no 80 mm/s, the paper's grid is not its own)."""
    _, enc_path = dataset
    out = tmp_path / "ev"
    r = _run("export", "events", enc_path, "--out", out, "--train-speeds", "40,60", "--train-forces", "500")
    assert r.exit_code == 0, r.output
    tasks = json.loads((out / "splits.json").read_text())["tasks"]
    with open_encoded(enc_path) as enc:
        t = enc.trials
        speed_of = dict(zip(np.asarray(t["trial_id"]).tolist(), np.asarray(t["speed_mm_s"]).tolist()))
        force_of = dict(zip(np.asarray(t["trial_id"]).tolist(), np.asarray(t["force_g"]).tolist()))
    (fold,) = tasks["untrained_speed"]["folds"]
    assert {speed_of[i] for i in fold["test"]} == {120.0} and {force_of[i] for i in fold["test"]} == {500.0}
    assert {speed_of[i] for i in fold["train"]} == {40.0, 60.0} and {force_of[i] for i in fold["train"]} == {500.0}
    (fold,) = tasks["untrained_force"]["folds"]
    assert {force_of[i] for i in fold["test"]} == {1000.0}
    bad = _run("export", "events", enc_path, "--out", tmp_path / "x", "--train-speeds", "fast")
    assert bad.exit_code == 2 and "comma-separated numbers" in bad.output and not (tmp_path / "x").exists()
