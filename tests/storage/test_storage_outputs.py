"""The one output policy (rigctl.storage.outputs) as every writer uses it: the one-writer lock, a full disk, modes.

The full-disk tests write onto a real tmpfs of a few KiB when this process may mount one (root); otherwise they
limit the file size of the child process (RLIMIT_FSIZE, SIGXFSZ ignored: writes past the limit fail with EFBIG),
which takes the same path through HDF5 and the guard. Either way the command runs in its own process: the bug was
a segfault (139) or a bus error (135) inside h5py, which would take pytest down with it. Those processes are forked
from one interpreter of this module's (:func:`forker`) that has imported the CLI, the encoder and the NWB writer once:
a fresh ``python -m rigctl`` paid ~2 CPU-s of imports for a fraction of a second of work.

The command-line tests import nothing but the session writer and the CLI, so that they run unchanged against an
older rigctl (issue 24's "failing on today's main": 78d85b9).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData, open_session

RATE = 1000.0


def _session(path: Path, n_trials: int = 6, duration_s: float = 0.2, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0 + 40 * (i % 3), force_g=500.0,
                 duration_s=duration_s) for i in range(n_trials)]
    n = int(round(duration_s * RATE))
    with SessionWriter.create(path, plan=plan, protocol_source="name = 't'") as w:
        for i in range(n_trials):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (n, 18)), seq=np.arange(n) % 65536,
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    return path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


#: the forking interpreter: imports what the commands use, then per request line (JSON: argv as ``python`` takes it,
#: the file-size limit or null, the files for stdout and stderr) forks a child that runs it as ``python ARGV`` would
#: (``-m MODULE`` or ``-c CODE``; exit status as the interpreter's), waits for it and answers its status (negative:
#: the signal that ended it, as subprocess says)
_FORKER = """
import json, os, resource, runpy, signal, sys, traceback
import rigctl.cli, rigctl.encoding.pipeline, rigctl.storage.nwb
print("ready", flush=True)
for line in sys.stdin:
    argv, limit, out, err = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            for fd, path in ((1, out), (2, err)):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                os.dup2(f, fd)
                os.close(f)
            if limit is not None:
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
            if argv[0] == "-m":
                sys.argv = [argv[1], *argv[2:]]
                runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
            else:
                sys.argv = ["-c", *argv[2:]]
                exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})
            code = 0
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    print(os.waitstatus_to_exitcode(status), flush=True)
"""


@pytest.fixture(scope="module")
def forker():
    """The forking interpreter (:data:`_FORKER`), for this module's tests; waited for at the end."""
    proc = subprocess.Popen([sys.executable, "-c", _FORKER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    yield proc
    proc.stdin.close()
    proc.wait(60)


def _rigctl(forker, tmp_path: Path, *args: str, limit_bytes: int | None = None,
            module: bool = True) -> subprocess.CompletedProcess:
    """``python -m rigctl ARGS`` (``python ARGS`` when not ``module``) in a child process (forked by ``forker``),
    its file size limited to ``limit_bytes`` when given."""
    argv = ["-m", "rigctl", *args] if module else list(args)
    out, err = tmp_path / f"out-{uuid.uuid4().hex[:6]}", tmp_path / f"err-{uuid.uuid4().hex[:6]}"
    forker.stdin.write(json.dumps([argv, limit_bytes, str(out), str(err)]) + "\n")
    forker.stdin.flush()
    code = int(forker.stdout.readline())
    return subprocess.CompletedProcess(argv, code, out.read_text(), err.read_text())


@pytest.fixture
def session(tmp_path):
    return _session(tmp_path / "s.h5")


@pytest.fixture
def small_disk(tmp_path):
    """(folder, child file-size limit or None): a 48 KiB tmpfs when it can be mounted, else a plain folder and a
    48 KiB RLIMIT_FSIZE for the command's process."""
    d = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    d.mkdir()
    mounted = shutil.which("mount") is not None and os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=48k", "tmpfs", str(d)], capture_output=True).returncode == 0
    yield d, None if mounted else 48 * 1024
    if mounted:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


# -- the one-writer lock ---------------------------------------------------------------------------------------
def test_encode_overwrite_onto_a_session_being_recorded_is_refused_and_the_recording_finishes(tmp_path, session,
                                                                                               forker):
    live = tmp_path / "live.h5"
    n = 200
    plan = [dict(trial_id=i, texture="A", speed_mm_s=40.0, force_g=500.0, duration_s=0.2) for i in range(3)]
    rng = np.random.default_rng(3)
    trial = lambda: TrialData(taxels=rng.integers(0, 1024, (n, 18)), seq=np.arange(n),  # noqa: E731
                              force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0])
    with SessionWriter.create(live, plan=plan, protocol_source="name = 'live'") as w:  # the recorder
        w.write_trial(0, trial())
        before = _digest(live)
        r = _rigctl(forker, tmp_path, "encode", str(session), "--out", str(live), "--overwrite", "--quiet")
        assert r.returncode == 2, r.stderr
        assert "being written by" in r.stderr and len(r.stderr.strip().splitlines()) == 1
        assert _digest(live) == before
        w.write_trial(1, trial())  # the recorder goes on and finishes
        w.write_trial(2, trial())
    with open_session(live) as s:
        assert s.completed_ids() == [0, 1, 2]


def test_every_writer_checks_the_lock(tmp_path, session):
    from rigctl.encoding.pipeline import encode_session
    from rigctl.storage.journal import WriterLock
    from rigctl.storage.nwb import export_nwb
    from rigctl.storage.outputs import OutputLocked, check_output, output_file, replacing

    out, nwb, csv = (tmp_path / f"held.{ext}" for ext in ("h5", "nwb", "csv"))
    for path in (out, nwb, csv):
        path.write_bytes(b"x")
    locks = [WriterLock(path) for path in (out, nwb, csv)]
    try:
        with pytest.raises(OutputLocked):
            check_output(out, overwrite=True)
        with pytest.raises(OutputLocked):
            with output_file(out, overwrite=True):
                pass
        with pytest.raises(OutputLocked):
            with replacing(out):
                pass
        with pytest.raises(OutputLocked):
            encode_session(session, out, overwrite=True, progress=None)
        with pytest.raises(OutputLocked):
            export_nwb(session, out, overwrite=True)
        from rigctl.storage.model_file import save_model
        from rigctl_gui.analysis_jobs import encode as gui_encode  # the GUI's worker (no Qt in it)

        with pytest.raises(OutputLocked):
            gui_encode(str(session), str(out))
        with pytest.raises(OutputLocked):  # the GUI's and analyze --save-model's model file
            save_model({"a": 1}, csv)
        runner = CliRunner()
        for args in (["export", "nwb", str(session), "--out", str(nwb), "--overwrite", "--no-progress"],
                     ["analyze", str(session), "--csv", str(csv), "--overwrite"]):
            r = runner.invoke(main, args)
            assert r.exit_code == 2 and "being written by" in r.stderr, (args, r.output)
        r = runner.invoke(main, ["export", "nwb", str(session), "--out", str(tmp_path / "free.nwb"),
                                 "--no-progress"])
        assert r.exit_code == 0, r.output  # another file: not held
    finally:
        for lock in locks:
            lock.release()
    assert out.read_bytes() == nwb.read_bytes() == csv.read_bytes() == b"x"


# -- a full disk -----------------------------------------------------------------------------------------------
def _blind(*args: str) -> list[str]:
    """``python -c`` running ``rigctl ARGS`` on a file system that does not report its free space (as some network
    file systems do): no space check up front can help, the disk fills during the write itself."""
    return ["-c", "import os, runpy, sys\n"
            "del os.statvfs\n"  # shutil.disk_usage and every free-space estimate fail: nothing known up front
            f"sys.argv = ['rigctl', *{list(args)!r}]\n"
            "runpy.run_module('rigctl', run_name='__main__')"]


@pytest.mark.parametrize("blind", [False, True], ids=["space-checked", "filled-during-the-write"])
@pytest.mark.parametrize("command", ["encode", "export"])
def test_a_full_disk_is_one_line_no_part_file_inputs_unchanged(tmp_path, session, small_disk, command, blind,
                                                                 forker):
    folder, limit = small_disk
    before = _digest(session)
    if command == "encode":
        args = ["encode", str(session), "--out", str(folder / "e.h5"), "--quiet"]
    else:
        args = ["export", "nwb", str(session), "--out", str(folder / "e.nwb"), "--no-progress"]
    r = _rigctl(forker, tmp_path, *(_blind(*args) if blind else args), limit_bytes=limit, module=not blind)
    assert r.returncode in (1, 2), (r.returncode, r.stderr[-3000:])  # 2: refused up front by the space estimate
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr[-3000:]
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    if blind:
        assert r.returncode == 1 and ("no space left" in r.stderr.lower() or "too large" in r.stderr.lower())
    assert list(folder.iterdir()) == []  # no .part, no lock file, no temporary file
    assert _digest(session) == before


def test_a_full_disk_during_the_write_is_caught_by_the_guard(tmp_path, session, small_disk, forker):
    """The library calls (no space estimate): the disk fills in the middle of HDF5's writes."""
    folder, limit = small_disk
    before = _digest(session)
    code = ("from rigctl.encoding.pipeline import encode_session\n"
            "from rigctl.storage.nwb import export_nwb\n"
            "from rigctl.storage.outputs import OutputWriteError\n"
            "import sys\n"
            f"for f, out in ((encode_session, {str(folder / 'e.h5')!r}), (export_nwb, {str(folder / 'e.nwb')!r})):\n"
            "    try:\n"
            f"        f({str(session)!r}, out)\n"
            "    except OutputWriteError as exc:\n"
            "        print('refused:', exc)\n")
    r = _rigctl(forker, tmp_path, "-c", code, limit_bytes=limit, module=False)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.count("refused:") == 2, r.stdout + r.stderr[-2000:]
    assert "the partial output was removed" in r.stdout
    assert list(folder.iterdir()) == []
    assert _digest(session) == before


def test_guarded_file_keeps_refused_writes_readable(tmp_path):
    from rigctl.storage.outputs import GuardedFile, OutputWriteError

    g = GuardedFile(tmp_path / "x")
    g.write(b"abc")
    g.error = OSError(28, "No space left on device")  # as if the disk had refused the next write
    g.seek(1)
    g.write(b"ZZZZ")
    g.seek(0)
    buf = bytearray(5)
    assert g.readinto(buf) == 5 and bytes(buf) == b"aZZZZ"
    assert (tmp_path / "x").read_bytes() == b"abc"  # nothing more reached the disk
    with pytest.raises(OutputWriteError, match="no space left on device"):
        g.check()
    g.truncate(2)  # HDF5 truncates to its end of allocation; what lies beyond reads as zeros if it grows again
    g.seek(4)
    g.write(b"Q")
    g.seek(0)
    buf = bytearray(5)
    assert g.readinto(buf) == 5 and bytes(buf) == b"aZ\x00\x00Q"
    g.close()


# -- modes and refusals -------------------------------------------------------------------------------------------
def test_outputs_honour_the_umask(tmp_path):
    """Sessions were 0644 but encoded files, NWB files and figures 0600 (mkstemp + rename): a colleague on the lab's
    shared drive could not read them. In this process (the umask is the process's)."""
    session = _session(tmp_path / "u.h5", n_trials=8)  # 4 trials per texture: 4-fold CV
    runner = CliRunner()
    old = os.umask(0o022)
    try:
        for args in (["encode", str(session), "--out", str(tmp_path / "e.h5"), "--quiet"],
                     ["export", "nwb", str(session), "--out", str(tmp_path / "e.nwb"), "--no-progress"],
                     ["analyze", str(tmp_path / "e.h5"), "--task", "textures", "--repeats", "1", "--pcs", "1-2",
                      "--per-texture", "4", "--variants", "original", "--plot", str(tmp_path / "fig.png"),
                      "--csv", str(tmp_path / "c.csv"), "--no-progress"]):
            r = runner.invoke(main, args)
            assert r.exit_code == 0, (args, r.output)
    finally:
        os.umask(old)
    for name in ("e.h5", "e.nwb", "fig.png", "c.csv"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name


def test_check_output_refusals(tmp_path, session):
    from rigctl.storage.outputs import OutputError, check_output

    with pytest.raises(OutputError, match="exists"):
        check_output(session)
    with pytest.raises(OutputError, match="one of the input files"):
        check_output(session, overwrite=True, inputs=[session])
    with pytest.raises(OutputError, match="needs about"):
        check_output(tmp_path / "big.h5", need_bytes=1e18)
    with pytest.raises(OutputError, match="does not exist"):
        check_output(tmp_path / "nope" / "x.h5")
