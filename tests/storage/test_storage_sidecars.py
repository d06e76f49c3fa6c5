"""The sidecars of every writer (issue 77 item 3, :mod:`rigctl.storage.sidecars`): created new, never followed,
truncated or deleted unless made by this process; an ``overwrite`` keeps the old session until the new one has
committed a trial. Links, hard links and a user's own files at each sidecar's name, with the library's writers
(the command line's writers: tests/test_cli_writers.py)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from rigctl.acquisition.rigconfig import save_rig_config
from rigctl.storage import journal
from rigctl.storage.outputs import OutputError, output_file, replacing
from rigctl.storage.session import SessionWriter, TrialData, open_session
from rigctl.storage.session_format import SessionWriteError
from rigctl.storage.sidecars import SidecarExists, write_small_file

PLAN = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0, force_g=500.0, duration_s=0.1) for i in range(2)]


def _trial(seed: int) -> TrialData:
    rng = np.random.default_rng(seed)
    return TrialData(taxels=rng.integers(100, 900, (100, 18)), seq=np.arange(100), force_g=[500.0],
                     force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0])


def _session(path: Path, seed: int = 0) -> Path:
    with SessionWriter.create(path, plan=PLAN, protocol_source=f"name = 's{seed}'") as w:
        for i in range(2):
            w.write_trial(i, _trial(seed + i))
    return path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def victim(tmp_path):
    """A session outside the output folder, the file each planted link points to."""
    (tmp_path / "elsewhere").mkdir()
    return _session(tmp_path / "elsewhere" / "precious.h5", seed=7)


@pytest.fixture
def out_dir(tmp_path):
    d = tmp_path / "out"
    d.mkdir()
    return d


def _write_encoded_like(path: Path) -> None:
    import h5py

    with output_file(path, kind="encoded") as target:
        with h5py.File(target.h5_file(), "w") as f:
            f["features"] = np.arange(10)


@pytest.mark.parametrize("sidecar", [".part", ".lock"])
@pytest.mark.parametrize("link", ["symlink", "hard link"])
def test_output_file_never_follows_a_link_at_its_sidecars(sidecar, link, victim, out_dir):
    out = out_dir / "x.h5"
    planted = out_dir / ("x.h5" + sidecar)
    (planted.symlink_to if link == "symlink" else planted.hardlink_to)(victim)
    before = _digest(victim)
    with pytest.raises(OutputError, match="left as it is"):
        _write_encoded_like(out)
    assert _digest(victim) == before and not out.exists()
    assert planted.is_symlink() if link == "symlink" else os.path.samefile(planted, victim)


@pytest.mark.parametrize("sidecar", [".part", ".lock"])
def test_replacing_never_follows_a_link_at_its_sidecars(sidecar, victim, out_dir):
    """What analyze --csv/--plot/--confusion/--save-model and gui --screenshot write through."""
    out = out_dir / "curves.csv"
    with replacing(out, kind="curves") as tmp:
        tmp.write_text("a,b\n")
    assert out.read_text() == "a,b\n" and sorted(os.listdir(out_dir)) == ["curves.csv"]
    (out_dir / ("fig.png" + sidecar)).symlink_to(victim)
    before = _digest(victim)
    with pytest.raises(OutputError, match="left as it is"):
        with replacing(out_dir / "fig.png", kind="figure") as tmp:
            tmp.write_bytes(b"png")
    assert _digest(victim) == before and not (out_dir / "fig.png").exists()
    assert sorted(os.listdir(out_dir)) == ["curves.csv", "fig.png" + sidecar]


def test_a_users_own_part_file_is_refused_and_kept(out_dir):
    mine = out_dir / "x.h5.part"
    mine.write_bytes(b"mine")
    with pytest.raises(OutputError, match="x.h5.part exists .*a file.*left as it is"):
        _write_encoded_like(out_dir / "x.h5")
    assert mine.read_bytes() == b"mine" and not (out_dir / "x.h5").exists()
    assert sorted(os.listdir(out_dir)) == ["x.h5.part"]  # no lock left either


def test_the_part_file_becomes_the_output_and_no_sidecar_is_left(out_dir):
    _write_encoded_like(out_dir / "x.h5")
    assert sorted(os.listdir(out_dir)) == ["x.h5"]
    # a part file replaced by someone else during the write is not renamed into place (nor removed)
    import h5py

    with pytest.raises(OutputError, match="replaced while rigctl wrote it"):
        with output_file(out_dir / "y.h5", kind="encoded") as target:
            with h5py.File(target.h5_file(), "w") as f:
                f["features"] = np.arange(3)
            os.unlink(target.part)
            target.part.write_bytes(b"someone else's")
    assert (out_dir / "y.h5.part").read_bytes() == b"someone else's" and not (out_dir / "y.h5").exists()


def test_a_stale_rigctl_lock_is_taken_and_a_foreign_file_at_the_lock_is_refused(out_dir):
    (out_dir / "x.h5.lock").write_text("999999\n")  # what a killed writer leaves: its pid, nobody holds it
    _write_encoded_like(out_dir / "x.h5")
    assert sorted(os.listdir(out_dir)) == ["x.h5"]
    (out_dir / "y.h5.lock").write_text("a user's notes\n")
    with pytest.raises(OutputError, match="not a lock file of rigctl's"):
        _write_encoded_like(out_dir / "y.h5")
    assert (out_dir / "y.h5.lock").read_text() == "a user's notes\n"
    # a lock held by a live writer is refused as before, naming it
    held = journal.WriterLock(out_dir / "z.h5")
    try:
        with pytest.raises(OutputError, match="being written by another writer in this process"):
            _write_encoded_like(out_dir / "z.h5")
    finally:
        held.release()
    assert not (out_dir / "z.h5.lock").exists()


@pytest.mark.parametrize("sidecar", [".creating", ".lock", ".journal"])
def test_a_session_writer_never_follows_a_link_at_its_sidecars(sidecar, victim, out_dir):
    planted = out_dir / ("s.h5" + sidecar)
    planted.symlink_to(victim)
    before = _digest(victim)
    with pytest.raises(SidecarExists, match="left as it is"):
        SessionWriter.create(out_dir / "s.h5", plan=PLAN)
    assert _digest(victim) == before and planted.is_symlink() and not (out_dir / "s.h5").exists()


def test_overwrite_keeps_the_old_session_until_the_new_one_commits_a_trial(out_dir):
    path = _session(out_dir / "s.h5", seed=1)
    old = _digest(path)
    w = SessionWriter.create(path, plan=PLAN, protocol_source="name = 'new'", overwrite=True)
    try:
        assert _digest(path) == old  # started: the old session is still the file
        assert (out_dir / "s.h5.creating").exists()
    finally:
        w.close()  # closed before any commit (a run killed or stopped at once): the old one kept, the new removed
    assert _digest(path) == old and sorted(os.listdir(out_dir)) == ["s.h5"]
    with open_session(path) as s:
        assert s.protocol_source == "name = 's1'" and len(s.completed_ids()) == 2
    with SessionWriter.create(path, plan=PLAN, protocol_source="name = 'new'", overwrite=True) as w:
        w.write_trial(0, _trial(5))  # the first commit: the new session replaces the old one, atomically
        assert w.path == path
        with open_session(path) as s:
            assert s.protocol_source == "name = 'new'" and s.completed_ids() == [0]
        w.write_trial(1, _trial(6))
    assert sorted(os.listdir(out_dir)) == ["s.h5"]
    with open_session(path) as s:
        assert s.completed_ids() == [0, 1]


def test_small_files_are_written_through_a_sidecar_of_a_random_name(tmp_path, victim):
    """The rig config (and serve's queue and token files, the same function): the fixed names an attacker could
    plant (``rig.json.tmp``) are never used; a link there is left; the file's mode follows the umask, a token's is
    0600."""
    cfg = tmp_path / "rig.json"
    (tmp_path / "rig.json.tmp").symlink_to(victim)
    before = _digest(victim)
    save_rig_config({}, cfg)
    assert json.loads(cfg.read_text()) == {} and _digest(victim) == before
    assert sorted(os.listdir(tmp_path)) == ["elsewhere", "rig.json", "rig.json.tmp"]
    write_small_file(tmp_path / "t.token", b"secret", mode=0o600, exact_mode=True)
    assert (tmp_path / "t.token").stat().st_mode & 0o777 == 0o600


def test_a_session_swapped_for_a_link_is_never_written_through(tmp_path):
    """A session file swapped for a symlink (inside a served data folder held by its descriptor, or anywhere): a
    writer resuming it opens the file itself, ``O_NOFOLLOW``, and refuses the link in one line; the session it
    points to (outside the folder) is unchanged."""
    PLAN3 = [*PLAN, dict(trial_id=2, texture="A", speed_mm_s=40.0, force_g=500.0, duration_s=0.1)]
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = outside / "theirs.h5"
    with SessionWriter.create(victim, plan=PLAN3, protocol_source="name = 'x'") as w:
        w.write_trial(0, _trial(0))
    before = _digest(victim)
    data = tmp_path / "data"
    data.mkdir()
    link = data / "s1.h5"
    link.symlink_to(victim)
    with pytest.raises(SessionWriteError, match="is a symbolic link: a session is written where it is"):
        with SessionWriter.open(link, protocol_source="name = 'x'") as w:
            w.write_trial(1, _trial(1))
    assert _digest(victim) == before and link.is_symlink()
    with open_session(victim) as s:
        assert s.completed_ids() == [0]
