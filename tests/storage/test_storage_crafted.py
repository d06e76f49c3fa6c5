"""One validator for every command (issue 36 part 4): a crafted-file generator puts every kind of damage the
reviewers found into one schema-4 session (13 kinds of damage inside a trial's group, a trial id listed twice in
``/recording/index``, NaN / inf readings, a trial declaring 2**34 samples of a dataset declared (2**34, 18) with
nothing written), one kind per trial beside whole trials; ``info``, ``encode``, ``export nwb`` and ``analyze
--encode`` must each exclude exactly the damaged trials, name each with the same reason, and use every whole one
(on main before this, info and export refused the whole file and encode/analyze used every trial).

Cheap by construction: one small file (200 samples a trial) and each command run once, in-process (CliRunner).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.encoded import open_encoded
from rigctl.storage.nwb import read_nwb_summary
from rigctl.storage.session import SessionWriter, TrialData, open_session
from rigctl.storage.validate import KEEP_HINT, usable_trials

N = 200  # samples a trial (0.2 s at 1 kHz)
BIG = 2 ** 34


def _replace(g: h5py.Group, name: str, data: np.ndarray) -> None:
    del g[name]
    g.create_dataset(name, data=data)


def _group(f: h5py.File, tid: int) -> h5py.Group:
    return f[f"trials/{tid:06d}"]


def _index_set(f: h5py.File, tid: int, **values: int) -> None:
    idx = f["recording/index"][()]
    for k, v in values.items():
        idx[k][idx["trial_id"] == tid] = v
    f["recording/index"][...] = idx


def _rows(f: h5py.File, tid: int, prefix: str = "sample") -> slice:
    r = f["recording/index"][()]
    r = r[r["trial_id"] == tid][0]
    n = r["n_samples" if prefix == "sample" else f"n_{prefix}"]
    return slice(int(r[f"{prefix}_start"]), int(r[f"{prefix}_start"] + n))


def _unopenable(f: h5py.File, tid: int) -> None:
    del f[f"trials/{tid:06d}"]
    f[f"trials/{tid:06d}"] = h5py.SoftLink("/nowhere/at/all")  # listed under /trials, opens as nothing


def _declared_2_34(f: h5py.File, tid: int) -> None:
    """The per-sample arrays declared 2**34 rows long (nothing written past the real ones), ``tid`` pointing at the
    declared rows: a reader that allocates what is declared needs 618 GB."""
    rec = f["recording"]
    for name in ("taxels", "seq", "flags", "host_time_s"):
        rec[name].resize((BIG,) + rec[name].shape[1:])
    _index_set(f, tid, sample_start=BIG // 2, n_samples=BIG // 2)


#: damage kind -> (what it does to trial t, words of the reason every command must give)
CRAFTS = {
    # the 13 kinds of damage inside one trial's group
    "taxels float32": (lambda f, t: _replace(_group(f, t), "taxels", _group(f, t)["taxels"][()].astype("f4")),
                       "taxels are float32, not integer ADC counts"),
    "taxels 17 channels": (lambda f, t: _replace(_group(f, t), "taxels", _group(f, t)["taxels"][()][:, :17]),
                           "not (samples, 18) for the sensor"),
    "taxels 1-d": (lambda f, t: _replace(_group(f, t), "taxels", np.zeros(N, np.uint16)),
                   f"taxels are ({N},), not (samples, 18)"),
    "taxels shorter": (lambda f, t: _replace(_group(f, t), "taxels", _group(f, t)["taxels"][()][:150]),
                       f"its taxels view holds 150 samples, /recording/index gives it {N}"),
    "taxels missing": (lambda f, t: _group(f, t).__delitem__("taxels"), "taxels is missing"),
    "taxels a group": (lambda f, t: (_group(f, t).__delitem__("taxels"), _group(f, t).create_group("taxels")),
                       "taxels cannot be opened as a dataset"),
    "n_samples -5": (lambda f, t: _group(f, t).attrs.__setitem__("n_samples", -5),
                     f"its n_samples attribute says -5, /recording/index gives it {N} samples"),
    "n_samples 2**62": (lambda f, t: _group(f, t).attrs.__setitem__("n_samples", 2 ** 62),
                        f"its n_samples attribute says {2 ** 62}, /recording/index gives it {N} samples"),
    "n_samples text": (lambda f, t: _group(f, t).attrs.__setitem__("n_samples", "two hundred"),
                       "its n_samples attribute says 'two hundred'"),
    "dropped_frames many": (lambda f, t: _group(f, t).attrs.__setitem__("dropped_frames", "many"),
                            "its dropped_frames attribute is 'many', not a count"),
    "crc_errors -1": (lambda f, t: _group(f, t).attrs.__setitem__("crc_errors", -1),
                      "its crc_errors attribute is -1, not a count"),
    "dropped_frames disagrees": (lambda f, t: _group(f, t).attrs.__setitem__("dropped_frames", 7),
                                 "its dropped_frames attribute says 7, /recording/index says 0"),
    "group unopenable": (_unopenable, "its group /trials/"),
    # beside the groups
    "duplicate trial id": (lambda f, t: _index_set(f, t + 1, trial_id=t),
                           "/recording/index lists it 2 times"),
    # recorded so (written by the writer: an edit after writing is a change the seal names, issue 77 item 6)
    "NaN force": (None, "non-finite readings: 4 NaN in force_g" + KEEP_HINT),
    "inf speed": (None, "non-finite readings: 1 inf in speed_mm_s" + KEEP_HINT),
    "declared 2**34": (_declared_2_34, "it holds 8589934592 samples, its plan asks 0.2 s"),
}


def _trial(rng: np.random.Generator) -> TrialData:
    start = int(rng.integers(0, 65536))
    return TrialData(taxels=rng.integers(100, 900, (N, 18)), seq=(start + np.arange(N)) % 65536,
                     force_g=rng.normal(500, 2, 4), force_time_s=np.arange(4) * 0.05,
                     speed_mm_s=rng.normal(80, 1, 4), speed_time_s=np.arange(4) * 0.05)


#: damage kind -> what the trial held when it was recorded (its data, changed before the writer takes it)
RECORDED = {"NaN force": lambda d: d.force_g.__setitem__(slice(None), np.nan),
            "inf speed": lambda d: d.speed_mm_s.__setitem__(0, np.inf)}


def craft_session(path: Path, kinds: list[str], n_whole: int = 16) -> dict[int, str]:
    """Write a schema-4 session with one trial per damage kind of ``kinds`` (each followed by a spare whole trial,
    which "duplicate trial id" takes the row of) and ``n_whole`` more whole trials (two textures), then damage it;
    returns damaged trial id -> the reason's words (the duplicate's victim: no index row)."""
    rng = np.random.default_rng(11)
    n = 2 * len(kinds) + n_whole
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(n)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 'crafted'", compression=None,
                              durable=False) as w:
        trials = [_trial(rng) for i in range(n)]
        for k, kind in enumerate(kinds):
            if kind in RECORDED:
                RECORDED[kind](trials[2 * k])
        w.write_trials(enumerate(trials))
    want = {}
    with h5py.File(path, "r+") as f:
        for k, kind in enumerate(kinds):
            damage, words = CRAFTS[kind]
            if damage is not None:
                damage(f, 2 * k)
            want[2 * k] = words
            if kind == "duplicate trial id":
                want[2 * k + 1] = "it is marked complete but /recording/index has no row for it"
    return want


def _said(caplog: pytest.LogCaptureFixture, tid: int) -> str:
    """The reason a command logged for trial ``tid`` (the validator logs one line per excluded trial)."""
    lines = [r.getMessage() for r in caplog.records if f": trial {tid} is damaged: " in r.getMessage()]
    return lines[-1].split(f": trial {tid} is damaged: ", 1)[1].removesuffix("; its data are not used (excluded)") \
        if lines else ""


@pytest.fixture(scope="module")
def crafted(tmp_path_factory) -> tuple[Path, dict[int, str]]:
    path = tmp_path_factory.mktemp("crafted") / "crafted.h5"
    return path, craft_session(path, sorted(CRAFTS))


def test_every_command_excludes_the_same_damaged_trials_for_the_same_reason(crafted, tmp_path, caplog):
    path, want = crafted
    with open_session(path) as s:
        n_trials = len(s.plan)
        report = usable_trials(s)
    assert sorted(report.excluded) == sorted(want), report.excluded
    for tid, words in want.items():
        assert words in report.excluded[tid], (tid, report.excluded[tid])
    whole = [t for t in range(n_trials) if t not in want]
    assert report.ids == whole
    runner = CliRunner()
    left_out, said = {}, {}

    def run(name: str, args: list[str]) -> str:
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="rigctl"):
            t0 = time.perf_counter()
            r = runner.invoke(main, args)
            took = time.perf_counter() - t0
        assert r.exit_code == 0, (name, r.output)
        assert "internal error" not in r.output and "Traceback" not in r.output
        said[name] = {t: _said(caplog, t) for t in want}
        print(f"{name}: {took:.2f} s")
        return r.stdout

    info = json.loads(run("info", ["info", str(path), "--json"]))
    left_out["info"] = [t["trial_id"] for t in info["trials"] if t["status"] != "complete"]
    assert {t["trial_id"]: t["error"] for t in info["trials"] if t["status"] == "excluded"} == report.excluded
    assert info["totals"]["excluded"] == len(want)

    enc = tmp_path / "c.enc.h5"
    run("encode", ["encode", str(path), "--out", str(enc), "--no-progress", "--variant", "original"])
    with open_encoded(enc) as e:
        left_out["encode"] = sorted(set(range(n_trials)) - {int(t) for t in e.trials["trial_id"]})

    nwb = tmp_path / "c.nwb"
    run("export nwb", ["export", "nwb", str(path), "--out", str(nwb), "--no-progress"])
    left_out["export nwb"] = sorted(set(range(n_trials)) - {int(t) for t in read_nwb_summary(nwb)[1]["trial_id"]})

    out = run("analyze", ["analyze", str(path), "--encode", "--task", "textures", "--repeats", "1", "--pcs", "1-2",
                          "--per-texture", "4", "--variants", "original", "--json", "--no-progress"])
    assert json.loads(out)
    left_out["analyze"] = sorted(t for t, why in said["analyze"].items() if why)

    assert left_out == dict.fromkeys(left_out, sorted(want))
    for command, reasons in said.items():  # every excluded trial named, with the validator's reason
        assert reasons == report.excluded, (command, reasons)


def test_nonfinite_readings_are_kept_and_flagged_with_keep_nonfinite(crafted, tmp_path):
    path, want = crafted
    nonfinite = {t for t, words in want.items() if "non-finite" in words}
    runner = CliRunner()
    r = runner.invoke(main, ["info", str(path), "--json", "--keep-nonfinite"])
    assert r.exit_code == 0, r.output
    rows = {t["trial_id"]: t for t in json.loads(r.stdout)["trials"]}
    for t in nonfinite:
        assert rows[t]["status"] == "complete" and "NaN in force_g" in rows[t]["nonfinite"] or \
            "inf in speed_mm_s" in rows[t]["nonfinite"], rows[t]
    assert {t for t, row in rows.items() if row["status"] == "excluded"} == set(want) - nonfinite
    nwb = tmp_path / "k.nwb"
    r = runner.invoke(main, ["export", "nwb", str(path), "--out", str(nwb), "--no-progress", "--keep-nonfinite"])
    assert r.exit_code == 0, r.output
    assert nonfinite <= {int(t) for t in read_nwb_summary(nwb)[1]["trial_id"]}


def test_a_file_whose_only_trial_is_declared_2_34_samples_is_refused_at_once(tmp_path):
    """Nothing is allocated from a declared size: the recording arrays declared (2**34, 18) with one trial's 200
    rows written, its index claiming 10**8 of them (a 27.8-hour trial, which its plan asks for): info lists the trial
    excluded for its size against the file's, encode and export refuse the file (no usable trial: exit 1, one line,
    no internal error), each in well under a second of work."""
    path = tmp_path / "declared.h5"
    plan = [dict(trial_id=0, texture="A", speed_mm_s=80.0, force_g=500.0, duration_s=80_000.0)]
    with SessionWriter.create(path, plan=plan, protocol_source="x", compression=None, durable=False) as w:
        w.write_trial(0, _trial(np.random.default_rng(0)))
    with h5py.File(path, "r+") as f:
        _declared_2_34(f, 0)
        _index_set(f, 0, sample_start=0, n_samples=10 ** 8)
    runner = CliRunner()
    for args, code in ((["info", str(path), "--json"], 0),
                       (["encode", str(path), "--out", str(tmp_path / "d.enc.h5"), "--no-progress", "--windows-unscaled", "2"],
                        1),
                       (["export", "nwb", str(path), "--out", str(tmp_path / "d.nwb"), "--no-progress"], 1)):
        t0 = time.process_time()
        r = runner.invoke(main, args)
        took = time.process_time() - t0
        assert r.exit_code == code, (args, r.output)
        assert "internal error" not in r.output and "MemoryError" not in r.output, r.output
        assert "it declares 100000000 samples (3.60 GB of taxels), more than this" in r.output, r.output
        assert took < 5, (args, took)  # CPU time, not wall: generous for a loaded machine (measured ~0.1 s)
        print(f"{args[0]}: {took:.2f} CPU-s")
    assert not list(tmp_path.glob("d.*"))
