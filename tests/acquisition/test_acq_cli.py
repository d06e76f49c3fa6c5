"""`rigctl acquire` and `rigctl info` as separate processes: quick_check end to end and the replays on the simulated
rig (real ptys, real pymodbus/pyserial), and a kill -9 mid-session followed by --resume on the in-process rig
(``--inprocess``: the runner, the session writer and the resume are what it checks, in a fraction of the real time;
the soak, tests/acquisition/test_acq_soak.py, kills ``rigctl acquire --sim`` on ptys again and again)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from ..conftest import wait_unlocked

REPO = Path(__file__).resolve().parents[2]
RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)


def _env(tmp_path):
    env = dict(os.environ)
    env["RIGCTL_CONFIG"] = str(tmp_path / "rig.json")  # never the user's ~/.config
    return env


def _info(path, env) -> dict:
    out = subprocess.run([*RIGCTL, "info", str(path), "--json"], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_quick_check_end_to_end(tmp_path):
    env = _env(tmp_path)
    out = tmp_path / "quick.h5"
    # quick_check with one trial a plate (its three plates, 2 s trials: what the checks below need; the README's
    # six-trial quick_check --sim runs from the installed wheel in tests/test_packaging.py)
    proto = tmp_path / "quick_check.toml"
    proto.write_text((REPO / "protocols" / "quick_check.toml").read_text().replace("trials_per_condition = 2",
                                                                                  "trials_per_condition = 1"))
    # no wall-clock target here (the simulated rig runs in real time, so a loaded machine only stretches the run;
    # speed targets belong in benchmarks/, e.g. bench_acquisition.py): the timeout only bounds a hang
    run = subprocess.run([*RIGCTL, "acquire", str(proto), "--sim", "--out", str(out)],
                         capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "trials complete: 3/3" in run.stdout and "dropped frames: 0" in run.stdout
    info = _info(out, env)
    assert info["totals"]["complete"] == info["totals"]["trials"] == 3
    assert {t["texture"] for t in info["trials"]} == set("ABL")
    assert info["totals"]["dropped_frames"] == 0 and info["totals"]["crc_errors"] == 0
    for t in info["trials"]:
        assert t["status"] == "complete"
        assert t["samples"] == round(t["duration_s"] * 1000)
        assert abs(t["samples_per_s"] - 1000) <= 1
        # the device's frame rate measured on the host clock (independent of how many frames were kept)
        # over a 2 s trial, within 1 %: a loaded machine delays the host's reads, not the board (993 Hz at load ~15)
        assert abs(t["host_rate_hz"] - 1000) <= 10, t
        # the force loop held the setpoint (the trial's force and speed from the drum status reads while the board
        # recorded it; null in the JSON: the rig measured none, rig.recorded_means)
        assert t["force_mean_g"] is not None and t["speed_mean_mm_s"] is not None, f"no force or speed measured: {t}"
        assert abs(t["force_mean_g"] - t["force_g"]) < 15, t
        assert abs(t["speed_mean_mm_s"] - t["speed_mm_s"]) < 2, t
    # the human-readable table prints the same trials
    table = subprocess.run([*RIGCTL, "info", str(out)], capture_output=True, text=True, env=env, timeout=60)
    assert table.returncode == 0
    assert sum(line.endswith("  complete") for line in table.stdout.splitlines()) == 3
    with h5py.File(out, "r") as f:  # plain h5py: contiguous sequence numbers, textures from the plan
        for g in f["trials"].values():
            seq = g["seq"][()].astype(np.int64)
            assert ((np.diff(seq) & 0xFFFF) == 1).all()
            assert g["taxels"].shape == (2000, 18)
            assert g.attrs["texture"] in "ABL"
        rig = json.loads(f.attrs["rig_config"])
        from rigctl.devices.wire import MEGA_FIRMWARE_VERSION  # the version the virtual Mega reports (test_wire_spec
        # holds it equal to the firmware header's)
        assert rig["mode"] == "sim" and rig["drum_firmware"] == list(MEGA_FIRMWARE_VERSION)


#: the kill -9 test's protocol: 16 short trials, so that the in-process rig is still recording when it is killed
MANY = """\
name = "many"
textures = ["A", "B"]
speeds_mm_s = [120]
forces_g = [400]
trials_per_condition = 8
duration_s = 0.4

