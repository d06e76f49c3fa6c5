"""The one trial validator (rigctl.storage.validate): crafted damaged files are excluded identically by ``info``,
``encode``, ``analyze`` and ``export nwb``, with the same reason, counted in each summary.

The command-line checks come first and import only the session writer, the CLI and the readers, so that they run
unchanged against an older rigctl (issue 24: on 78d85b9 ``info`` refused some of these trials while ``encode`` and
``analyze`` used them all)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.encoded import open_encoded
from rigctl.storage.nwb import read_nwb_summary
from rigctl.storage.session import SessionWriter, TrialData, open_session

N_TRIALS, N = 20, 200  # 0.2 s at 1 kHz


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("validate") / "base.h5"
    rng = np.random.default_rng(5)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=[40.0, 80.0][i // 2 % 2], force_g=500.0,
                 duration_s=N / 1000.0) for i in range(N_TRIALS)]
    # schema 3 (a group of datasets per trial, which the crafts below edit); schema 4: test_storage_recording.py
    with SessionWriter.create(path, plan=plan, protocol_source="name = 'v'", schema_version=3) as w:
        for i in range(N_TRIALS):
            start = int(rng.integers(0, 65536))
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (N, 18)), seq=(start + np.arange(N)) % 65536,
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    return path


def _replace(g: h5py.Group, name: str, data: np.ndarray) -> None:
    del g[name]
    g.create_dataset(name, data=data)


def _group(f, tid):
    names = sorted(f["trials"])
    return f["trials"][names[tid]]


def _gap(f, tid):  # a 7-frame gap in the seq column, dropped_frames still 0
    g = _group(f, tid)
    seq = g["seq"][()].astype(np.int64)
    seq[100:] += 7
    _replace(g, "seq", (seq % 65536).astype(np.uint16))


def _copy(f, tid):  # a byte copy of trial 0 (which stays in)
    _replace(_group(f, tid), "taxels", _group(f, 0)["taxels"][()])


def _crc(f, tid):
    _group(f, tid).attrs["crc_errors"] = 2 ** 62


def _duration(f, tid):
    plan = f["plan"][()]
    plan["duration_s"][tid] = 1e9
    f["plan"][...] = plan


def _short(f, tid):  # a 10-sample trial in a 0.2 s plan
    g = _group(f, tid)
    for k in ("taxels", "seq", "flags", "host_time_s"):
        _replace(g, k, g[k][()][:10])
    g.attrs["n_samples"] = 10


def _negative(f, tid):  # counts shifted negative
    g = _group(f, tid)
    _replace(g, "taxels", g["taxels"][()].astype(np.int16) - 600)


def _n_samples(f, tid):
    _group(f, tid).attrs["n_samples"] = 300


#: craft -> (damage, the trial it damages, what the reason says); each on a trial of its own (0 is the copies'
#: original): with all 7 out, 7 trials of texture A and 6 of B would be left for the analysis' 4 per texture
CRAFTS = {"gap": (_gap, 1, "seq column shows 7 missing frames"), "copy": (_copy, 2, "byte copy of trial 0"),
          "crc": (_crc, 3, "crc_errors attribute"), "duration": (_duration, 4, "plan duration 1e+09 s"),
          "short": (_short, 5, "holds 10 samples"), "negative": (_negative, 6, "outside the sensor's"),
          "n_samples": (_n_samples, 7, "n_samples attribute says 300")}

#: the crafts three to a file (a command's summary line names the reasons of the first three trials it leaves out):
#: one run of each command per file instead of one per craft; the trials are checked one by one, so a damaged trial
#: is found alone or beside others alike
GROUPS = [("copy", "crc", "gap"), ("duration", "negative", "short"), ("n_samples",)]


@pytest.mark.parametrize("crafts", GROUPS, ids="+".join)
def test_crafted_trials_are_excluded_identically_by_every_command(base, tmp_path, crafts):
    """Each command leaves out exactly the crafted trials, and says each one's reason, the reason ``info`` gives."""
    path = tmp_path / "crafted.h5"
    shutil.copy(base, path)
    with h5py.File(path, "r+") as f:
        for craft in crafts:
            damage, tid, _ = CRAFTS[craft]
            damage(f, tid)
    bad = sorted(CRAFTS[craft][1] for craft in crafts)
    runner = CliRunner()
    verdict = {}  # command -> (exit status, trials left out, every reason said)

    r = runner.invoke(main, ["info", str(path), "--json"])
    info = json.loads(r.stdout) if r.exit_code == 0 else {"trials": []}
    rows = {t["trial_id"]: t for t in info["trials"] if t["status"] != "complete"}
    reasons = {CRAFTS[c][1]: (rows[CRAFTS[c][1]].get("error") or "") if CRAFTS[c][1] in rows else "" for c in crafts}
    worded = {craft: CRAFTS[craft][2] in reasons[CRAFTS[craft][1]] for craft in crafts}
    assert all(worded.values()), (worded, reasons)
    verdict["info"] = (r.exit_code, sorted(rows), [t["status"] for t in rows.values()] == ["excluded"] * len(bad)
                       and info["totals"]["excluded"] == len(bad))

    def said(text: str) -> bool:
        return all(reason and reason in text for reason in reasons.values())

    enc = tmp_path / "crafted.enc.h5"
    r = runner.invoke(main, ["encode", str(path), "--out", str(enc), "--quiet", "--variant", "original"])
    left_out = None
    if r.exit_code == 0:
        with open_encoded(enc) as e:
            left_out = sorted(set(range(N_TRIALS)) - set(int(t) for t in e.trials["trial_id"]))
    verdict["encode"] = (r.exit_code, left_out, said(r.stderr))

    nwb = tmp_path / "crafted.nwb"
    r = runner.invoke(main, ["export", "nwb", str(path), "--out", str(nwb), "--no-progress"])
    left_out = None
    if r.exit_code == 0:
        left_out = sorted(set(range(N_TRIALS)) - set(int(t) for t in read_nwb_summary(nwb)[1]["trial_id"]))
    verdict["export nwb"] = (r.exit_code, left_out, said(r.stderr))

    r = runner.invoke(main, ["analyze", str(path), "--encode", "--task", "textures", "--repeats", "1",
                             "--pcs", "1-2", "--per-texture", "4", "--variants", "original", "--json"])
    verdict["analyze"] = (r.exit_code, bad if said(r.stderr) else None, said(r.stderr))

    assert verdict == {command: (0, bad, True) for command in verdict}, (reasons, verdict)

    from rigctl.storage.validate import usable_trials

    with open_session(path) as s:  # the library's word is the commands' word
        assert usable_trials(s).excluded == reasons


