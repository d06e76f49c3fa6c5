"""Session files under faults: one writer per file, writes that check the file (not only the writer's memory),
readers that validate what they read and say what is wrong in one line, a full disk and a read-only target
(docs/session-format.md, "Crash safety" and "Validation")."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import textwrap
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.storage import journal
from rigctl.storage.session import (
    SessionError,
    SessionLocked,
    SessionWriteError,
    SessionWriter,
    TrialData,
    TrialStatus,
    open_session,
)

from .forked import PythonC


def _plan(n, texture="A"):
    return [dict(trial_id=i, texture=texture, speed_mm_s=40.0, force_g=100.0, duration_s=0.5) for i in range(n)]


def _trial(value, n=500):
    return TrialData(taxels=np.full((n, 18), value, np.uint16), force_g=[1.0], force_time_s=[0.0])


def _session(path, n_plan=6, n_done=3, **kw):
    """A session of ``n_plan`` trials, the first ``n_done`` written (trial k holds the value k), writer closed.
    (Tests that damage one trial's datasets write schema 3, one group of datasets per trial; the checks of schema
    4's recording arrays are in test_storage_recording.py.)"""
    with SessionWriter.create(path, plan=_plan(n_plan), protocol_source="src", **kw) as w:
        for k in range(n_done):
            w.write_trial(k, _trial(k))
    return path


# -- one writer per session file ------------------------------------------------------------------------------------
_HOLDER = textwrap.dedent(
    """
    import sys, time
    from rigctl.storage.session import SessionWriter
    w = SessionWriter.open(sys.argv[1])
    print("holding", flush=True)
    time.sleep(120)
    """
)


def test_a_second_writer_is_refused_in_this_process_and_from_another_one(tmp_path):
    path = _session(tmp_path / "s.h5")
    w = SessionWriter.open(path, protocol_source="src")
    with pytest.raises(SessionLocked, match="another writer in this process"):
        SessionWriter.open(path, protocol_source="src")
    with pytest.raises(SessionLocked):
        SessionWriter.create(path, plan=_plan(1), overwrite=True)  # a file being written is never replaced
    with h5py.File(path, "r") as f:  # plain HDF5 readers still open it between the writer's commits
        assert list(f["plan"]["status"][:3]) == [TrialStatus.COMPLETE] * 3
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1, 2]
    w.write_trial(3, _trial(3))  # the reader closed: the holder writes on
    w.close()
    assert w.closed and not journal.lock_path(path).exists()  # a closed writer leaves no lock file
    with pytest.raises(SessionError, match="closed"):
        w.write_trial(4, _trial(4))
    # another process holds it: refused, naming the holder's pid
    proc = PythonC(_HOLDER, str(path), stdout=True)
    try:
        assert proc.stdout.readline().strip() == "holding"
        with pytest.raises(SessionLocked, match=f"another process \\(pid {proc.pid}\\)") as err:
            SessionWriter.open(path)
        assert err.value.pid == proc.pid and str(path) in str(err.value)
        # a CLI user gets that one line: `rigctl acquire --resume` checks the file before the rig moves
    finally:
        proc.send_signal(signal.SIGKILL)  # kill -9: the kernel drops the lock; the lock file it leaves is harmless
        proc.wait()
    assert journal.lock_path(path).exists()
    with SessionWriter.open(path) as w2:
        w2.write_trial(4, _trial(4))
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1, 2, 3, 4]
        assert all((s.trial(k).taxels == k).all() for k in range(5))


def test_an_abandoned_writer_releases_its_lock_when_collected(tmp_path):
    path = _session(tmp_path / "s.h5")
    SessionWriter.open(path)  # never closed, not kept
    with SessionWriter.open(path) as w:
        assert w.completed_ids() == [0, 1, 2]


