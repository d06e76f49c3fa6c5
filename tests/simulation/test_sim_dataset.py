"""render_trial (durations, traces, ramps) and generate_dataset (a readable session with the plan; reproducible for
any number of workers); the `rigctl sim dataset` command."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.acquisition.protocol import load_protocol
from rigctl.simulation.dataset import RampProfile, generate_dataset, render_trial
from rigctl.simulation.model import RigConfig
from rigctl.simulation.textures import TEXTURES
from rigctl.storage.session import TrialStatus, open_session

PROTOCOL = """
name = "sim-test"
textures = ["A", "C", "L"]
speeds_mm_s = [40, 120]
forces_g = [250, 1000]
trials_per_condition = 2
travel_mm = 120
"""


@pytest.fixture
def protocol_path(tmp_path):
    p = tmp_path / "sim_test.toml"
    p.write_text(PROTOCOL)
    return p


@pytest.mark.parametrize("speed,seconds", [(40, 6.0), (60, 4.0), (80, 3.0), (100, 2.4), (120, 2.0)])
def test_trial_durations_follow_240_mm_of_travel(speed, seconds):
    cfg = RigConfig()
    t = render_trial("B", speed, 500, config=cfg, rng=np.random.default_rng(0))
    assert t.n_samples == round(seconds * 1000)
    assert t.taxels.shape == (t.n_samples, 18) and t.taxels.dtype == np.uint16
    np.testing.assert_array_equal(t.seq, np.arange(t.n_samples) % 65536)
    # the stepper's static speed error and slow wobble are small (< 2 %, mean within 1 %)
    np.testing.assert_allclose(t.speed_mm_s, speed, rtol=0.02)
    assert np.mean(t.speed_mm_s) == pytest.approx(speed, rel=0.01)
    assert abs(np.mean(t.force_g) - 500) < 25
    assert t.force_time_s[-1] < seconds and t.speed_time_s.shape == t.speed_mm_s.shape
    # the trial starts at the drum's index mark (first frame flagged SYNC_IN, like a recorded trial), up to a small
    # jitter, and 240 mm is less than a revolution (314 mm): no second index pulse
    assert t.attrs["aligned_to_index"] and abs(t.attrs["start_phase_mm"]) < 2.0
    assert t.flags[0] & 1 and int((t.flags & 1).sum()) == 1
    assert 240.0 < cfg.drum.circumference_mm


def test_ramp_profile_covers_the_travel():
    prof = RampProfile(40.0, 120.0)
    assert prof.duration_for_travel(240) == pytest.approx(3.0)
    t = render_trial("L", 80, 500, rng=np.random.default_rng(1), profile=prof)
    assert t.n_samples == 3000
    assert t.speed_mm_s[0] == pytest.approx(40, rel=0.02) and t.speed_mm_s[-1] > 115  # within the speed error
    assert np.all(np.diff(t.speed_mm_s) >= -0.3)  # rising, up to the stepper's slow wobble
    # the texture's temporal frequency rises along the ramp (time contracts as the drum speeds up)
    x = t.taxels[:, 4].astype(float)
    early, late = x[:1000] - x[:1000].mean(), x[-1000:] - x[-1000:].mean()
    crossings = lambda s: int(np.sum(np.diff(np.sign(s)) != 0))  # noqa: E731
    assert crossings(late) > 1.5 * crossings(early)
    # a ramp with a held end: 1 s ramp 40 -> 120 (80 mm), then 160 mm at 120 mm/s
    assert RampProfile(40.0, 120.0, 1.0).duration_for_travel(240) == pytest.approx(1 + 160 / 120)


def test_render_trial_is_seeded_and_varies_between_trials():
    a = render_trial("D", 80, 500, rng=np.random.default_rng(7))
    b = render_trial("D", 80, 500, rng=np.random.default_rng(7))
    c = render_trial("D", 80, 500, rng=np.random.default_rng(8))
    np.testing.assert_array_equal(a.taxels, b.taxels)
    assert a.attrs["start_phase_mm"] != c.attrs["start_phase_mm"]
    assert np.any(a.taxels != c.taxels)
    # trial-to-trial variability is there, but the texture dominates: same-texture trials are closer in their
    # per-taxel spectra than trials of another texture
    other = render_trial("H", 80, 500, rng=np.random.default_rng(9))

    def spectrum(t):
        return np.abs(np.fft.rfft(t.taxels[:, :9].astype(float) - t.taxels[:, :9].mean(0), axis=0))[:400].ravel()

    assert np.linalg.norm(spectrum(a) - spectrum(c)) < 0.5 * np.linalg.norm(spectrum(a) - spectrum(other))


def _windows(t, taxel=4, window_ms=100):
    x = t.taxels[:, taxel].astype(float)
    return x[: x.size // window_ms * window_ms].reshape(-1, window_ms).mean(axis=1)


def test_trials_of_a_texture_are_phase_aligned():
    """Trials start at the index mark: the 100 ms-window means (what the paper's SR features see) of two trials of
    one texture agree far better than those of two textures, and far better than if the start were random."""
    a = _windows(render_trial("L", 80, 500, rng=np.random.default_rng(1)))
    b = _windows(render_trial("L", 80, 500, rng=np.random.default_rng(2)))
    assert a.std() > 50  # the ridges modulate the window means (not averaged away)
    for letter in "AN":  # the smooth plate; waves of double spacing
        other = _windows(render_trial(letter, 80, 500, rng=np.random.default_rng(3)))
        assert np.abs(a - b).mean() < 0.2 * np.abs(a - other).mean(), letter
    # a trial started half a period later (what a random drum position would give) does not line up
    period_ms = int(round(TEXTURES["L"].period_mm / 80 * 1000 / 2))
    rng = np.random.default_rng(4)
    shifted = render_trial("L", 80, 500, rng=rng, duration_s=3.0 + period_ms / 1000)
    s = shifted.taxels[period_ms:, 4].astype(float)
    s = s[: s.size // 100 * 100].reshape(-1, 100).mean(axis=1)[: a.size]
    assert np.abs(a - b).mean() < 0.2 * np.abs(a - s).mean()


def test_trials_can_start_at_any_drum_angle():
    """DrumConfig.start_at_index = False: a recorder without an index signal starts each trial at an arbitrary drum
    angle; the first frame is no index frame, the later index passes are still flagged, the start angles spread over
    the circumference, and the default (index start) is untouched by the option."""
    cfg = RigConfig()
    cfg.drum.start_at_index = False
    circ = cfg.drum.circumference_mm
    phases = []
    for i in range(16):
        t = render_trial("L", 120, 500, config=cfg, rng=np.random.default_rng(i))
        phase = t.attrs["start_phase_mm"]
        assert t.attrs["aligned_to_index"] is False and 0.0 <= phase < circ
        # 240 mm of travel crosses the index mark once exactly when the start is within 240 mm before it
        crossings = int((t.flags & 1).sum())
        assert crossings == (1 if phase + 240.0 * np.mean(t.speed_mm_s) / 120 >= circ else 0), (phase, crossings)
        assert not (t.flags[0] & 1) or phase < 1e-6
        phases.append(phase)
    assert np.std(phases) > 0.2 * circ  # uniform over 314 mm: sd ~ 91 mm
    aligned = render_trial("L", 120, 500, config=RigConfig(), rng=np.random.default_rng(0))
    assert aligned.attrs["aligned_to_index"] is True and aligned.flags[0] & 1


def test_render_trial_rejects_bad_input():
    with pytest.raises(ValueError):
        render_trial("A", 0, 500, rng=np.random.default_rng())
    with pytest.raises(ValueError):
        render_trial("A", 80, -1, rng=np.random.default_rng())
    with pytest.raises(KeyError):
        render_trial("Z", 80, 500, rng=np.random.default_rng())


def test_dataset_dynamic_range_suits_sa_encoding():
    """Normalised 0-1 per taxel over a dataset (the paper's normalisation), the readings use the range."""
    rng = np.random.default_rng(3)
    trials = [render_trial(tex, v, f, rng=rng) for tex in "AHM" for v in (40, 120) for f in (250, 1000)]
    x = np.concatenate([t.taxels for t in trials]).astype(float)
    assert (x == 1023).mean() < 1e-3 and (x == 0).mean() < 1e-3  # no ADC clipping to speak of
    norm = (x - x.min(0)) / (x.max(0) - x.min(0))
    p5, p95 = np.percentile(norm, [5, 95], axis=0)
    assert np.all(p95 - p5 > 0.3)  # force and texture spread the readings over the range, per taxel


def test_generate_dataset_writes_a_readable_session(protocol_path, tmp_path):
    out = tmp_path / "ds.h5"
    summary = generate_dataset(load_protocol(protocol_path), out, seed=4, workers=0, progress=False)
    assert summary["n_trials"] == 24 and summary["samples"] == 12 * 3000 + 12 * 1000
    with open_session(out) as s:
        assert s.kind == "simulated-dataset"
        assert len(s.plan) == 24 and np.all(s.plan["status"] == TrialStatus.COMPLETE)
        assert sorted(set(s.plan["texture"])) == ["A", "C", "L"]
        assert RigConfig.from_dict(s.rig_config) == RigConfig()
        for row in s.plan[::5]:
            t = s.trial(int(row["trial_id"]))
            assert t.n_samples == round(row["duration_s"] * 1000) == round(120 / row["speed_mm_s"] * 1000)
            assert t.attrs["texture"] == row["texture"] and t.attrs["force_g"] == row["force_g"]
            assert abs(t.force_g.mean() - row["force_g"]) < 0.05 * row["force_g"]
        cal = s.calibration
        assert cal is not None and np.all(cal["taxel_min"] < cal["taxel_max"])
        first = s.trial(0).taxels
    # the same seed gives the same file content; a reduced trial count is a prefix-free new plan
    again = generate_dataset(load_protocol(protocol_path), tmp_path / "again.h5", seed=4, workers=0, progress=False,
                             trials_per_condition=1)
    assert again["n_trials"] == 12
    with open_session(tmp_path / "again.h5") as s:
        assert len(s.plan) == 12
    with pytest.raises(FileExistsError):
        generate_dataset(load_protocol(protocol_path), out, seed=4, workers=0, progress=False)
    summary = generate_dataset(load_protocol(protocol_path), out, seed=4, workers=0, progress=False, overwrite=True)
    with open_session(out) as s:
        np.testing.assert_array_equal(s.trial(0).taxels, first)


def test_cli_sim_dataset(protocol_path, tmp_path):
    from rigctl.cli import main

    out = tmp_path / "cli.h5"
    result = CliRunner().invoke(main, ["sim", "dataset", str(protocol_path), "--out", str(out),
                                       "--trials-per-condition", "1", "--seed", "2", "--workers", "0", "--quiet"])
    assert result.exit_code == 0, result.output
    assert "12 trials" in result.output and "real time" in result.output
    with open_session(out) as s:
        assert len(s.completed_ids()) == 12
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\ntextures = ["Z"]\nforces_g = [500]\nspeeds_mm_s = [80]\n')
    result = CliRunner().invoke(main, ["sim", "dataset", str(bad), "--out", str(tmp_path / "bad.h5")])
    assert result.exit_code != 0 and "textures" in result.output


def test_resume_renders_only_missing_trials_and_matches_a_fresh_run(protocol_path, tmp_path):
    from rigctl.simulation.dataset import _init_worker, _render_planned
    from rigctl.storage.session import SessionWriter

    fresh = tmp_path / "fresh.h5"
    generate_dataset(load_protocol(protocol_path), fresh, seed=6, workers=0, progress=False)
    # an interrupted run: the plan is there, 5 trials were written
    proto = load_protocol(protocol_path)
    part = tmp_path / "part.h5"
    writer = SessionWriter.create(part, plan=proto.plan(), protocol_source=proto.source, protocol_name=proto.name,
                                  kind="simulated-dataset", attrs={"dataset_seed": 6}, compression=None)
    _init_worker(RigConfig().to_dict(), 6)
    rows = [(p.trial_id, p.texture, p.speed_mm_s, p.force_g, p.duration_s, p.ramp_start_mm_s, p.ramp_end_mm_s)
            for p in proto.plan()[:5]]
    writer.write_trials(_render_planned(r) for r in rows)
    writer.close()  # one writer per session file: the resume opens its own
    summary = generate_dataset(load_protocol(protocol_path), part, seed=999, workers=0, progress=False, resume=True)
    assert summary["n_trials"] == 24 - 5  # the stored dataset seed (6) wins over the argument
    with open_session(fresh) as a, open_session(part) as b:
        assert a.completed_ids() == b.completed_ids() == list(range(24))
        for tid in range(24):
            np.testing.assert_array_equal(a.trial(tid).taxels, b.trial(tid).taxels)
        np.testing.assert_array_equal(a.calibration["taxel_min"], b.calibration["taxel_min"])
        np.testing.assert_array_equal(a.calibration["taxel_max"], b.calibration["taxel_max"])
    from rigctl.storage.provenance import read_provenance

    (resumed,) = read_provenance(part)["resumed"]  # the run that rendered trials 5-23 is named in the file
    assert resumed["complete_trials_before"] == 5 and resumed["provenance"]["kind"] == "simulated-dataset"
    assert "resumed" not in read_provenance(fresh)
    # a file keeps its layout: the generator's own is schema 5 (no views in the trials' groups), the interrupted run's
    # schema 4 (SessionWriter.create's default), whose resumed trials got their views as the first five did
    import h5py

    with h5py.File(fresh, "r") as a, h5py.File(part, "r") as b:
        assert a.attrs["schema_version"] == 5 and b.attrs["schema_version"] == 4
        for tid in range(24):
            assert "taxels" not in a[f"trials/{tid:06d}"]
            assert b[f"trials/{tid:06d}/taxels"].is_virtual and b[f"trials/{tid:06d}/taxels"].shape[1] == 18


def test_cli_start_at_any_angle_and_a_resume_keeps_the_stored_model(protocol_path, tmp_path):
    """`--start-at any-angle` is stored in the session's rig config and its trials are not index-aligned; a resume
    renders the missing trials with the stored model, whatever model it is given, so the file equals a fresh one."""
    import json

    from rigctl.cli import main
    from rigctl.simulation.dataset import _init_worker, _render_planned
    from rigctl.storage.session import SessionWriter

    fresh = tmp_path / "any.h5"
    result = CliRunner().invoke(main, ["sim", "dataset", str(protocol_path), "--out", str(fresh), "--seed", "6",
                                       "--workers", "0", "--start-at", "any-angle", "--quiet"])
    assert result.exit_code == 0, result.output
    with open_session(fresh) as s:
        assert s.rig_config["drum"]["start_at_index"] is False
        assert not any(s.trial(t).attrs["aligned_to_index"] for t in s.completed_ids())
    # an interrupted any-angle run, resumed by a command that does not repeat the option
    cfg = RigConfig()
    cfg.drum.start_at_index = False
    proto = load_protocol(protocol_path)
    part = tmp_path / "part.h5"
    writer = SessionWriter.create(part, plan=proto.plan(), protocol_source=proto.source, protocol_name=proto.name,
                                  kind="simulated-dataset", attrs={"dataset_seed": 6}, compression=None,
                                  rig_config=cfg.to_dict())
    _init_worker(cfg.to_dict(), 6)
    rows = [(p.trial_id, p.texture, p.speed_mm_s, p.force_g, p.duration_s, p.ramp_start_mm_s, p.ramp_end_mm_s)
            for p in proto.plan()[:5]]
    writer.write_trials(_render_planned(r) for r in rows)
    writer.close()
    result = CliRunner().invoke(main, ["sim", "dataset", str(protocol_path), "--out", str(part), "--resume",
                                       "--workers", "0", "--quiet", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["n_trials"] == 24 - 5
    with open_session(fresh) as a, open_session(part) as b:
        assert a.completed_ids() == b.completed_ids() == list(range(24))
        for tid in range(24):
            np.testing.assert_array_equal(a.trial(tid).taxels, b.trial(tid).taxels)
            assert b.trial(tid).attrs["aligned_to_index"] is False


CUSTOM = """
name = "custom-set"
textures = ["HB3", "Linen", "ridge-15"]
speeds_mm_s = [80]
forces_g = [500]
trials_per_condition = 2
travel_mm = 80

[texture_set]
name = "lab"
textures = ["Linen", "HB3", "ridge-15", "unused"]

[texture_set.groups]
woven = ["Linen"]
printed = ["HB3", "ridge-15", "unused"]

[texture_set.geometry.ridge-15]
kind = "rectangular"
period_mm = 15.0
height_mm = 1.0
width_mm = 5.0
"""


def test_generate_dataset_stores_the_sensor_and_the_protocols_texture_set_and_two_workers_give_the_same_file(
        tmp_path):
    """The sensor and the protocol's own texture set are stored, and reach the worker processes: two workers (a spawned
    pool) render the same file as this process does (one pool here: starting its workers is most of the cost)."""
    from rigctl.core import PAPER_SENSOR

    path = tmp_path / "custom.toml"
    path.write_text(CUSTOM)
    proto = load_protocol(path)
    for workers in (0, 2):
        out = tmp_path / f"custom{workers}.h5"
        generate_dataset(proto, out, seed=3, workers=workers, progress=False)
        with open_session(out) as s:
            assert s.layout is PAPER_SENSOR
            assert s.textures == proto.texture_set and s.textures.name == "lab"
            assert s.textures.labels == ("Linen", "HB3", "ridge-15", "unused") and s.textures.code("HB3") == 1
            assert s.textures.group_of("Linen") == "woven"
            assert sorted(set(s.plan["texture"])) == ["HB3", "Linen", "ridge-15"]
            trials = {str(r["texture"]): s.trial(int(r["trial_id"])) for r in s.plan}
            assert all(t.layout is PAPER_SENSOR and t.taxels.shape == (1000, 18) for t in trials.values())
            # each label is rendered with its own geometry (the set's for ridge-15, one derived from the label else)
            assert len({t.taxels.tobytes() for t in trials.values()}) == 3
            row = s.plan[s.plan["texture"] == "ridge-15"][-1]
            again = render_trial("ridge-15", 80.0, 500.0, rng=np.random.default_rng(
                np.random.SeedSequence([3, int(row["trial_id"])])), duration_s=1.0, textures=proto.texture_set)
            np.testing.assert_array_equal(trials["ridge-15"].taxels, again.taxels)
    with open_session(tmp_path / "custom0.h5") as a, open_session(tmp_path / "custom2.h5") as b:
        assert a.completed_ids() == b.completed_ids() == list(range(6))
        for tid in a.completed_ids():
            ta, tb = a.trial(tid), b.trial(tid)
            np.testing.assert_array_equal(ta.taxels, tb.taxels)
            np.testing.assert_array_equal(ta.force_g, tb.force_g)
            np.testing.assert_array_equal(ta.speed_mm_s, tb.speed_mm_s)
            assert ta.attrs.keys() == tb.attrs.keys()
            assert ta.attrs["texture"] == tb.attrs["texture"] and ta.attrs["start_phase_mm"] == tb.attrs["start_phase_mm"]
        np.testing.assert_array_equal(a.calibration["taxel_max"], b.calibration["taxel_max"])
        np.testing.assert_array_equal(a.calibration["taxel_min"], b.calibration["taxel_min"])


def test_the_per_taxel_extremes_are_numpys_column_min_and_max_and_make_the_calibration(protocol_path, tmp_path):
    """Issue 57 item 6: the generator's per-taxel extremes (its calibration) are computed over 64 rows laid side by
    side (numpy's column reduction of an 18-wide array cost ~0.5 ms a trial of the writer): the same numbers as
    ``min(axis=0)`` / ``max(axis=0)`` for any length (a multiple of the fold, a remainder, fewer rows than it, none)
    and a non-contiguous input; a generated dataset's calibration is the column extremes of all its trials."""
    from rigctl.simulation.dataset import EXTREMA_FOLD, taxel_extrema

    rng = np.random.default_rng(5)
    assert taxel_extrema(np.zeros((0, 18), np.uint16)) is None
    for n in (1, 2, EXTREMA_FOLD - 1, EXTREMA_FOLD, EXTREMA_FOLD + 1, 3 * EXTREMA_FOLD, 6000, 6001):
        x = rng.integers(0, 1024, (n, 18)).astype(np.uint16)
        for arr in (x, x[:, ::2], np.asfortranarray(x)):
            lo, hi = taxel_extrema(arr)
            assert lo.dtype == hi.dtype == np.uint16
            np.testing.assert_array_equal(lo, arr.min(axis=0))
            np.testing.assert_array_equal(hi, arr.max(axis=0))
    out = tmp_path / "ds.h5"
    generate_dataset(load_protocol(protocol_path), out, seed=2, workers=0, progress=False, trials_per_condition=1)
    with open_session(out) as s:
        every = np.concatenate([s.trial(t).taxels for t in s.completed_ids()])
        np.testing.assert_array_equal(s.calibration["taxel_min"], every.min(axis=0))
        np.testing.assert_array_equal(s.calibration["taxel_max"], every.max(axis=0))


def test_the_render_workers_fork_from_a_one_thread_process_and_spawn_beside_threads(monkeypatch):
    """Issue 57 item 6: a worker forked from the generating process starts from its imports (numpy, numba, the
    model) instead of importing them again; beside other threads (a GUI, tqdm's monitor) it is spawned, since a fork
    can leave the child waiting on a lock another thread held."""
    import multiprocessing as mp
    import threading

    from rigctl.simulation import dataset

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    monkeypatch.setattr(threading, "active_count", lambda: 1)
    assert dataset._pool_context().get_start_method() == "fork"
    monkeypatch.setattr(threading, "active_count", lambda: 2)
    assert dataset._pool_context().get_start_method() == "spawn"


def test_a_forked_worker_with_a_commits_worth_of_slots_writes_the_in_process_file(protocol_path, tmp_path,
                                                                                  monkeypatch):
    """Issue 57 item 6: the worker renders on while the writer appends and commits a batch (the slots hold a whole
    commit's trials, not 24), and a forked worker renders the very file this process renders alone."""
    import multiprocessing as mp

    from rigctl.simulation import dataset

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    made = []
    real = dataset.TrialSlots

    def slots(*args, **kwargs):
        made.append(kwargs["n_blocks"] * kwargs["block"])
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset, "TrialSlots", slots)
    monkeypatch.setattr(dataset, "_pool_context", lambda: mp.get_context("fork"), raising=False)
    proto = load_protocol(protocol_path)
    generate_dataset(proto, tmp_path / "w0.h5", seed=5, workers=0, progress=False)
    generate_dataset(proto, tmp_path / "w1.h5", seed=5, workers=1, progress=False)
    assert made and made[0] >= dataset.COMMIT_TRIALS
    with open_session(tmp_path / "w0.h5") as a, open_session(tmp_path / "w1.h5") as b:
        assert a.completed_ids() == b.completed_ids() == list(range(24))
        for tid in a.completed_ids():
            ta, tb = a.trial(tid), b.trial(tid)
            for name in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s",
                         "speed_time_s"):
                np.testing.assert_array_equal(getattr(ta, name), getattr(tb, name))
            assert {k: repr(v) for k, v in ta.attrs.items()} == {k: repr(v) for k, v in tb.attrs.items()}  # (NaN)
        np.testing.assert_array_equal(a.calibration["taxel_min"], b.calibration["taxel_min"])
        np.testing.assert_array_equal(a.calibration["taxel_max"], b.calibration["taxel_max"])


def test_the_render_worker_hands_the_trial_facts_and_extremes_to_the_writer(protocol_path, tmp_path, monkeypatch):
    """Issue 57 item 6: the writing process (the bound at 1 worker) no longer computes a trial's facts (storage's
    ``trial_facts.sample_facts``: SHA-256, extremes, fingerprint) nor its per-taxel extremes: the render worker
    does, from its slot's bytes, and hands them over with the trial. The file is the in-process one (every trial's
    facts row and the calibration equal)."""
    import multiprocessing as mp

    from rigctl.simulation import dataset
    from rigctl.storage import trial_facts

    proto = load_protocol(protocol_path)
    generate_dataset(proto, tmp_path / "w0.h5", seed=5, workers=0, progress=False)
    calls = {"sha256": 0, "extrema": 0}
    sha256, extrema = trial_facts.sha256, dataset.taxel_extrema

    def counted_sha256(data):
        calls["sha256"] += 1
        return sha256(data)

    def counted_extrema(taxels):
        calls["extrema"] += 1
        return extrema(taxels)

    # a spawned worker imports the real functions: only this (the writing) process counts its own calls
    monkeypatch.setattr(trial_facts, "sha256", counted_sha256)
    monkeypatch.setattr(dataset, "taxel_extrema", counted_extrema)
    monkeypatch.setattr(dataset, "_pool_context", lambda: mp.get_context("spawn"))
    generate_dataset(proto, tmp_path / "w1.h5", seed=5, workers=1, progress=False)
    assert calls == {"sha256": 0, "extrema": 0}
    with h5py.File(tmp_path / "w0.h5", "r") as a, h5py.File(tmp_path / "w1.h5", "r") as b:
        assert len(a["recording/facts"]) == 24
        assert a["recording/facts"][()].tobytes() == b["recording/facts"][()].tobytes()
        for name in ("taxel_min", "taxel_max"):
            np.testing.assert_array_equal(a["calibration"][name][()], b["calibration"][name][()])
