"""One rule for replacing files, everywhere (issue 36 item 3): ``overwrite`` replaces only a regular file that is a
rigctl output of the same kind (a session, an encoded file, an NWB export); never a device, a FIFO, a folder, a
symlink leading out of the output's folder or another program's file; each refusal one line, the file unchanged.

The device tests make their own character device in tmp_path (major/minor of /dev/null, so even a wrong replace
would harm nothing) when this process may (root); otherwise a FIFO, which the rule treats the same. /dev/null itself
is only ever given to :func:`check_output` (which writes nothing) and checked to be a device afterwards.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.outputs import OutputError, check_output, check_replaceable, existing_kind
from rigctl.storage.session import SessionWriter, TrialData


def _session(path: Path, n_trials: int = 2) -> Path:
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0, force_g=500.0, duration_s=0.1)
            for i in range(n_trials)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 't'") as w:
        for i in range(n_trials):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (100, 18)), seq=np.arange(100),
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    return path


def _device(path: Path) -> Path:
    """A character device (1, 3: what /dev/null is) at ``path``, or a FIFO where mknod is not allowed."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except (PermissionError, OSError):
        os.mkfifo(path)
    return path


def _unchanged_device(path: Path) -> bool:
    mode = os.lstat(path).st_mode
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


def test_dev_null_is_refused_and_left_a_device():
    for kind in ("session", "encoded", "nwb", None):
        with pytest.raises(OutputError, match="is a device, not a regular file"):
            check_output("/dev/null", overwrite=True, kind=kind)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_the_rule_file_by_file(tmp_path):
    session = _session(tmp_path / "s.h5")
    assert existing_kind(session) == "session"
    text = tmp_path / "notes.h5"
    text.write_text("someone's notes")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = [1]
    (tmp_path / "empty.h5").touch()
    assert [existing_kind(p) for p in (text, other, tmp_path / "empty.h5")] == ["other", "hdf5", "empty"]
    check_replaceable(session, kind="session")  # its own kind: replaced
    check_replaceable(text)  # no kind (CSV, figures): any regular file
    refusals = {text: ("session", "a file of another program"), other: ("session", "an HDF5 file of another program"),
                session: ("encoded", "is a rigctl session file, not a rigctl encoded file"),
                tmp_path / "empty.h5": ("nwb", "an empty file"), tmp_path: (None, "is a folder")}
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    refusals[fifo] = (None, "is a FIFO")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "target.h5").write_bytes(session.read_bytes())
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "link.h5").symlink_to(outside / "target.h5")
    refusals[folder / "link.h5"] = ("session", "outside its folder")
    for path, (kind, words) in refusals.items():
        with pytest.raises(OutputError, match=words) as err:
            check_replaceable(path, kind=kind)
        assert "\n" not in str(err.value)
    check_replaceable(tmp_path / "missing.h5", kind="session")  # nothing there: nothing to refuse


def test_session_writer_overwrite_onto_a_non_session_is_refused_and_the_file_unchanged(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("keep")
    with pytest.raises(OutputError, match="not a rigctl session"):
        SessionWriter.create(text, plan=[dict(trial_id=0, texture="A", speed_mm_s=40.0, force_g=500.0,
                                              duration_s=0.1)], overwrite=True)
    assert text.read_text() == "keep"
    dev = _device(tmp_path / "dev.h5")
    with pytest.raises(OutputError, match="not a regular file"):
        SessionWriter.create(dev, plan=[], overwrite=True)
    assert _unchanged_device(dev) and not list(tmp_path.glob("dev.h5.*"))


def test_encode_acquire_export_overwrite_onto_a_device_are_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    session = _session(tmp_path / "s.h5")
    dev = _device(tmp_path / "dev.h5")
    nwb_dev = _device(tmp_path / "dev.nwb")
    text = tmp_path / "notes.h5"
    text.write_text("keep")
    runs = {
        "encode": ["encode", str(session), "--out", str(dev), "--overwrite"],
        "encode onto a text file": ["encode", str(session), "--out", str(text), "--overwrite"],
        "acquire": ["acquire", "quick_check", "--inprocess", "--out", str(dev), "--overwrite"],
        "acquire onto a text file": ["acquire", "quick_check", "--inprocess", "--out", str(text),
                                     "--overwrite"],
        "export": ["export", "nwb", str(session), "--out", str(nwb_dev), "--overwrite"],
    }
    for name, args in runs.items():
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 2, (name, r.output)
        line = r.output.strip().splitlines()[0]
        assert ("not a regular file" in line or "not a rigctl" in line) and "Traceback" not in r.output, (name, line)
    assert _unchanged_device(dev) and _unchanged_device(nwb_dev) and text.read_text() == "keep"
