"""The test command's second chance for wall-clock tests (scripts/test.sh, tests/conftest.py): in the parallel run a
failed test of a wall-clock tier runs again at once (pytest-rerunfailures, ``$RIGCTL_WALL_RERUNS``), and only a
test's last verdict reaches the failures log the script reruns from; a logic test never gets a second run, nor does
a firmware test under simavr (its boards share the host's clock: docs/architecture.md "Time on a simulated rig")."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

TESTS = Path(__file__).resolve().parent

#: a sandbox suite: one wall-clock test that fails its first run only, one that always fails, one logic test and one
#: firmware test that fail their first run only (each run counted in a file), and a conftest using the suite's own hooks
SANDBOX_TESTS = """
import os
from pathlib import Path

import pytest

RUNS = Path(os.environ["SANDBOX_RUNS"])


def runs(name):
    f = RUNS / name
    n = int(f.read_text()) if f.exists() else 0
    f.write_text(str(n + 1))
    return n + 1


# wall: the sandbox's wall-clock test
@pytest.mark.realtime
def test_wall_fails_once():
    assert runs("wall_once") > 1


@pytest.mark.gui
def test_wall_always_fails():
    runs("wall_always")
    assert False


def test_logic_fails_once():
    assert runs("logic_once") > 1


@pytest.mark.hil
def test_firmware_fails_once():
    assert runs("firmware_once") > 1
"""

SANDBOX_CONFTEST = """
import importlib.util

spec = importlib.util.spec_from_file_location("suite_conftest", {conftest!r})
suite = importlib.util.module_from_spec(spec)
spec.loader.exec_module(suite)
pytest_runtest_logreport = suite.pytest_runtest_logreport


def pytest_configure(config):
    for tier in (*suite.WALL_CLOCK_TIERS, "hil"):
        config.addinivalue_line("markers", tier)


def pytest_collection_modifyitems(config, items):
    suite.wall_clock_reruns(items)
"""


def _run(tmp_path: Path, reruns: str | None) -> tuple[subprocess.CompletedProcess, dict[str, int], list[str]]:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_sandbox.py").write_text(textwrap.dedent(SANDBOX_TESTS))
    (suite / "conftest.py").write_text(SANDBOX_CONFTEST.format(conftest=str(TESTS / "conftest.py")))
    runs, log = tmp_path / "runs", tmp_path / "failures.log"
    runs.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("RIGCTL_WALL_RERUNS", "RIGCTL_FAILURES_LOG", "RIGCTL_RERUNS_LOG", "PYTEST_XDIST_WORKER")}
    env.update(SANDBOX_RUNS=str(runs), RIGCTL_FAILURES_LOG=str(log), RIGCTL_RERUNS_LOG=str(tmp_path / "reruns.log"),
               PYTHONDONTWRITEBYTECODE="1")
    if reruns is not None:
        env["RIGCTL_WALL_RERUNS"] = reruns
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-r", "fER",
                        "--rootdir", str(suite), "-c", os.devnull, str(suite)],
                       capture_output=True, text=True, cwd=suite, env=env, timeout=120)
    counts = {p.name: int(p.read_text()) for p in runs.iterdir()}
    lines = sorted(set(log.read_text().splitlines())) if log.exists() else []
    return r, counts, lines


def test_a_wall_clock_failure_runs_again_at_once_and_only_last_verdicts_are_logged(tmp_path):
    r, counts, logged = _run(tmp_path, "1")
    assert r.returncode == 1, r.stdout[-2000:]
    # the wall-clock tests ran twice each, the logic and the firmware test once
    assert counts == {"wall_once": 2, "wall_always": 2, "logic_once": 1, "firmware_once": 1}, counts
    assert "RERUN test_sandbox.py::test_wall_fails_once" in r.stdout, r.stdout[-2000:]
    assert "2 rerun" in r.stdout and "3 failed, 1 passed" in r.stdout, r.stdout[-800:]
    # the reruns log: each attempt run again, with why it failed (the assertion pytest's summary leaves out)
    reruns = (tmp_path / "reruns.log").read_text().splitlines()
    assert [line.split("\t")[:2] for line in reruns] == [["test_sandbox.py::test_wall_fails_once", "call"],
                                                        ["test_sandbox.py::test_wall_always_fails", "call"]], reruns
    assert all("test_sandbox.py:" in line and "assert" in line.split("\t")[3] for line in reruns), reruns
    # the failures log: what failed in the end, with its tier (the one that passed on its second run is not there)
    assert logged == ["test_sandbox.py::test_firmware_fails_once\tlogic\tcall",
                      "test_sandbox.py::test_logic_fails_once\tlogic\tcall",
                      "test_sandbox.py::test_wall_always_fails\twall\tcall"], logged


def test_without_the_setting_nothing_is_rerun(tmp_path):
    """A developer's own pytest run (and the script's serial rerun at the end) judges each test once."""
    r, counts, logged = _run(tmp_path, None)
    assert r.returncode == 1
    assert counts == {"wall_once": 1, "wall_always": 1, "logic_once": 1, "firmware_once": 1}, counts
    assert "rerun" not in r.stdout.splitlines()[-1] and not (tmp_path / "reruns.log").exists()
    assert [line.split("\t")[:2] for line in logged] == [
        ["test_sandbox.py::test_firmware_fails_once", "logic"], ["test_sandbox.py::test_logic_fails_once", "logic"],
        ["test_sandbox.py::test_wall_always_fails", "wall"], ["test_sandbox.py::test_wall_fails_once", "wall"]]


#: the folders whose tests run on the clock their simulated boards share with the host: never the real-time tier
SHARED_CLOCK_FOLDERS = ("conformance", "firmware")


def realtime_marks() -> list[tuple[str, int, str]]:
    """Every ``pytest.mark.realtime`` of the suite's files (a test's or a module's): (file, line, the first line of the
    comment block right above it, '' if none)."""
    import re

    tests = Path(__file__).resolve().parent
    marks = []
    for path in sorted(tests.rglob("*.py")):
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            if not re.match(r"\s*(@pytest\.mark\.realtime\b|pytestmark\s*=.*\bpytest\.mark\.realtime\b)", line):
                continue
            j = i
            while j > 0 and re.match(r"\s*#", lines[j - 1]):
                j -= 1
            head = lines[j].strip() if j < i else ""
            marks.append((path.relative_to(tests).as_posix(), i + 1, head))
    return marks


def test_every_realtime_mark_says_why_and_none_is_in_a_shared_clock_folder():
    """Issue 54 item 3: the real-time tier (the one with a second run) is small and says why. Each mark has a comment
    right above it: ``# wall: WHY`` (the wall clock is the point: a real window, LSL, a `rigctl sim` process, the fault
    proxy, a Ctrl-C, a deadline of wall time) or ``# wall (not yet moved): WHY`` (a test still waiting on the wall
    clock, or on a board paced to it, where the rig's clock would do: the list of what is left to move). No test of a
    folder that runs on the shared clock (the conformance and firmware tests) is in the tier."""
    marks = realtime_marks()
    assert len(marks) > 10  # (the scan finds them)
    unexplained = [f"{f}:{n}" for f, n, head in marks if not head.startswith(("# wall: ", "# wall (not yet moved): "))]
    assert not unexplained, unexplained
    shared = [f"{f}:{n}" for f, n, _ in marks if f.split("/")[0] in SHARED_CLOCK_FOLDERS]
    assert not shared, shared


#: a sandbox suite of two modules, each writing its worker's pid and session id
SESSION_TESTS = """
import os
from pathlib import Path


