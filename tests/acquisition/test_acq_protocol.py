"""Protocol files: the shipped ones plan what the paper did; bad files are refused naming the key and its line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from rigctl.acquisition.protocol import ProtocolError, ScriptProtocol, load_protocol, parse_protocol

REPO = Path(__file__).resolve().parents[2]
PROTOCOLS = REPO / "protocols"

GOOD = """\
name = "t"
textures = ["A", "B"]
speeds_mm_s = [40, 120]
forces_g = [250, 1000]
trials_per_condition = 3
"""


def test_paper_dataset_is_the_papers_24000_trials():
    p = load_protocol(PROTOCOLS / "paper_dataset.toml")
    plan = p.plan()
    assert len(plan) == 16 * 5 * 3 * 100
    assert sorted({t.texture for t in plan}) == list("ABCDEFGHIJKLMNOP")
    assert sorted({t.speed_mm_s for t in plan}) == [40, 60, 80, 100, 120]
    assert sorted({t.force_g for t in plan}) == [250, 500, 1000]
    # 240 mm of travel: 6, 4, 3, 2.4 and 2 s (Materials and Methods)
    assert {t.speed_mm_s: round(t.duration_s, 6) for t in plan} == {40: 6, 60: 4, 80: 3, 100: 2.4, 120: 2}
    # blocked: one plate change per texture
    changes = sum(a.texture != b.texture for a, b in zip(plan, plan[1:]))
    assert changes == 15
    assert [t.trial_id for t in plan] == list(range(len(plan)))


def test_realtime_profiles_ramps_and_constants():
    p = load_protocol(PROTOCOLS / "realtime_profiles.toml")
    plan = p.plan()
    assert sorted({t.texture for t in plan}) == ["A", "B", "D", "L", "N"]
    by_profile = {t.profile: t for t in plan}
    assert set(by_profile) == {"slow", "medium", "fast", "slow-to-fast", "fast-to-slow"}
    up, down = by_profile["slow-to-fast"], by_profile["fast-to-slow"]
    assert up.is_ramp and (up.ramp_start_mm_s, up.ramp_end_mm_s) == (40, 120)
    assert down.is_ramp and (down.ramp_start_mm_s, down.ramp_end_mm_s) == (120, 40)
    # a ramp covers the travel (200 mm) at its mean speed
    assert math.isclose(up.duration_s * (40 + 120) / 2, 200)
    assert not by_profile["slow"].is_ramp and by_profile["slow"].duration_s == 5
    assert len(plan) == 5 * 5 * 4


def test_quick_check_is_short():
    p = load_protocol(PROTOCOLS / "quick_check.toml")
    assert sum(t.duration_s for t in p.plan()) <= 20
    assert p.estimated_duration_s() < 60


def test_orders():
    blocked = parse_protocol(GOOD).plan()
    assert [t.texture for t in blocked] == ["A"] * 12 + ["B"] * 12
    inter = parse_protocol(GOOD + 'order = "interleaved"\n').plan()
    assert [t.texture for t in inter[:8]] == ["A"] * 4 + ["B"] * 4 and [t.repeat for t in inter[:8]] == [0] * 8
    r1 = parse_protocol(GOOD + 'order = "random"\nseed = 1\n').plan()
    r1b = parse_protocol(GOOD + 'order = "random"\nseed = 1\n').plan()
    r2 = parse_protocol(GOOD + 'order = "random"\nseed = 2\n').plan()
    key = [(t.texture, t.speed_mm_s, t.force_g, t.repeat) for t in r1]
    assert key == [(t.texture, t.speed_mm_s, t.force_g, t.repeat) for t in r1b]
    assert key != [(t.texture, t.speed_mm_s, t.force_g, t.repeat) for t in r2]
    assert sorted(key) == sorted((t.texture, t.speed_mm_s, t.force_g, t.repeat) for t in blocked)
    assert parse_protocol(GOOD + "duration_s = 1.5\n").plan()[0].duration_s == 1.5


BAD = [
    # (text, line, key, words in the message)
    (GOOD.replace("[40, 120]", "[40, 200]"), 3, "speeds_mm_s", "200"),
    (GOOD.replace("[250, 1000]", "[250, 0]"), 4, "forces_g", "rig limits"),
    (GOOD.replace("[250, 1000]", "[250, 1600]"), 4, "forces_g", "1500"),
    (GOOD.replace('["A", "B"]', '["A", "Q"]'), 2, "textures", "'Q'"),
    (GOOD + "\nspeed = 3\n", 7, "speed", "unknown key"),
    (GOOD.replace("trials_per_condition = 3", "trials_per_condition = 2.5"), 5, "trials_per_condition", "integer"),
    (GOOD + 'order = "sorted"\n', 6, "order", "sorted"),
    (GOOD + "\n\n[settle]\nforce_timeout_s = -1\n", 9, "settle.force_timeout_s", "-1"),
    (GOOD + "\n[settle]\nforce_timeout = 3\n", 8, "settle.force_timeout", "unknown key"),
    (GOOD.replace('name = "t"\n', ""), None, "name", "required"),
    (GOOD + "travel_mm = 240\nduration_s = 2\n", 7, "duration_s", "either"),
    (
        GOOD + '\n[[profiles]]\nname = "up"\nkind = "ramp"\nstart_mm_s = 40\nend_mm_s = 160\n\n'
        '[[profiles]]\nname = "down"\nkind = "ramp"\nstart_mm_s = 120\nend_mm_s = 40\n',
        11, "profiles[0].end_mm_s", "160",
    ),
    (
        GOOD + '\n[[profiles]]\nname = "up"\nkind = "ramp"\nstart_mm_s = 40\nend_mm_s = 60\n\n'
        '[[profiles]]\nname = "down"\nkind = "wobble"\nstart_mm_s = 120\nend_mm_s = 40\n',
        15, "profiles[1].kind", "wobble",
    ),
    (GOOD.replace("[40, 120]", "[0.001]"), 3, "speeds_mm_s", "longer than"),  # a 66-hour trial
]


@pytest.mark.parametrize("text,line,key,words", BAD, ids=[b[2] + "-" + str(i) for i, b in enumerate(BAD)])
def test_bad_protocol_names_key_and_line(tmp_path, text, line, key, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ProtocolError) as err:
        load_protocol(path)
    e = err.value
    assert e.key == key
    assert e.line == line
    assert words in str(e)
    assert str(e).startswith(f"{path}:{line if line is not None else '?'}: {key}: ")
    if line is not None:  # the reported line really holds the key (or its [[table]] header)
        src_line = text.splitlines()[line - 1]
        assert key.split(".")[-1].split("[")[0] in src_line or src_line.startswith("[[")


def test_toml_syntax_error_carries_its_line(tmp_path):
    path = tmp_path / "syntax.toml"
    path.write_text(GOOD + "forces_g = [250,\n")
    with pytest.raises(ProtocolError) as err:
        load_protocol(path)
    assert err.value.line is not None and err.value.line >= 6
    assert "syntax" in str(err.value)


def test_script_protocols(tmp_path):
    p = load_protocol(PROTOCOLS / "example_script.py")
    assert isinstance(p, ScriptProtocol) and p.name == "force_sweep_example" and callable(p.plan_function)
    assert p.max_trials == 6
    bad = tmp_path / "bad.py"
    bad.write_text("x = 1\n\ndef run(rig, session)\n    pass\n")
    with pytest.raises(ProtocolError) as err:
        load_protocol(bad)
    assert err.value.line == 3
    norun = tmp_path / "norun.py"
    norun.write_text("def go(rig, session):\n    pass\n")
    with pytest.raises(ProtocolError, match=r"must define plan\(ctx\)"):
        load_protocol(norun)
    old_form = tmp_path / "old.py"
    old_form.write_text("def run(rig, session):\n    pass\n")
    with pytest.raises(ProtocolError, match=r"run\(rig, session\) protocols are gone: write plan\(ctx\)"):
        load_protocol(old_form)


def test_replay_mode_key(tmp_path):
    """`replay = "continuous"` lets a replay rig play the recording on across trials; the default starts each trial
    at the recording's next trial; anything else is refused with the key named."""
    from rigctl.acquisition.protocol import ProtocolError, load_protocol

    base = 'name = "r"\ntextures = ["A"]\nspeeds_mm_s = [40]\nforces_g = [500]\nduration_s = 1.0\n'
    p = tmp_path / "p.toml"
    p.write_text(base)
    assert load_protocol(p).replay == "trials"
    p.write_text(base + 'replay = "continuous"\n')
    assert load_protocol(p).replay == "continuous"
    p.write_text(base + 'replay = "loop"\n')
    with pytest.raises(ProtocolError, match="replay"):
        load_protocol(p)