def test_a_write_checks_the_files_plan_not_only_the_writers_memory(tmp_path):
    """A trial the file holds complete (written behind this writer's back, e.g. by another tool) is refused and
    stays as it is: the old writer replaced it (its 'already complete' check read only its own memory)."""
    path = _session(tmp_path / "s.h5")
    w = SessionWriter.open(path)
    assert 3 in w.pending_ids()
    with h5py.File(path, "r+") as f:  # someone else records trial 3 meanwhile
        g = f["trials"].create_group("000003")
        g.create_dataset("taxels", data=np.full((500, 18), 33, np.uint16))
        g.attrs["status"] = "complete"
        f["plan"][3:4, "status"] = np.array([TrialStatus.COMPLETE], np.uint8)
    with pytest.raises(SessionError, match="trial 3 is already complete"):
        w.write_trial(3, _trial(99))
    assert 3 in w.completed_ids()  # the writer now knows
    w.write_trial(4, _trial(4))  # the others are written as usual
    w.close()
    with h5py.File(path, "r") as f:
        assert (f["trials/000003/taxels"][()] == 33).all()
        assert list(f["plan"]["status"]) == [1, 1, 1, 1, 1, 0]


def test_a_complete_recording_is_never_deleted_to_make_room(tmp_path):
    """/plan says pending but the trial's group holds a complete recording (two writers of an older rigctl): the
    writer refuses to replace it, and to mark the trial failed over it."""
    path = _session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        f["plan"][1:2, "status"] = np.array([TrialStatus.PENDING], np.uint8)
    with SessionWriter.open(path) as w:
        assert 1 in w.pending_ids()
        with pytest.raises(SessionError, match="already holds a complete recording"):
            w.write_trial(1, _trial(77))
        with pytest.raises(SessionError, match="already holds a complete recording"):
            w.mark_failed(1, "late")
    with h5py.File(path, "r") as f:
        assert (f["trials/000001/taxels"][()] == 1).all() and f["trials/000001"].attrs["status"] == "complete"


# -- readers validate ------------------------------------------------------------------------------------------------
def _edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)
    return path


def _info(path):
    from rigctl.cli import main

    return CliRunner().invoke(main, ["info", str(path)])


def _one_line_error(result, *needles):
    assert result.exit_code != 0 and result.exception is None or isinstance(result.exception, SystemExit), \
        result.output
    text = result.output.strip()
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    for n in needles:
        assert n in text, text


def test_duplicate_plan_ids_refuse_the_file(tmp_path):
    def dup(f):
        plan = f["plan"][()]
        plan["trial_id"] = 0  # the crafted file of the probe: encode read trial 0 six times
        f["plan"][...] = plan
    path = _edit(_session(tmp_path / "d.h5"), dup)
    with pytest.raises(SessionError, match="lists trial 0 6 times"):
        open_session(path)
    with pytest.raises(SessionError, match="lists trial 0 6 times"):
        SessionWriter.open(path)
    _one_line_error(_info(path), "lists trial 0 6 times")


def test_a_complete_trial_without_its_recording_is_pending_with_a_warning(tmp_path, caplog):
    """info counted it complete (0 samples) and encode dropped it: now both see it pending, a warning names it,
    and a resume records it."""
    path = _edit(_session(tmp_path / "m.h5"), lambda f: f.__delitem__("trials/000001"))
    with open_session(path) as s:
        assert s.completed_ids() == [0, 2]
        assert s.plan["status"][1] == TrialStatus.PENDING
        assert any("trial 1 is marked complete in /plan but has no recording" in p for p in s.problems)
    assert "trial 1 is marked complete" in caplog.text
    out = _info(path)
    assert out.exit_code == 0 and "2/6 trials complete, 0 failed, 4 pending" in out.output
    with SessionWriter.open(path) as w:
        assert w.pending_ids() == [1, 3, 4, 5]
        w.write_trial(1, _trial(11))
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1, 2] and not s.problems