[settle]
settle_time_ms = 50
"""


def _digest(f, tid):
    g = f[f"trials/{tid:06d}"]
    return hashlib.sha1(g["taxels"][()].tobytes()).hexdigest(), g.attrs["started_utc"]


def _complete(path) -> list[int]:
    try:
        with h5py.File(path, "r") as f:
            return [int(t) for t in np.flatnonzero(f["plan"]["status"][()] == 1)]
    except (OSError, KeyError):
        return []


def test_kill_9_mid_session_then_resume(tmp_path):
    env = _env(tmp_path)
    proto = tmp_path / "many.toml"
    proto.write_text(MANY)
    n_plan = 16
    out = tmp_path / "s.h5"
    # the writer in an interpreter of its own, so that SIGKILL hits the writer itself (through the preloaded rigctl it
    # hit the launcher's client, and the writer went on until the launcher noticed: a loaded CI run's resume then
    # found the session "being written by another process")
    proc = subprocess.Popen([sys.executable, "-m", "rigctl", "acquire", str(proto), "--inprocess", "--out", str(out),
                             "--quiet"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while len(_complete(out)) < 2:
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.05)  # somewhere inside a later trial
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL

    # plain h5py opens the file (once the killed writer's commit helper has let go of it: CI run 36 opened it while
    # the helper still held the lock, at load 7), every finished trial is whole, the unfinished ones are pending
    wait_unlocked(out)
    with h5py.File(out, "r") as f:
        status = f["plan"]["status"][()]
        before = {int(t): _digest(f, int(t)) for t in np.flatnonzero(status == 1)}
        assert 2 <= len(before) < n_plan
        for tid in before:
            assert f[f"trials/{tid:06d}/taxels"].shape == (400, 18)
        assert set(np.flatnonzero(status == 0)) == set(range(n_plan)) - set(before)

    # what the resume starts from: a trial whose commit mark was written before the kill, its in-place writes not
    # started, is replayed by the next opening (rigctl.storage.journal: the old file until then, never a torn one)
    from rigctl.storage.journal import journal_path, recover

    start = tmp_path / "start.h5"
    shutil.copyfile(out, start)
    if journal_path(out).exists():
        shutil.copyfile(journal_path(out), journal_path(start))
    recover(start)
    n_start = len(_complete(start))
    assert n_start - len(before) in (0, 1)

    # a different protocol is refused before the rig moves
    other = tmp_path / "other.toml"
    other.write_text(MANY.replace("[400]", "[300]"))
    refused = subprocess.run([*RIGCTL, "acquire", str(other), "--inprocess", "--out", str(out), "--resume"], env=env,
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0 and "protocol differs" in refused.stderr

    resumed = subprocess.run([*RIGCTL, "acquire", str(proto), "--inprocess", "--out", str(out), "--resume", "--quiet"],
                             env=env, capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0, resumed.stderr
    assert f"trials complete: {n_plan}/{n_plan}" in resumed.stdout
    assert f"recorded now: {n_plan - n_start}" in resumed.stdout
    with h5py.File(out, "r") as f:
        assert list(f["plan"]["status"][()]) == [1] * n_plan
        assert sorted(f["trials"]) == [f"{i:06d}" for i in range(n_plan)]  # one group per trial, none twice
        for tid, digest in before.items():  # trials finished before the kill were not recorded again
            assert _digest(f, tid) == digest
        starts = [f[f"trials/{i:06d}"].attrs["started_utc"] for i in range(n_plan)]
        assert starts == sorted(starts)  # recorded once each, in plan order across the two runs
    info = _info(out, env)
    assert info["totals"]["complete"] == n_plan and info["totals"]["dropped_frames"] == 0


def test_acquire_replays_a_recording_of_another_sensor(tmp_path):
    """`rigctl acquire --replay`: a 9-taxel 100 Hz session with its own labels streams through the simulated taxel
    board; the protocol mounts two of its textures and the new session keeps the sensor, the rate and the labels,
    and each recorded trial is a stretch of the mounted texture's recording."""
    from rigctl.core import SensorLayout, TextureSet, TrialData
    from rigctl.storage.session import SessionWriter, open_session

    layout = SensorLayout.grid(3, 3, 1, sample_rate_hz=100)
    textures = TextureSet.from_dict({"name": "lab", "textures": ["Linen weave", "HB3"]})
    rng = np.random.default_rng(3)
    source = {"Linen weave": rng.integers(0, 400, (400, 9)), "HB3": rng.integers(600, 1024, (400, 9))}
    src = tmp_path / "lab.h5"
    plan = [{"trial_id": i, "texture": t, "speed_mm_s": 40.0, "force_g": float("nan"), "duration_s": 4.0}
            for i, t in enumerate(source)]
    w = SessionWriter.create(src, plan=plan, layout=layout, textures=textures, protocol_format="none")
    w.write_trials([(i, TrialData(x, layout=layout)) for i, x in enumerate(source.values())])
    proto = tmp_path / "p.toml"
    proto.write_text('name = "replay"\ntextures = ["HB3", "Linen weave"]\nspeeds_mm_s = [120]\nforces_g = [500]\n'
                     'trials_per_condition = 1\nduration_s = 0.5\n\n[texture_set]\nname = "lab"\n'
                     'textures = ["Linen weave", "HB3"]\n')
    env = _env(tmp_path)
    out = tmp_path / "replayed.h5"
    same = subprocess.run([*RIGCTL, "acquire", str(proto), "--replay", str(src), "--out", str(src)],
                          capture_output=True, text=True, env=env, timeout=60)
    assert same.returncode == 2 and "is the recording being replayed" in same.stderr
    # replay = "continuous" (the recording plays on across trials) beside it, on a simulated rig of its own: both
    # wait on rigs paced to the wall clock
    continuous = tmp_path / "continuous.toml"
    continuous.write_text(proto.read_text().replace('duration_s = 0.5\n', 'duration_s = 0.5\nreplay = "continuous"\n'))
    out2 = tmp_path / "continuous.h5"
    beside = subprocess.Popen([*RIGCTL, "acquire", str(continuous), "--replay", str(src), "--out", str(out2), "--quiet"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**env, "RIGCTL_CONFIG": str(tmp_path / "rig2.json")})
    try:
        run = subprocess.run([*RIGCTL, "acquire", str(proto), "--replay", str(src), "--out", str(out), "--quiet"],
                             capture_output=True, text=True, env=env, timeout=180)
        _, beside_err = beside.communicate(timeout=180)
    finally:
        if beside.poll() is None:
            beside.kill()
    assert run.returncode == 0, run.stderr
    with open_session(out) as s:
        assert s.layout.n_channels == 9 and s.layout.sample_rate_hz == 100.0
        assert list(s.plan["texture"]) == ["HB3", "Linen weave"]
        # the plan rows hold the condition the samples were recorded under: the source's 40 mm/s, not the
        # protocol's 120 (what the encoder labels and speed-scales by); the source has no force: the plan's stays
        assert list(s.plan["speed_mm_s"]) == [40.0, 40.0] and list(s.plan["force_g"]) == [500.0, 500.0]
        assert all(s.trial_attrs(t)["planned_speed_mm_s"] == 120.0 for t in s.completed_ids())
        for tid in s.completed_ids():
            t = s.trial(tid)
            texture = str(s.plan["texture"][tid])
            assert t.taxels.shape == (50, 9)
            # the trial keeps the source's labels and says where its samples come from, which are exactly those
            a = t.attrs
            assert a["source_file"] == "lab.h5" and a["source_texture"] == texture
            assert int(a["source_trial_id"]) == list(source).index(texture)
            assert a["source_speed_mm_s"] == 40.0 and np.isnan(a["source_force_g"])
            first, last = int(a["source_first_sample"]), int(a["source_last_sample"])
            assert (first, last) == (0, 49)  # the trial starts with its source trial's first sample
            np.testing.assert_array_equal(t.taxels, source[texture][first:last + 1].astype(np.uint16))
    info = _info(out, env)
    assert info["trials"][0]["source"]["file"] == "lab.h5" and info["trials"][0]["source"]["trial_id"] == 1
    # replay = "continuous": the provenance still names every sample
    assert beside.returncode == 0, beside_err
    with open_session(out2) as s:
        for tid in s.completed_ids():
            a = s.trial_attrs(tid)
            pieces = json.loads(a["source_pieces"]) if "source_pieces" in a else [
                {k: a[k] for k in ("source_texture", "source_first_sample", "source_last_sample")}]
            rebuilt = np.concatenate([source[p["source_texture"]][p["source_first_sample"]:p["source_last_sample"] + 1]
                                      for p in pieces]).astype(np.uint16)
            np.testing.assert_array_equal(s.trial(tid).taxels, rebuilt)