def test_an_impossible_sample_rate_excludes_every_trial_everywhere(base, tmp_path):
    path = tmp_path / "rate.h5"
    shutil.copy(base, path)
    with h5py.File(path, "r+") as f:
        layout = json.loads(f.attrs["sensor_layout"])
        layout["sample_rate_hz"] = 1e12
        f.attrs["sensor_layout"] = json.dumps(layout)
    runner = CliRunner()
    r = runner.invoke(main, ["info", str(path), "--json"])
    assert r.exit_code == 0, r.output
    assert {t["status"] for t in json.loads(r.stdout)["trials"]} == {"excluded"}
    for args in (["encode", str(path), "--out", str(tmp_path / "e.h5"), "--quiet"],
                 ["export", "nwb", str(path), "--out", str(tmp_path / "e.nwb"), "--no-progress"]):
        r = runner.invoke(main, args)
        assert r.exit_code == 1 and "sample rate 1e+12 Hz is impossible" in r.stderr, (args, r.output)
        assert not list(tmp_path.glob("e.*"))


def test_seq_gaps_wrap_at_65536():
    from rigctl.storage.validate import seq_gaps

    assert seq_gaps(np.array([65534, 65535, 0, 1], np.uint16)) == 0
    assert seq_gaps(np.array([65534, 2], np.uint16)) == 3
    assert seq_gaps(np.array([5, 6, 10], np.uint16)) == 3


def test_block_seq_gaps_equals_seq_gaps_trial_by_trial():
    """The block form (only the jumps gathered) against the per-trial definition, on random blocks: wraps at
    65,536, repeats, jumps at trial boundaries (not counted: they are between trials), empty trials, int64 columns."""
    from rigctl.storage.validate import block_seq_gaps, seq_gaps

    rng = np.random.default_rng(7)
    for _ in range(2000):
        n = int(rng.integers(0, 60))
        steps = rng.choice([1, 1, 1, 2, 5, 0, 65535, 300], size=n)
        seq = ((int(rng.integers(0, 65536)) + np.cumsum(steps)) % 65536).astype(np.uint16)
        if rng.random() < 0.3:
            seq = seq.astype(np.int64)
        pos = np.concatenate([[0], np.sort(rng.integers(0, n + 1, size=int(rng.integers(0, 6)))), [n]])
        want = [seq_gaps(seq[pos[i]:pos[i + 1]]) for i in range(len(pos) - 1)]
        assert block_seq_gaps(seq, pos).tolist() == want, (seq, pos)


def test_trials_alike_in_their_fingerprint_rows_are_no_copies_unless_every_byte_is():
    """Byte copies are found by a fingerprint of a few hundred rows, confirmed on every byte: a trial that differs
    from an earlier one only in a row outside the fingerprint is not called a copy; an exact copy is."""
    from rigctl.storage.trial_facts import PRINT_ROWS as _PRINT_ROWS
    from rigctl.storage.validate import _Copies

    rng = np.random.default_rng(3)
    a = rng.integers(0, 1024, (5000, 18)).astype(np.uint16)
    printed = set(range(0, 5000, 5000 // _PRINT_ROWS)) | {4999}
    row = next(r for r in range(1, 5000) if r not in printed)
    b = a.copy()
    b[row, 3] ^= 1
    assert _Copies.fingerprint(a) == _Copies.fingerprint(b)  # the fingerprint alone cannot tell them apart
    copies = _Copies()
    assert copies.copy_of(0, a, lambda: a) is None
    assert copies.copy_of(1, b, lambda: b) is None  # ... every byte can
    assert copies.copy_of(2, a.copy(), lambda: a) == 0
