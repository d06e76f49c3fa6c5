"""Every numeric option has a range checked before any work: absurd values exit 2 naming the option, in under a
second of CPU (in process, imports done; this process's and its reaped children's, not the wall clock's, which a
loaded machine stretches), and memory- or disk-sized work is estimated first and refused with the figure."""

from __future__ import annotations

import os

import click
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = tmp_path_factory.mktemp("ranges") / "s.h5"
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0, force_g=500.0, duration_s=0.1) for i in range(4)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 'r'") as w:
        for i in range(4):
            w.write_trial(i, TrialData(taxels=rng.integers(0, 1024, (100, 18)), seq=np.arange(100)))
    return path


def _cpu_s() -> float:
    """CPU seconds of this process (all its threads) and of the children it has reaped: the work a command did,
    which the wall clock also counts but with whatever else the machine ran meanwhile."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _refused(args, *needles, seconds=1.0):
    runner = CliRunner()
    runner.invoke(main, [str(a) for a in args])  # the command's imports done before the clock starts
    t0 = _cpu_s()
    r = runner.invoke(main, [str(a) for a in args])
    took = _cpu_s() - t0
    assert r.exit_code == 2, (args, r.exit_code, r.output)
    assert "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1 and r.output.startswith("Error: "), r.output  # one line
    for n in needles:
        assert n in r.output, (args, r.output)
    assert took < seconds, (args, took)
    return r


@pytest.mark.parametrize("args, option", [
    (["encode", "{s}", "--out", "{d}/e.h5", "--workers", "-3", "--scheduler", "local"], "--workers"),
    (["encode", "{s}", "--out", "{d}/e.h5", "--windows-unscaled", "1000000000000"], "--windows-unscaled"),
    (["encode", "{s}", "--out", "{d}/e.h5", "--batch", "0"], "--batch"),
    (["encode", "{s}", "--out", "{d}/e.h5", "--window-ms", "1e12"], "--window-ms"),
    (["encode", "{s}", "--out", "{d}/e.h5", "--windows-scaled", "-4"], "--windows-scaled"),
    (["sim", "dataset", "quick_check", "--out", "{d}/d.h5", "--trials-per-condition", "1000000000"],
     "--trials-per-condition"),
    (["sim", "dataset", "paper_dataset", "--out", "{d}/d.h5", "--trials-per-condition", "100000"],
     "--trials-per-condition"),
    (["sim", "dataset", "quick_check", "--out", "{d}/d.h5", "--seed", "-1"], "--seed"),
    (["sim", "dataset", "quick_check", "--out", "{d}/d.h5", "--workers", "-2"], "--workers"),
    (["sim", "dataset", "quick_check", "--out", "{d}/missing.h5", "--resume"], "--resume"),
    (["acquire", "quick_check", "--out", "{d}/missing.h5", "--resume"], "--resume"),
    (["acquire", "quick_check", "--out", "{d}/a.h5", "--seed", "-1"], "--seed"),
    (["analyze", "{s}", "--seed", "-1"], "--seed"),
    (["analyze", "{s}", "--repeats", "1000000000"], "--repeats"),
    (["analyze", "{s}", "--jobs", "0"], "--jobs"),
    (["import", "{s}", "--out", "{d}/i.h5", "--rate", "1e12"], "--rate"),
    (["import", "{s}", "--out", "{d}/i.h5", "--rate", "100", "--layout", "0x0x0"], "--layout"),
    (["import", "{s}", "--out", "{d}/i.h5", "--rate", "100", "--segment", "fixed:-1"], "--segment"),
    (["export", "nwb", "{s}", "--out", "{d}/x.nwb", "--variants", "nope", "--no-progress"], "--variants"),
    (["udev-rules", "--drum-serial", 'a"b'], "--drum-serial"),
    (["udev-rules", "--taxel-serial", ""], "--taxel-serial"),
])
def test_absurd_values_are_refused_at_once_naming_the_option(session, tmp_path, args, option):
    _refused([a.format(s=session, d=tmp_path) for a in args], option)
    assert not [p for p in tmp_path.iterdir() if p.suffix in (".h5", ".nwb", ".part")]


def test_an_empty_protocol_is_a_usage_error(tmp_path):
    proto = tmp_path / "empty.toml"
    proto.write_text('name = "empty"\ntextures = []\n')
    _refused(["acquire", proto, "--out", tmp_path / "a.h5"], "textures")
    _refused(["sim", "dataset", proto, "--out", tmp_path / "d.h5"], "textures")


def test_disk_and_memory_sized_work_is_refused_with_the_figure(session, tmp_path, monkeypatch):
    import rigctl.encoding.sizing as sizing
    import rigctl.storage.outputs as outputs

    monkeypatch.setattr(outputs, "free_bytes", lambda folder: 10_000)  # a nearly full disk
    r = _refused(["encode", session, "--out", tmp_path / "e.h5", "--windows-unscaled", "100000"],
                 "--windows-unscaled 100000", "the encoded file would be about")
    assert "MB" in r.output or "GB" in r.output
    _refused(["sim", "dataset", "paper_dataset", "--out", tmp_path / "d.h5"], "needs about 4.4")
    monkeypatch.setattr(outputs, "free_bytes", lambda folder: 10 ** 15)
    monkeypatch.setattr(sizing, "available_memory_bytes", lambda: 10_000)  # 10 kB of memory left
    _refused(["encode", session, "--out", tmp_path / "e.h5", "--batch", "100"], "--batch 100",
             "of memory", "available")


#: what a user might type into any numeric option: none of it is a usable number of anything
NOT_USABLE = ("nan", "NaN", "inf", "-inf", "1e400", "-1e400", "99999999999999999999", "-99999999999999999999", "x")


def test_every_numeric_option_of_every_command_has_a_finite_range(cli_commands, tmp_path, monkeypatch):
    """Walks ``rigctl --help`` recursively: each integer or float option has both bounds, and each refuses what is
    not a usable number (NaN passed click's FloatRange: every comparison with it is false) with exit 2 naming it.
    The option comes first on the line, so click parses it before any argument and nothing runs."""
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))  # were a value let through: never $HOME's
    runner = CliRunner()
    seen = []
    for words, cmd in cli_commands:
        for param in cmd.params:
            if not isinstance(param.type, (click.types.IntParamType, click.types.FloatParamType)):
                continue
            name = param.opts[0]
            seen.append(f"{' '.join(words)} {name}")
            assert getattr(param.type, "min", None) is not None and getattr(param.type, "max", None) is not None, (
                words, name, param.type)
            for value in NOT_USABLE:
                r = runner.invoke(main, [*words, name, value])
                assert r.exit_code == 2 and name in r.output and "Traceback" not in r.output, (words, name, value,
                                                                                               r.output)
    assert len(seen) >= 20, seen  # the walk found the commands' options


def test_the_exit_statuses_are_documented():
    """What the tests of every command hold them to (0, 1, 2: test_cli_property; 2 for usage errors: above) is what
    ``rigctl --help`` promises."""
    r = CliRunner().invoke(main, ["--help"])
    text = " ".join(r.output.split())
    assert "Exit status: 0 done; 1 an error" in text and "2 a usage error" in text, text