def test_acquire_replays_a_fabricslide_folder_following_the_mounted_plate(tmp_path, fabricslide_dir):
    """`rigctl acquire --replay FOLDER`: each trial holds the mounted fabric's recording (a trial labelled Canvas
    holds Canvas samples, not the next file in name order), with the file, its setpoints and the sample range."""
    from rigctl.storage.fabricslide import read_recording, recording_adc
    from rigctl.storage.session import open_session

    proto = tmp_path / "p.toml"
    proto.write_text('name = "fabrics"\ntextures = ["Canvas", "BeigeCotton"]\nspeeds_mm_s = [100]\n'
                     'forces_g = [500]\ntrials_per_condition = 1\nduration_s = 0.3\n\n[texture_set]\n'
                     'name = "FabricSlide"\ntextures = ["BeigeCotton", "BrownCotton", "Canvas", "Linen"]\n')
    env = _env(tmp_path)
    out = tmp_path / "fabrics.h5"
    run = subprocess.run([*RIGCTL, "acquire", str(proto), "--replay", str(fabricslide_dir), "--out", str(out),
                          "--quiet"], capture_output=True, text=True, env=env, timeout=180)
    assert run.returncode == 0, run.stderr
    with open_session(out) as s:
        assert s.layout.n_channels == 16 and s.layout.sample_rate_hz == 1000.0
        for tid in s.completed_ids():
            t = s.trial(tid)
            texture, a = str(s.plan["texture"][tid]), t.attrs
            assert a["source_texture"] == texture and str(a["source_file"]).startswith(texture + "_")
            assert "source_pieces" not in a  # one recording per trial
            rec = recording_adc(read_recording(fabricslide_dir / "fabric" / str(a["source_file"])))
            first, last = int(a["source_first_sample"]), int(a["source_last_sample"])
            assert (first, last) == (0, 299)  # from the first sample of the mounted fabric's recording
            np.testing.assert_array_equal(t.taxels, rec[first:last + 1])


def test_a_calibration_for_another_sensor_is_not_copied_into_the_session(tmp_path, caplog):
    """The rig config holds an 18-taxel normalisation; a session of a 9-taxel sensor gets none (and a warning)
    instead of a failed session, and an 18-taxel session still gets it."""
    import logging

    from rigctl.acquisition.calibration import session_calibration_block

    cfg = {"taxel_normalisation": {"taxel_min": [100.0] * 18, "taxel_max": [900.0] * 18, "n_trials": 3},
           "loadcell": {"counts_per_g": 420.0, "mass_g": 500.0}}
    with caplog.at_level(logging.WARNING):
        nine = session_calibration_block(cfg, 9)
    assert "taxel_min" not in nine and nine["loadcell_counts_per_g"] == 420.0
    assert "has 18 taxels but the sensor has 9" in caplog.text
    assert session_calibration_block(cfg, 18)["taxel_min"].shape == (18,)
