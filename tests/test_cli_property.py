"""Property-based test (hypothesis) of the offline commands: random values of every numeric option (negative,
zero, huge, non-finite, not numbers at all) on small real inputs. Whatever the values: no traceback, exit status
0, 1 or 2 only, nothing left in the output folder when the command failed, no input changed.

The commands run in this process (click's CliRunner: imports paid once) on a 4-trial session, its encoded file and
a CSV recording; ``rigctl acquire``, ``sim``, ``gui``, ``firmware`` and ``doctor`` drive a rig, a display or a
compiler and are covered by their own tests. Deterministic (``derandomize``) and modest (``RIGCTL_PROPERTY_EXAMPLES``,
default 5 per command) so that it runs in seconds on an idle machine.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData

N_EXAMPLES = int(os.environ.get("RIGCTL_PROPERTY_EXAMPLES", "5"))
PROPERTY = settings(max_examples=N_EXAMPLES, deadline=None, database=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

#: any numeric text a user might type
NUMBER = st.one_of(st.integers(-10**13, 10**13).map(str), st.sampled_from(["0", "-1", "1", "2", "1e12", "-1e-9", "nan",
                                                                            "inf", "-inf", "1.5", "abc", ""]),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr))
SMALL = st.one_of(st.integers(-3, 4).map(str), NUMBER)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("property_inputs")
    rng = np.random.default_rng(2)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=[40.0, 80.0][i // 2 % 2], force_g=500.0,
                 duration_s=0.1) for i in range(8)]
    session = d / "s.h5"
    with SessionWriter.create(session, plan=plan, protocol_source="name = 'p'") as w:
        for i in range(8):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (100, 18)), seq=np.arange(100),
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    encoded = d / "s.enc.h5"
    r = CliRunner().invoke(main, ["encode", str(session), "--out", str(encoded), "--quiet"])
    assert r.exit_code == 0, r.output
    csv = d / "A__1.csv"
    np.savetxt(csv, rng.integers(0, 1024, (300, 9)), delimiter=",", fmt="%d")
    return {"session": session, "encoded": encoded, "csv": csv}


def _digests(paths):
    return {p: hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths}


def _check(inputs, out_dir: Path, args: list[str]):
    before_inputs = _digests(inputs.values())
    before = set(os.listdir(out_dir))
    r = CliRunner().invoke(main, args)
    text = r.output
    assert r.exit_code in (0, 1, 2), (args, r.exit_code, text)
    assert "Traceback" not in text and "internal error" not in text, (args, text)
    assert r.exception is None or isinstance(r.exception, SystemExit), (args, repr(r.exception))
    if r.exit_code != 0:
        assert set(os.listdir(out_dir)) == before, (args, sorted(set(os.listdir(out_dir)) - before), text)
    assert _digests(inputs.values()) == before_inputs, args
    for name in set(os.listdir(out_dir)) - before:  # a success: clear it for the next example
        p = out_dir / name
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return r


def _opts(draw_pairs):
    args = []
    for opt, value in draw_pairs:
        if value is not None:
            args += [opt, value]
    return args


def _maybe(strategy):
    return st.one_of(st.none(), strategy)


@given(data=st.data())
@PROPERTY
def test_encode(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--workers", SMALL), ("--batch", SMALL), ("--window-ms", NUMBER), ("--windows-unscaled", SMALL),
        ("--windows-scaled", st.one_of(SMALL, st.just("longest"))))]
    if dict(opts).get("--workers") is not None:
        opts.append(("--scheduler", "local"))
    _check(inputs, tmp_path, ["encode", str(inputs["session"]), "--out", str(tmp_path / "e.h5"), "--quiet",
                              "--variant", "original", *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_sim_dataset(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--trials-per-condition", st.one_of(st.sampled_from(["1", "0", "-1", "1000000000", "100000"]), NUMBER)),
        ("--seed", NUMBER), ("--workers", st.sampled_from(["0", "-2", "100000", "x"])))]
    if dict(opts).get("--workers") is None:
        opts.append(("--workers", "0"))
    _check(inputs, tmp_path, ["sim", "dataset", "quick_check", "--out", str(tmp_path / "d.h5"), "--quiet",
                              *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_analyze(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--repeats", SMALL), ("--per-texture", SMALL), ("--seed", NUMBER), ("--table-pcs", SMALL),
        ("--jobs", SMALL), ("--threads", SMALL), ("--channels", SMALL),
        ("--pcs", st.one_of(st.sampled_from(["1-2", "0-3", "3-1", "1-1000000000", "a-b", "-1"]), SMALL)))]
    _check(inputs, tmp_path, ["analyze", str(inputs["encoded"]), "--task", "textures", "--variants", "original",
                              "--csv", str(tmp_path / "c.csv"), *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_import(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--channels", SMALL), ("--resample", NUMBER), ("--volts-ref", NUMBER), ("--bits", SMALL),
        ("--layout", st.sampled_from(["3x3x1", "0x0x0", "3x3", "-1x2", "1e9x1e9x1", "x"])),
        ("--segment", st.sampled_from(["fixed:0.1", "fixed:-1", "fixed:1e12", "threshold:nan", "cycles:0", "bogus"])))]
    rate = data.draw(st.one_of(st.just("1000"), NUMBER), label="--rate")
    _check(inputs, tmp_path, ["import", str(inputs["csv"]), "--out", str(tmp_path / "i.h5"), "--rate", rate,
                              "--texture", "A", "--quiet", *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_info_export_and_protocols(inputs, tmp_path, data):
    variants = data.draw(_maybe(st.sampled_from(["original", "nope", "original,force_scaled", ",", "speed_scaled"])))
    _check(inputs, tmp_path, ["export", "nwb", str(inputs["session"]), "--encoded", str(inputs["encoded"]),
                              "--out", str(tmp_path / "x.nwb"), "--no-progress",
                              *(["--variants", variants] if variants is not None else [])])
    _check(inputs, tmp_path, ["info", str(inputs["session"]), *(["--json"] if data.draw(st.booleans()) else [])])
    _check(inputs, tmp_path, ["protocols"])
