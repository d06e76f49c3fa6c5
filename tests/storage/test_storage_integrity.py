"""Integrity from the content (issue 52 item 8): a sealed session was trusted on its modification time; NaN written
into a trial with the time put back passed as 6/6 complete (the NWB export held the NaN), a taxel edited the same way
passed unseen, and one flipped bit in a compressed taxel chunk took the whole file down in every command. Now every
trial's samples are read and checked against the checksum sealed with them, and a trial whose content changed or
whose chunk cannot be read is excluded by itself, named; the rest of the file stays usable."""

from __future__ import annotations

import os

import h5py
import numpy as np
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData, open_session
from rigctl.storage.validate import usable_trials

N = 8192  # samples a trial: two taxel chunks of 4096 rows each


def _session(path):
    rng = np.random.default_rng(4)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=N / 1000.0)
            for i in range(6)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 't'") as w:
        for i in range(6):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (N, 18)), seq=np.arange(N) % 65536,
                                       force_g=np.full(50, 500.0), force_time_s=np.arange(50) / 10,
                                       speed_mm_s=np.full(50, 80.0), speed_time_s=np.arange(50) / 10))
    return path


def _edit_keeping_mtime(path, edit):
    st = os.stat(path)
    with h5py.File(path, "r+") as f:
        edit(f)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_mtime_ns == st.st_mtime_ns


def _rows(f, tid):
    idx = f["recording/index"][()]
    return next(r for r in idx if int(r["trial_id"]) == tid)


def test_nan_and_an_edited_taxel_with_the_time_put_back_are_excluded_by_themselves(tmp_path):
    path = _session(tmp_path / "s.h5")

    def edit(f):
        r2, r4 = _rows(f, 2), _rows(f, 4)
        f["recording/force_g"][int(r2["force_start"]) + 3] = np.nan
        t = int(r4["sample_start"]) + 100
        f["recording/taxels"][t, 5] = 901 if f["recording/taxels"][t, 5] != 901 else 902

    _edit_keeping_mtime(path, edit)
    with open_session(path) as s:
        report = usable_trials(s)
        assert report.ids == [0, 1, 3, 5], report.excluded
        assert "NaN in force_g" in report.excluded[2]
        assert "differ from the checksum sealed with them" in report.excluded[4]
    r = CliRunner().invoke(main, ["info", str(path)])
    assert r.exit_code == 0 and "4/6" in r.output, r.output