@pytest.mark.parametrize("damage, message", [
    (lambda g: g.attrs.__setitem__("n_samples", 999_999), "n_samples attribute says 999999, its taxels hold 500"),
    (lambda g: _replace(g, "taxels", np.full((500, 18), 65535, np.uint16)), "taxels hold 65535 (sample 0), "
                                                                             "outside the sensor's 10-bit range"),
    (lambda g: _replace(g, "taxels", np.full((500, 18), 3.5)), "taxels are float64, not integer ADC counts"),
    (lambda g: _replace(g, "taxels", np.zeros((500, 17), np.uint16)), "taxels are (500, 17), not (samples, 18)"),
    (lambda g: _replace(g, "seq", np.zeros(499, np.uint16)), "seq is (499,), not (500,) like taxels"),
    (lambda g: _replace(g, "force_time_s", np.zeros(3)), "force_g (1,) and force_time_s (3,) are not one trace"),
    (lambda g: g.__delitem__("flags"), "flags is missing"),
    (lambda g: g.attrs.__setitem__("dropped_frames", -4), "dropped_frames attribute is -4"),
])
def test_a_damaged_trial_is_named_never_read_as_data(tmp_path, caplog, damage, message):
    path = _edit(_session(tmp_path / "t.h5", schema_version=3), lambda f: damage(f["trials/000002"]))
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1, 2]
        with pytest.raises(SessionError, match="trial 2 is damaged") as err:
            s.trial(2)
        assert message in str(err.value) and str(path) in str(err.value)
        assert [int(t.taxels[0, 0]) for t in s.iter_trials()] == [0, 1]  # skipped, with a warning naming it
        assert any("trial 2 is damaged" in p for p in s.problems)
        np.testing.assert_array_equal(s.trial(1).taxels, np.full((500, 18), 1))
    assert "trial 2 is damaged" in caplog.text
    result = _info(path)  # info lists it as excluded, with the reason encode and export give (rigctl.storage.validate)
    assert result.exit_code == 0, result.output
    row = [line for line in result.output.splitlines() if line.split()[:1] == ["2"]]
    assert len(row) == 1 and row[0].rstrip().endswith(")") and "excluded (" in row[0] and message in row[0], row


def _replace(group, name, data):
    del group[name]
    group.create_dataset(name, data=data)


