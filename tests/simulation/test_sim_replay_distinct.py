"""Replay never repeats or rewrites (issue 52 item 7): each recorded trial gets a source trial of its own (the one
streaming during the settle is not used up), a plan the source cannot serve is refused before it starts naming the
shortfall, and a texture the source has nothing of is a refusal, not a substitution."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from rigctl.core import SensorLayout, TextureSet, TrialData
from rigctl.simulation.replay import ReplayShortfall, SessionReplay
from rigctl.storage.session import SessionWriter

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)


def _source(path, textures=("A", "A", "B", "B")):
    layout = SensorLayout.grid(3, 3, 1, sample_rate_hz=100)
    plan = [{"trial_id": i, "texture": t, "speed_mm_s": 40.0, "force_g": 500.0, "duration_s": 1.0}
            for i, t in enumerate(textures)]
    w = SessionWriter.create(path, plan=plan, layout=layout, textures=TextureSet.from_dict(
        {"name": "lab", "textures": sorted(set(textures))}), protocol_format="none")
    # trial i holds the value 100 * (i + 1) everywhere: which source trial a stretch came from is its value
    w.write_trials([(i, TrialData(np.full((100, 9), 100 * (i + 1)), layout=layout)) for i in range(len(plan))])
    w.close()
    return path


def test_each_recorded_trial_gets_a_source_trial_of_its_own(tmp_path):
    """Before: the settle streamed source trial 0, begin_trial skipped to 1, the next trial wrapped to 0, ... (the
    same source trials recorded again and again). Now the one streaming is used from its first sample."""
    replay = SessionReplay(_source(tmp_path / "src.h5"))
    got = []
    for texture in ("A", "A"):
        replay.mount(texture)
        replay.read(30)  # the settle: streams, uses nothing up
        replay.begin_trial()
        got.append(int(replay.read(50)[0, 0]) // 100 - 1)
        replay.read(200)  # past the trial: the stream runs on between trials
    assert got == [0, 1]
    replay.mount("B")
    replay.begin_trial()
    assert int(replay.read(1)[0, 0]) == 300
    with pytest.raises(ReplayShortfall, match="every source trial of A was recorded once already"):
        replay.mount("A")
        replay.begin_trial()


def test_a_plan_the_source_cannot_serve_is_refused_naming_the_shortfall(tmp_path):
    replay = SessionReplay(_source(tmp_path / "src.h5"))
    replay.check_plan(["A", "B", "A", "B"])
    with pytest.raises(ReplayShortfall, match=r"A: 3 planned, 2 in the source") as err:
        replay.check_plan(["A", "A", "A", "B"])
    assert "\n" not in str(err.value)
    with pytest.raises(ReplayShortfall, match=r"has no trial of texture 'L' \(it has: A, B\)"):
        replay.check_plan(["A", "L", "B"])
    with pytest.raises(KeyError):
        replay.mount("L")
    with pytest.raises(ReplayShortfall, match="a trial of L would record another texture's samples"):
        replay.begin_trial()


def test_acquire_refuses_a_missing_texture_before_recording(tmp_path):
    """`acquire --replay` with a protocol mounting a texture the recording lacks: refused before the first trial,
    naming it (it rewrote the plan's textures with one stderr line, exit 0); nothing written."""
    src = _source(tmp_path / "src.h5")
    proto = tmp_path / "p.toml"
    proto.write_text('name = "p"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [500]\n'
                     'trials_per_condition = 1\nduration_s = 0.5\n\n[texture_set]\nname = "lab"\n'
                     'textures = ["A", "B", "L"]\n')
    env = {"RIGCTL_CONFIG": str(tmp_path / "rig.json")}
    import os

    r = subprocess.run([*RIGCTL, "acquire", str(proto), "--replay", str(src), "--out", str(tmp_path / "o.h5")],
                       capture_output=True, text=True, env={**os.environ, **env}, timeout=180)
    assert r.returncode == 1 and "has no trial of texture 'L'" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "o.h5").exists()