def test_a_flipped_bit_in_a_compressed_chunk_excludes_its_trial_only(tmp_path):
    path = _session(tmp_path / "s.h5")
    with h5py.File(path, "r") as f:
        ds = f["recording/taxels"]
        r3 = _rows(f, 3)
        chunk = int(r3["sample_start"]) // ds.chunks[0] + 1  # a chunk of trial 3's alone (4096-row chunks)
        info = ds.id.get_chunk_info(chunk)
        offset, size = int(info.byte_offset), int(info.size)
    st = os.stat(path)
    with open(path, "r+b") as fh:
        fh.seek(offset + size // 2)
        byte = fh.read(1)[0]
        fh.seek(offset + size // 2)
        fh.write(bytes([byte ^ 0x10]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    with open_session(path) as s:
        report = usable_trials(s)
        assert report.ids == [0, 1, 2, 4, 5], report.excluded
        assert "cannot be read (a damaged chunk" in report.excluded[3] or "differ from the checksum" in report.excluded[3]
    r = CliRunner().invoke(main, ["info", str(path)])
    assert r.exit_code == 0 and "5/6" in r.output and "damaged chunk" in r.output, r.output
    r = CliRunner().invoke(main, ["encode", str(path), "--out", str(tmp_path / "e.h5"), "--no-progress",
                                  "--variant", "original"])
    assert r.exit_code == 0 and "trial 3" in r.output, r.output


def test_blocks_hashed_while_the_next_is_read_keep_each_trials_reason(tmp_path, monkeypatch):
    """The validator hashes a block on its worker thread while it reads the next: with one trial a block (six
    blocks in flight in turn) each damaged trial keeps its own reason and the report is the one-block report."""
    import rigctl.storage.validate as validate

    path = _session(tmp_path / "s.h5")

    def edit(f):
        r1, r3, r4 = _rows(f, 1), _rows(f, 3), _rows(f, 4)
        t = int(r1["sample_start"]) + 7
        f["recording/taxels"][t, 0] = 901 if f["recording/taxels"][t, 0] != 901 else 902
        f["recording/speed_mm_s"][int(r3["speed_start"]) + 1] = np.inf
        t = int(r4["sample_start"]) + N - 1
        f["recording/taxels"][t, 17] = 4000  # outside the 10-bit range, and not the sealed checksum

    _edit_keeping_mtime(path, edit)
    reports = []
    for rows in (N, 1 << 20):  # a block a trial, then one block for all
        monkeypatch.setattr(validate, "_BLOCK_ROWS", rows)
        with open_session(path) as s:
            reports.append(usable_trials(s))
    one_a_block, one_block = reports
    assert one_a_block.ids == [0, 2, 5], one_a_block.excluded
    assert "differ from the checksum sealed with them" in one_a_block.excluded[1]
    assert "inf in speed_mm_s" in one_a_block.excluded[3]
    assert "differ from the checksum sealed with them" in one_a_block.excluded[4]
    assert list(one_a_block.excluded) == [1, 3, 4]
    assert (one_a_block.ids, one_a_block.excluded, one_a_block.dropped_frames) == \
        (one_block.ids, one_block.excluded, one_block.dropped_frames)


def _datasets(path, skip=()) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()])
                     if isinstance(obj, h5py.Dataset) and not name.startswith(skip) else None)
    return out


def test_a_session_checked_beside_the_work_gives_what_checking_it_first_gives(tmp_path, monkeypatch):
    """A large session is checked by the validator in a process of its own while the export works on the trials
    that pass the checks that read no data (`validate.check_beside`). Those are not the usable ones when reading the
    data excludes some (a NaN and a taxel edited with the time put back): the export is then made again with the
    validator's trials. Either way the NWB file holds the trials and data of checking first, and the excluded trials
    are warned of once by each command (the encoder checks in its own process)."""
    import warnings

    import rigctl.storage.validate as validate
    from rigctl.encoding.pipeline import encode_session
    from rigctl.storage.nwb import export_nwb, read_nwb_summary

    clean = _session(tmp_path / "clean.h5")
    edited = _session(tmp_path / "edited.h5")

    def edit(f):
        r2, r4 = _rows(f, 2), _rows(f, 4)
        f["recording/force_g"][int(r2["force_start"]) + 3] = np.nan
        t = int(r4["sample_start"]) + 100
        f["recording/taxels"][t, 5] = 901 if f["recording/taxels"][t, 5] != 901 else 902

    _edit_keeping_mtime(edited, edit)
    started = []
    beside = validate.Beside

    class Spy(beside):
        def __init__(self, *a, **k):
            started.append(a[1])
            super().__init__(*a, **k)

    kw = dict(fit_memory_bytes=400_000, batch_trials=2, store_spikes=("original",), progress=False)
    for path, usable in ((clean, [0, 1, 2, 3, 4, 5]), (edited, [0, 1, 3, 5])):
        out = {}
        for mode in ("first", "beside"):
            here = []
            if mode == "beside":
                monkeypatch.setattr(validate, "BESIDE_BYTES", 0)
                monkeypatch.setattr(validate, "Beside", Spy)
                check = validate._check_session
                monkeypatch.setattr(validate, "_check_session",
                                    lambda *a, here=here, check=check: here.append(1) or check(*a))
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                encode_session(path, tmp_path / f"{path.stem}.{mode}.enc.h5", **kw)
                export_nwb(path, tmp_path / f"{path.stem}.{mode}.nwb", encoded_path=tmp_path / f"{path.stem}.{mode}"
                                                                                                ".enc.h5")
            assert len(here) == (mode == "beside")  # the encoder's check here, the export's in its own process
            said = [str(w.message) for w in caught if issubclass(w.category, validate.TrialsExcluded)]
            assert len(said) == (2 if path == edited else 0), said  # once by each command
            out[mode] = (_datasets(tmp_path / f"{path.stem}.{mode}.enc.h5"),
                         read_nwb_summary(tmp_path / f"{path.stem}.{mode}.nwb"))
            monkeypatch.undo()
        assert started == [[0, 1, 2, 3, 4, 5]], started  # the export guessed every trial usable
        started.clear()
        (enc_a, (nwb_a, arr_a)), (enc_b, (nwb_b, arr_b)) = out["first"], out["beside"]
        for k in enc_a:
            np.testing.assert_array_equal(enc_a[k], enc_b[k], err_msg=k)
        assert list(arr_b["trial_id"]) == usable
        assert (nwb_a.n_trials, nwb_a.n_samples, nwb_a.units, nwb_a.spikes) == \
            (nwb_b.n_trials, nwb_b.n_samples, nwb_b.units, nwb_b.spikes)
        for k in arr_a:
            np.testing.assert_array_equal(arr_a[k], arr_b[k], err_msg=k)


def test_the_validator_hands_over_only_the_taxels_of_trials_that_pass(tmp_path):
    """``usable_trials(kept=KeptTaxels(session, groups))``: the counts of the wanted trials that pass, as read, in
    the blocks asked for (what the encoder's force fit then uses without reading them again); a trial whose taxels no
    longer meet the checksum sealed with them (edited, the time put back) is never handed over, nor its block."""
    from rigctl.storage.validate import KeptTaxels

    path = _session(tmp_path / "s.h5")

    def edit(f):
        t = int(_rows(f, 4)["sample_start"]) + 100
        f["recording/taxels"][t, 5] = 901 if f["recording/taxels"][t, 5] != 901 else 902

    _edit_keeping_mtime(path, edit)
    with open_session(path) as s:
        kept = KeptTaxels(s, [[3, 1], [4, 5]])
        report = usable_trials(s, kept=kept)
        assert 4 in report.excluded and len(kept) == 3
        assert kept.block(s, [4, 5]) is None  # not every one kept: the caller reads them
        assert kept.block(s, [1, 3]) is None  # not a block asked for
        got = kept.block(s, [3, 1], traces=True)
        want = s.read_taxels([3, 1], traces=True)
        assert got is not None and want.speed_traces is not None and got.speed_traces is not None
        for name in ("data", "starts", "dropped_frames", "has_speed_trace"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        for (t1, v1), (t2, v2) in zip(got.speed_traces, want.speed_traces):
            np.testing.assert_array_equal(t1, t2)
            np.testing.assert_array_equal(v1, v2)
        assert kept.block(s, [3, 1]) is None and len(kept) == 1  # handed over: freed
        again = KeptTaxels(s, [[1]])
        usable_trials(s, kept=again)  # the report is cached on the open file: no read, nothing handed over
        assert len(again) == 0
