"""The seal covers everything the analysis reads (issue 77 item 6) and the validator recounts held readings (item 2).

On main before this the seal covered the taxels only: force x100 (exported as 50 kg), a swapped texture label, NaN
host times and a force time stamp moved 100 s passed info, encode and export; a plain h5py edit (the modification
time moved) passed even for the taxels; ``/recording/taxels`` as an external link or a virtual dataset into another
file was read as the session's own; and info / encode took a trial's held readings from its stored attribute. Now
each edited trial is excluded by itself with its reason (the others stay usable, export writes them), data of
another file excludes every trial naming it, and the repeated samples are counted from the counts read."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.core.trial import repeated_samples
from rigctl.storage.session import SessionWriter, TrialData, open_session
from rigctl.storage.trial_blocks import block_repeated
from rigctl.storage.validate import usable_trials

N = 300


def _trial(rng, held_every=0):
    tax = rng.integers(100, 900, (N, 18))
    if held_every:
        tax[held_every::held_every] = tax[held_every - 1::held_every][: len(tax[held_every::held_every])]
    return TrialData(taxels=tax, seq=np.arange(N), host_time_s=100.0 + np.arange(N) / 1000.0,
                     force_g=rng.normal(500, 2, 6), force_time_s=np.arange(6) * 0.05,
                     speed_mm_s=rng.normal(80, 1, 6), speed_time_s=np.arange(6) * 0.05)


@pytest.fixture(scope="module")
def sealed(tmp_path_factory):
    path = tmp_path_factory.mktemp("seal") / "s.h5"
    rng = np.random.default_rng(7)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(6)]
    with SessionWriter.create(path, plan=plan, protocol_source="seal", compression=None, durable=False) as w:
        w.write_trials((i, _trial(rng, held_every=5 if i == 5 else 0)) for i in range(6))
    return path


def _copy(src, tmp_path, name):
    path = tmp_path / name
    path.write_bytes(src.read_bytes())  # a plain copy: the modification time moves, as any edit's does
    return path


def _row(f, tid):
    idx = f["recording/index"][()]
    return idx[idx["trial_id"] == tid][0]


def _force_x100(f):
    r = _row(f, 1)
    a = int(r["force_start"])
    f["recording/force_g"][a:a + 6] = f["recording/force_g"][a:a + 6] * 100


def _label(f):
    rows = f["plan"][()]
    i = int(np.flatnonzero(rows["trial_id"] == 1)[0])
    row = rows[i]
    row["texture"] = "A"  # trial 1 is a B
    f["plan"][i] = row


def _host_nan(f):
    f["recording/host_time_s"][int(_row(f, 1)["sample_start"]) + 10] = np.nan


def _force_time(f):
    f["recording/force_time_s"][int(_row(f, 1)["force_start"]) + 2] += 100.0


def _taxel_plain(f):
    t = int(_row(f, 1)["sample_start"]) + 20
    f["recording/taxels"][t, 3] = 901 if f["recording/taxels"][t, 3] != 901 else 902


EDITS = {"force x100": (_force_x100, "force / speed traces differ from the checksum sealed"),
         "label swapped": (_label, "its /plan labels (texture, speed, force, duration, ...) differ"),
         "host time NaN": (_host_nan, "host times or force / speed traces differ from the checksum sealed"),
         "force time moved": (_force_time, "force / speed traces differ from the checksum sealed"),
         "taxel, time not put back": (_taxel_plain, "its stored taxels differ from the checksum sealed")}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_an_edit_of_anything_the_analysis_reads_excludes_its_trial_only(sealed, tmp_path, edit):
    damage, words = EDITS[edit]
    path = _copy(sealed, tmp_path, "e.h5")
    with h5py.File(path, "r+") as f:
        damage(f)
    with open_session(path) as s:
        report = usable_trials(s)
    assert list(report.excluded) == [1] and words in report.excluded[1], report.excluded
    assert report.ids == [0, 2, 3, 4, 5]
    r = CliRunner().invoke(main, ["info", str(path)])
    assert r.exit_code == 0 and "5/6 trials complete, 1 excluded" in r.output, r.output
    r = CliRunner().invoke(main, ["export", "nwb", str(path), "--out", str(tmp_path / "e.nwb"), "--no-progress"])
    assert r.exit_code == 0 and "Traceback" not in r.output, r.output


def test_an_edit_stays_found_after_a_resume_seals_the_file_again(tmp_path):
    path = tmp_path / "r.h5"
    rng = np.random.default_rng(3)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(3)]
    with SessionWriter.create(path, plan=plan, protocol_source="seal", compression=None, durable=False) as w:
        w.write_trials((i, _trial(rng)) for i in range(2))
    with h5py.File(path, "r+") as f:
        _force_x100(f)
    with SessionWriter.open(path, protocol_source="seal", durable=False) as w:
        w.write_trial(2, _trial(rng))
    with open_session(path) as s:
        report = usable_trials(s)
    assert report.ids == [0, 2] and "force / speed traces differ" in report.excluded[1], report.excluded


def test_a_changed_sensor_layout_excludes_every_trial_naming_it(sealed, tmp_path):
    path = _copy(sealed, tmp_path, "l.h5")
    with h5py.File(path, "r+") as f:
        layout = json.loads(f.attrs["sensor_layout"])
        layout["sample_rate_hz"] = 2000.0
        f.attrs["sensor_layout"] = json.dumps(layout)
    r = CliRunner().invoke(main, ["info", str(path)])
    assert r.exit_code == 0 and "0/6 trials complete, 6 excluded" in r.output, r.output
    assert "the session's sensor_layout differs from the checksum sealed at its last commit" in r.output, r.output


def _external(f, other):
    with h5py.File(other, "w") as o:
        o["taxels"] = f["recording/taxels"][()]
    del f["recording/taxels"]
    f["recording/taxels"] = h5py.ExternalLink(str(other), "taxels")


def _virtual(f, other):
    shape = f["recording/taxels"].shape
    with h5py.File(other, "w") as o:
        o["taxels"] = f["recording/taxels"][()]
    layout = h5py.VirtualLayout(shape=shape, dtype="<u2")
    layout[:] = h5py.VirtualSource(str(other), "taxels", shape=shape)
    del f["recording/taxels"]
    f["recording"].create_virtual_dataset("taxels", layout, fillvalue=0)


@pytest.mark.parametrize("how", ["external link", "virtual dataset"])
@pytest.mark.parametrize("source", ["present", "missing"])
def test_taxels_of_another_file_are_not_the_sessions_own(sealed, tmp_path, how, source):
    path = _copy(sealed, tmp_path, "x.h5")
    other = tmp_path / "other.h5"
    with h5py.File(path, "r+") as f:
        (_external if how == "external link" else _virtual)(f, other)
    if source == "missing":
        other.unlink()  # read through, it gave all-zero taxels, exported as 6/6
    with open_session(path) as s:
        report = usable_trials(s)
    assert report.ids == [] and len(report.excluded) == 6, report.excluded
    assert all("/recording/taxels is a" in why and "not the session's own" in why for why in report.excluded.values())
    r = CliRunner().invoke(main, ["export", "nwb", str(path), "--out", str(tmp_path / "x.nwb"), "--no-progress"])
    assert r.exit_code == 1 and "Traceback" not in r.output and "internal error" not in r.output, r.output
    assert "no usable" in r.output and not (tmp_path / "x.nwb").exists(), r.output


def test_repeated_samples_are_recounted_not_taken_from_an_attribute(sealed, tmp_path):
    """Trial 5 holds every 5th reading (59 of 300 samples): info and encode count them from the counts even when
    its stored count says 0."""
    path = _copy(sealed, tmp_path, "h.h5")
    with h5py.File(path, "r+") as f:
        f["trials/000005"].attrs["repeated_samples"] = 0
        f["trials/000001"].attrs["repeated_samples"] = 250  # and a count that is not there
    with open_session(path) as s:
        report = usable_trials(s)
        want = repeated_samples(s.trial(5).taxels)
    assert want == 59 and report.repeated_samples == {5: 59}, report.repeated_samples
    r = CliRunner().invoke(main, ["info", str(path), "--json"])
    rows = {t["trial_id"]: t for t in json.loads(r.stdout)["trials"]}
    assert rows[5]["repeated_samples"] == 59 and rows[1]["repeated_samples"] == 0, rows[5]


def test_block_repeated_counts_each_trial_as_repeated_samples_does():
    rng = np.random.default_rng(0)
    lengths = [0, 1, 2, 7, 0, 30, 1, 12, 0]
    trials = []
    for n in lengths:
        x = rng.integers(0, 3, (n, 2))  # two channels of three values: many repeats, some across trial edges
        trials.append(x)
    tax = np.concatenate(trials)
    pos = np.concatenate([[0], np.cumsum(lengths)])
    assert block_repeated(tax, pos).tolist() == [repeated_samples(x) for x in trials]