def test_where_i_run():
    Path(os.environ["SANDBOX_RUNS"], os.environ["PYTEST_XDIST_WORKER"]).write_text(f"{os.getpid()} {os.getsid(0)}")
"""


def test_each_worker_leads_a_session_of_its_own(tmp_path):
    """tests/conftest.py's :func:`own_session_per_worker`: every pytest-xdist worker of a parallel run leads its own
    session (its own scheduling group under Linux's autogroups: the kernel's pty worker is not held back behind one
    group holding the whole suite and the CPU hogs beside it), and the controller stays in the caller's session."""
    suite, runs = tmp_path / "suite", tmp_path / "runs"
    suite.mkdir()
    runs.mkdir()
    for name in ("test_a.py", "test_b.py"):
        (suite / name).write_text(textwrap.dedent(SESSION_TESTS))
    (suite / "conftest.py").write_text(textwrap.dedent(f"""
        import importlib.util

        spec = importlib.util.spec_from_file_location("suite_conftest", {str(TESTS / "conftest.py")!r})
        suite = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(suite)


        def pytest_configure(config):
            suite.own_session_per_worker()
        """))
    env = {**os.environ, "SANDBOX_RUNS": str(runs), "PYTHONDONTWRITEBYTECODE": "1"}
    p = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2",
                          "--dist", "loadfile", "--rootdir", str(suite), "-c", os.devnull, str(suite)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=suite, env=env)
    controller_sid = os.getsid(p.pid)
    out, _ = p.communicate(timeout=120)
    assert p.returncode == 0, out[-2000:]
    assert controller_sid == os.getsid(0)  # the controller: the caller's session
    workers = {f.name: tuple(int(x) for x in f.read_text().split()) for f in runs.iterdir()}
    assert sorted(workers) == ["gw0", "gw1"], (workers, out[-800:])
    for name, (pid, sid) in workers.items():
        assert sid == pid != controller_sid, (name, pid, sid, controller_sid)