def test_encode_excludes_a_damaged_trial_and_says_why_in_one_line(tmp_path):
    from rigctl.cli import main
    from rigctl.storage.encoded import open_encoded

    path = _edit(_session(tmp_path / "e.h5", schema_version=3), lambda f: _replace(f["trials/000001"], "taxels",
                                                                 np.full((500, 18), 65535, np.uint16)))
    out = tmp_path / "e.enc.h5"
    result = CliRunner().invoke(main, ["encode", str(path), "--out", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    warned = [line for line in result.stderr.splitlines() if "trial 1" in line]
    assert len(warned) == 1 and "65535" in warned[0] and "2 of 3 complete trials usable" in warned[0]
    with open_encoded(out) as e:
        assert [int(t) for t in e.trials["trial_id"]] == [0, 2]


def test_not_hdf5_and_foreign_files_are_session_errors(tmp_path):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not an HDF5 file at all" * 100)
    with pytest.raises(SessionError, match="not a readable HDF5 file"):
        open_session(junk)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["plan"] = np.arange(3)
        f.create_group("trials")
        f.create_group("protocol")
        f.attrs["schema_version"] = 3
    with pytest.raises(SessionError, match="/plan is not a plan table"):
        open_session(foreign)
    _one_line_error(_info(foreign), "not a plan table")


# -- disk full, read-only ------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _tmpfs(tmp_path, size_kib):
    """A tmpfs of ``size_kib`` mounted in ``tmp_path`` (we run as root here and in CI); skips where mounting is not
    permitted (not root, or no CAP_SYS_ADMIN in a container)."""
    d = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(d)], capture_output=True,
                       text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here to fill a disk (mount: {r.stderr.strip()})")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _fill(d: Path, leave_kib: int) -> None:
    """Fill the file system of ``d`` until about ``leave_kib`` KiB are free."""
    st = os.statvfs(d)
    free = st.f_bavail * st.f_frsize
    with open(d / "filler", "wb") as fh:
        fh.write(b"\0" * max(0, free - leave_kib * 1024))


_CREATE_ON_FULL_DISK = textwrap.dedent(
    """
    import sys
    from rigctl.storage.session import SessionError, SessionWriter
    plan = [dict(trial_id=i, texture="A", speed_mm_s=40.0, force_g=100.0, duration_s=1.0) for i in range(6)]
    try:
        SessionWriter.create(sys.argv[1], plan=plan)
    except SessionError as exc:
        print("ERROR", type(exc).__name__, exc)
    else:
        print("CREATED")
    """
)


@pytest.mark.parametrize("free_kib", [4, 8, 16])
def test_creating_a_session_on_a_full_disk_is_a_clear_error_not_a_crash(tmp_path, free_kib):
    """At 4-8 KiB free HDF5 crashed the process (SIGSEGV) creating the file and left S.h5.creating behind."""
    with _tmpfs(tmp_path, 256) as d:
        _fill(d, free_kib)
        proc = PythonC(_CREATE_ON_FULL_DISK, str(d / "S.h5"), stdout=True)  # a crash takes only the child
        assert proc.wait(60) == 0, proc.returncode  # (its traceback, if any, on stderr)
        out = proc.stdout.read()
        assert out.startswith("ERROR SessionWriteError no space left on device creating"), out
        assert "free space or choose another --out" in out
        assert sorted(p.name for p in d.iterdir()) == ["filler"]  # no S.h5, no .creating, no lock file


def test_a_full_disk_mid_session_keeps_every_finished_trial_and_resumes(tmp_path):
    with _tmpfs(tmp_path, 1024) as d:
        path = d / "S.h5"
        rng = np.random.default_rng(4)
        data = {k: rng.integers(0, 1024, (1000, 18)).astype(np.uint16) for k in range(40)}  # ~36 KiB each
        w = SessionWriter.create(path, plan=_plan(40), protocol_source="src", compression=None)
        _fill(d, 450)  # a few trials: schema 4 allocates its recording arrays 4,096 samples (~190 KiB) at a time
        written = []
        with pytest.raises(SessionWriteError) as err:
            for k in range(40):
                w.write_trial(k, TrialData(taxels=data[k]))
                written.append(k)
        msg = str(err.value)
        assert 2 <= len(written) < 10
        assert msg.startswith(f"no space left on device writing {path} (writing trials)")
        assert f"trials 0-{written[-1]} are intact; free space and --resume" in msg
        assert err.value.intact == written and w.completed_ids() == written
        assert not journal.journal_path(path).exists()
        with h5py.File(path, "r") as f:  # plain HDF5, before rigctl touches the file again
            assert [int(t) for t in np.flatnonzero(f["plan"]["status"][()] == 1)] == written
            for k in written:
                np.testing.assert_array_equal(f[f"trials/{k:06d}/taxels"][()], data[k])
        with pytest.raises(SessionWriteError):  # still full: the same clear error, nothing lost
            w.write_trial(written[-1] + 1, TrialData(taxels=data[written[-1] + 1]))
        w.close()
        (d / "filler").unlink()  # free space, then --resume
        with SessionWriter.open(path, protocol_source="src", compression=None) as w2:
            for k in w2.pending_ids()[:4]:
                w2.write_trial(k, TrialData(taxels=data[k]))
        with open_session(path) as s:
            done = s.completed_ids()
            assert done == list(range(len(written) + 4))
            for k in done:
                np.testing.assert_array_equal(s.trial(k).taxels, data[k])


def test_a_read_only_target_is_a_clear_error(tmp_path):
    with _tmpfs(tmp_path, 1024) as d:
        path = _session(d / "S.h5", n_done=2)
        subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        with pytest.raises(SessionWriteError, match="read-only file system"):
            SessionWriter.open(path)
        with pytest.raises(SessionWriteError, match="read-only file system"):
            SessionWriter.create(d / "new.h5", plan=_plan(2))
        with open_session(path) as s:  # readers are not affected
            assert s.completed_ids() == [0, 1] and (s.trial(1).taxels == 1).all()
