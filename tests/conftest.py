"""Shared pytest fixtures. Area tests live in tests/<area>/ with their own conftest.py where needed."""

from __future__ import annotations

import getpass
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import NoReturn

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TESTS = Path(__file__).resolve().parent

#: folders of tests/ whose every test is of one kind (markers registered in pyproject.toml)
FOLDER_MARKERS = {"gui": ["gui"], "conformance": ["slow"]}


#: liblsl's configuration for the tests (docs/lsl.md: how it was checked that nothing leaves the host)
LSL_API_CFG = """[ports]
IPv6 = disable

[multicast]
ResolveScope = machine
ListenAddress = 127.0.0.1

[lab]
KnownPeers = {127.0.0.1}
"""


def scratch_dir() -> Path:
    """``$TMPDIR/rigctl-tests-<user>``: what the suite keeps between runs (the firmware build of the current
    sources, Hypothesis' examples), outside the checkout."""
    return Path(tempfile.gettempdir()) / f"rigctl-tests-{getpass.getuser()}"


def pytest_configure(config):
    """Keep the checkout clean: the firmware builds (``rigctl.firmware.build_dir`` honours $RIGCTL_FIRMWARE_BUILD),
    numba's kernel cache and Hypothesis' storage go under :func:`scratch_dir` unless the caller chose a place
    (scripts/test.sh does)."""
    from hypothesis.configuration import set_hypothesis_home_dir

    from rigctl import firmware

    scratch = scratch_dir()
    # numba's compiled kernels (cache=True) would go to __pycache__ beside the sources; workers and the CLI
    # subprocesses share this folder (read by numba when it is first imported: nothing has imported it yet)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(scratch / "numba"))
    if not os.environ.get("RIGCTL_FIRMWARE_BUILD"):
        digest = firmware.source_digest()[:16]
        os.environ["RIGCTL_FIRMWARE_BUILD"] = str(scratch / f"firmware-{digest}")
    set_hypothesis_home_dir(os.environ.get("HYPOTHESIS_STORAGE_DIRECTORY") or scratch / "hypothesis")
    # the rig's own safety log and the server's queue ($XDG_STATE_HOME/rigctl) never in the user's home; a test that
    # reads them sets its own (monkeypatch.setenv), which CLI subprocesses inherit
    os.environ["XDG_STATE_HOME"] = str(scratch / "state")
    # the simulated rigs a command opens for itself (`--sim`, `--replay`, `--hil`; CLI subprocesses inherit it) run
    # unpaced on the clock they share with their host (docs/architecture.md "Time on a simulated rig"): as fast as the
    # CPU and the host's grants allow, a starved host pausing them; a person's default is the wall clock. A test of the
    # wall itself sets RIGCTL_SIM_PACE=wall (the README's first command beside four CPU hogs)
    os.environ.setdefault("RIGCTL_SIM_PACE", "none")
    # LSL on this machine alone (liblsl reads LSLAPICFG when it first resolves or opens a stream; CLI subprocesses
    # inherit it): discovery only to 127.0.0.1, never a multicast or broadcast address, no IPv6; never $HOME's file
    cfg_dir = Path(tempfile.mkdtemp(prefix="rigctl-lsl-"))
    (cfg_dir / "lsl_api.cfg").write_text(LSL_API_CFG)
    os.environ["LSLAPICFG"] = str(cfg_dir / "lsl_api.cfg")
    config._rigctl_lsl_cfg_dir = cfg_dir
    own_session_per_worker()


def own_session_per_worker() -> None:
    """A pytest-xdist worker leads a session of its own (``setsid``), and so, with Linux's autogroups
    (``/proc/sys/kernel/sched_autogroup_enabled``, on by default), a scheduling group of its own, with the simulated
    rigs, simavr harnesses and CLI subprocesses it starts. In one session, the whole suite and the CPU hogs started
    beside it (a shell's ``.ci/run`` and its ``while :; do :; done`` loops) shared one group, and the kernel worker
    that hands a pty's bytes from writer to reader (``flush_to_ldisc`` on the unbound workqueue, outside every
    session's group) sat runnable for seconds while that group's threads ran: traced (ftrace, Linux 6.18), a
    kworker woken at once ran 2.3 s later; a plain 8-byte pty hop beside 40 threads waking every 1-5 ms and two hogs,
    all in one session, took up to 7.4-26.6 s, each in a session of its own at most 3 ms
    (benchmarks/bench_pty_hop.py). Those hops were the loaded runs' DrumTimeouts, stalled guides and slow STOPs
    (issue 54). A worker has no terminal of its own to lose, and the tests that press Ctrl-C send it to the process
    they started. The controller (not a worker) stays in the caller's session; a terminal's Ctrl-C now reaches only
    it, and its KeyboardInterrupt ends the workers (a run of two 60 s tests ended 2-8 s after Ctrl-C, with the
    workers in sessions of their own or not, none left behind)."""
    if os.environ.get("PYTEST_XDIST_WORKER") and os.getsid(0) != os.getpid():
        try:
            os.setsid()
        except OSError:  # already a process group's leader: stays where it is
            pass


@pytest.hookimpl(trylast=True, specname="pytest_configure")
def pytest_configure_pyside_source_check(config):
    """PySide6 (imported by pytest-qt when it configures, before the tests are collected) asks of every module
    imported after it whether its source names PySide6 (its ``__feature__`` switch: PYSIDE-2029), through
    ``inspect.getsource``: ~0.25 ms a module, ~15-20 % of what a test worker spends importing the ~2,500 modules its
    tests load. The same question answered by reading the file (the same verdict for every module a worker loads;
    PySide6's own check for anything but a ``.py`` file): ~0.7 CPU-s less a worker."""
    import sys

    feature = sys.modules.get("PySide6.support.feature")
    slow = getattr(feature, "_mod_uses_pyside", None)
    if slow is None:
        return

    def mod_uses_pyside(module) -> bool:
        path = getattr(module, "__file__", None)
        if not isinstance(path, str) or not path.endswith(".py"):
            return slow(module)
        try:
            with open(path, "rb") as f:
                return b"PySide6" in f.read()
        except OSError:
            return slow(module)

    feature._mod_uses_pyside = mod_uses_pyside


@pytest.fixture(autouse=True)
def _ctrl_c_reaches_children():
    """Before each test, SIGINT is handled in this process at the OS level, as in a terminal: a test that presses
    Ctrl-C on a child needs the child to hear it, and an ignored signal stays ignored across fork and exec. A shell
    starts a background job (``.ci/run &`` in a script, as CI may) with SIGINT ignored, and code below Python can
    switch it to ignored behind ``signal.getsignal``'s back; either way every child Python then started with
    KeyboardInterrupt off (CI: ``rigctl sim`` ran on for 120 s after its Ctrl-C, a commit's Ctrl-C was never seen).
    Re-installing the Python-level handler re-installs it in the kernel."""
    if threading.current_thread() is threading.main_thread():
        handler = signal.getsignal(signal.SIGINT)
        if handler in (None, signal.SIG_IGN, signal.SIG_DFL):
            handler = signal.default_int_handler
        signal.signal(signal.SIGINT, handler)
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """With ``$RIGCTL_TEST_CPU_LOG`` set (a file path), append one line per test: its node id, wall seconds and CPU
    seconds (this process and the children it reaped meanwhile: CLI subprocesses, and a module's simavr harnesses
    when its rig closes), then the worker (pytest-xdist's id), when the test started (Unix time) and the CPU seconds of the worker's whole
    process tree (:func:`tree_cpu`), tab-separated:
    where the suite's CPU goes, which ``--durations`` (wall) cannot say, and what ran beside what."""
    path = os.environ.get("RIGCTL_TEST_CPU_LOG")
    if not path:
        yield
        return
    import resource
    import time

    def cpu() -> float:
        a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    def tree_cpu() -> float:
        """:func:`cpu` plus the live descendants' CPU and that of the children they reaped (/proc/PID/stat fields
        14-17, clock ticks): the preloaded launcher's commands and the harnesses still running count too."""
        stats: dict[int, tuple[int, float]] = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    with open(f"/proc/{entry}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                except OSError:
                    continue
                stats[int(entry)] = (int(fields[1]), sum(int(x) for x in fields[11:15]) / os.sysconf("SC_CLK_TCK"))
        children: dict[int, list[int]] = {}
        for pid, (ppid, _) in stats.items():
            children.setdefault(ppid, []).append(pid)
        total, todo = cpu(), list(children.get(os.getpid(), []))
        while todo:
            pid = todo.pop()
            total += stats[pid][1]
            todo.extend(children.get(pid, []))
        return total

    t0, c0, tc0, start = time.monotonic(), cpu(), tree_cpu(), time.time()
    yield
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(path, "a") as f:
        f.write(f"{item.nodeid}\t{time.monotonic() - t0:.2f}\t{cpu() - c0:.2f}\t{worker}\t{start:.1f}"
                f"\t{tree_cpu() - tc0:.2f}\n")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own starts the workers
def pytest_sessionstart(session):
    """numba's kernels compiled into the run's cache before its first test, outside every test's timeout (issue 79
    item 7: a module run as the README says timed out at 300 s on a cold cache at load ~55, its first test compiling
    them): scripts/compile_kernels.py's two parts side by side, each only when its stamp is stale (nothing to do on a
    warm cache, as after scripts/test.sh's own compile). Once per run: in the controller of a parallel run."""
    if hasattr(session.config, "workerinput") or session.config.option.collectonly:
        return
    script = Path(__file__).resolve().parents[1] / "scripts" / "compile_kernels.py"
    procs = [subprocess.Popen([sys.executable, str(script), "--if-stale", part], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for part in ("serial", "parallel")]
    for proc in procs:
        out, _ = proc.communicate()
        if out.strip():
            session.config.get_terminal_writer().line(out.strip().splitlines()[-1])


#: the tiers whose tests judge against the wall clock (a live view's frame rate, LSL timing, a real pty's latency; a
#: real window): on a saturated machine one of them can fail for want of CPU, not of correctness. The simulated rigs'
#: tests (conformance, firmware under simavr, faults, packaging's commands) are not among them: their boards and their
#: host share one clock, and a starved host pauses its boards (docs/architecture.md "Time on a simulated rig"), so a
#: failure there is a failure
WALL_CLOCK_TIERS = ("realtime", "gui")


def pytest_runtest_logreport(report):
    """With ``$RIGCTL_FAILURES_LOG`` set (a file path), append one line per failed test: its node id and its tier,
    ``wall`` (one of :data:`WALL_CLOCK_TIERS`) or ``logic``, tab-separated. A failed attempt that
    pytest-rerunfailures runs again (:func:`wall_clock_reruns`) is reported as ``rerun``, not failed: only a test's
    last verdict is logged. scripts/test.sh reruns a run's wall-clock failures alone, one at a time, once the
    parallel run is over (the CPU then free), and fails on any logic failure and any wall-clock test that fails again
    alone. (Both an xdist worker and the controller see each report: the script takes each node id once.)"""
    path = os.environ.get("RIGCTL_FAILURES_LOG")
    if path and report.failed:
        tier = "wall" if any(m in report.keywords for m in WALL_CLOCK_TIERS) else "logic"
        with open(path, "a") as f:
            f.write(f"{report.nodeid}\t{tier}\t{report.when}\n")
    log_rerun(report)


def log_rerun(report) -> None:
    """With ``$RIGCTL_RERUNS_LOG`` set (a file path), append one line per failed attempt that pytest-rerunfailures
    runs again: node id, phase and the first line of why it failed, tab-separated (pytest's summary lists a rerun
    with no reason: a loaded CI run reran test_gui_handheld's stop/resume and left no word of which wait ran out).
    Written by the process that reports to the terminal only (the controller of a parallel run), so once per attempt;
    scripts/test.sh prints the log at the end of its run."""
    path = os.environ.get("RIGCTL_RERUNS_LOG")
    if not path or report.outcome != "rerun" or os.environ.get("PYTEST_XDIST_WORKER"):
        return
    crash = getattr(report.longrepr, "reprcrash", None)
    why = str(getattr(crash, "message", None) or report.longrepr or "?")
    why = " ".join(why.split())[:400]
    where = f"{crash.path}:{crash.lineno}" if crash is not None else "?"
    with open(path, "a") as f:
        f.write(f"{report.nodeid}\t{report.when}\t{where}\t{why}\n")


def wall_clock_reruns(items) -> None:
    """With ``$RIGCTL_WALL_RERUNS`` set to N > 0 (scripts/test.sh's parallel run), mark each test of a
    :data:`WALL_CLOCK_TIERS` tier ``flaky(reruns=N)``: pytest-rerunfailures runs a failed one again at once, on its
    own worker, while the other workers go on (the run lists it as ``R``/``RERUN``). A wall-clock judgement that
    failed for want of CPU on a saturated machine mostly passes then, without the serial rerun at the end of the run
    (its whole wall time added to the run's: ~25 s for a firmware test). A logic test is never rerun."""
    try:
        reruns = int(os.environ.get("RIGCTL_WALL_RERUNS", "0"))
    except ValueError:
        reruns = 0
    if reruns <= 0:
        return
    for item in items:
        if any(item.get_closest_marker(m) for m in WALL_CLOCK_TIERS):
            item.add_marker(pytest.mark.flaky(reruns=reruns))


def pytest_unconfigure(config):
    import shutil

    cfg_dir = getattr(config, "_rigctl_lsl_cfg_dir", None)
    if cfg_dir is not None:
        shutil.rmtree(cfg_dir, ignore_errors=True)


#: how long a unit of work of each kind takes, roughly (the scheduling order below; the biggest go first)
_KIND_WEIGHT = {"packaging": 4, "hil": 3, "slow": 2, "realtime": 1, "gui": 1}

#: test files whose tests split into units of work by the first part of their parameter id: each value of their
#: module-scoped fixture (a backend, sim or hil; a screen size) sets up its own rig or X server anyway, so the parts can
#: run on two workers
SPLIT_BY_PARAM = ("tests/conformance/", "tests/gui/test_gui_x11.py", "tests/test_guides.py")


def unit_of(nodeid: str) -> str:
    """The unit of work an xdist worker takes whole (--dist loadfile, scripts/test.sh): the test's file, or for
    :data:`SPLIT_BY_PARAM`, ``file[first part of the parameter id]`` (``...[hil]`` for ``...::test_x[hil-external]``)."""
    file = nodeid.split("::", 1)[0]
    if file.startswith(SPLIT_BY_PARAM) and nodeid.endswith("]") and "[" in nodeid:
        return f"{file}[{nodeid.split('[', 1)[1][:-1].split('-', 1)[0]}]"
    return file


#: seconds each unit of work took in a clean-clone run of the test command (scripts/unit_seconds.py writes it from a
#: $RIGCTL_TEST_CPU_LOG): only the order the units are handed out in; a stale or missing entry changes no result
UNIT_SECONDS = TESTS / "unit_seconds.json"


def unit_seconds() -> dict[str, float]:
    """:data:`UNIT_SECONDS` as {unit: seconds} ({} when missing or unreadable)."""
    import json

    try:
        data = json.loads(UNIT_SECONDS.read_text())
        return {str(k): float(v) for k, v in data.items()}
    except (OSError, ValueError, AttributeError):
        return {}


def pytest_collection_modifyitems(config, items):
    folders: dict[Path, str | None] = {}  # a test file's folder under tests/ (None: a file of tests/ itself, or outside)
    for item in items:
        if item.path not in folders:  # (resolved once a file, not twice an item: ~0.1 CPU-s of each worker's start)
            resolved = item.path.resolve()
            rel = resolved.relative_to(TESTS).parts if resolved.is_relative_to(TESTS) else ()
            folders[item.path] = rel[0] if len(rel) > 1 else None
        folder = folders[item.path]
        if folder is not None:
            for name in FOLDER_MARKERS.get(folder, []):
                item.add_marker(name)
    wall_clock_reruns(items)
    # the longest units first (packaging, firmware under simavr, slow, real-time rigs), so that with a few workers
    # none starts a ten-minute module last; within a unit, and between units of one cost, collection order is kept
    units: dict[str, list] = {}
    for item in items:
        units.setdefault(unit_of(item.nodeid), []).append(item)

    measured = unit_seconds()

    def cost(unit: str) -> tuple[float, int, int]:
        weights = [max((w for k, w in _KIND_WEIGHT.items() if it.get_closest_marker(k)), default=0)
                   for it in units[unit]]
        # a unit's measured seconds first (longest first is the best list schedule for a few workers); a new unit,
        # not measured yet, by its kinds: packaging and hil ones among the long, the rest among the short
        return measured.get(unit, 20.0 * max(weights)), max(weights), sum(weights)

    order = sorted(units, key=cost, reverse=True)  # stable: ties keep collection order
    items[:] = [it for u in order for it in units[u]]


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` by :func:`unit_of` (a file, or the parameter parts of one), handed out in the order
    :func:`pytest_collection_modifyitems` gives (longest first) instead of xdist's (most tests first)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class UnitScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return unit_of(nodeid)

    config.option.loadscopereorder = False
    return UnitScheduling(config, log)


def skip_or_fail(reason: str, ci_reason: str | None = None) -> NoReturn:
    """Skip the test for ``reason`` (a tool, library or data folder this machine lacks); under ``CI=true``, where
    scripts/test.sh installs everything, fail it instead, with ``ci_reason`` (default ``reason``)."""
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(reason if ci_reason is None else ci_reason)
    pytest.skip(reason)


def wait_unlocked(path, timeout_s: float = 20.0) -> None:
    """Wait until no process holds ``path``'s lock (flock), as a reader after a ``kill -9`` of its writer waits: the
    writer's commit helper (rigctl.storage.journal.apply_journal) outlives it by design and holds the lock until it
    has finished its in-place writes, milliseconds on an idle machine, longer on a loaded one. AssertionError after
    ``timeout_s``."""
    import fcntl
    import time

    deadline = time.monotonic() + timeout_s
    with open(path, "rb") as fh:
        while True:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
                return
            except BlockingIOError:
                assert time.monotonic() < deadline, f"{path} still locked after {timeout_s} s"
                time.sleep(0.01)


def wait_for(pred, timeout_s: float = 120.0, every_s: float = 0.02):
    """``pred()``'s first truthy value, asked every ``every_s``; AssertionError after ``timeout_s`` (a bound on a
    hang, not a judgement)."""
    import time

    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        value = pred()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError(f"timed out after {timeout_s} s")


def shared_path(*parts: str) -> Path:
    """Path under ``../shared/`` beside the repo. Skips the test if missing, fails it under ``CI=true``."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        msg = f"{path} is missing (the shared data beside the repo)"
        skip_or_fail(msg, msg + "; under CI=true it must be present")
    return path


def require_lsl():
    """pylsl with a working liblsl: skip with the reason when it cannot load (a failure under ``CI=true``)."""
    try:
        import pylsl

        pylsl.library_version()
    except Exception as exc:  # noqa: BLE001 - ImportError, RuntimeError (no liblsl), OSError
        msg = f"pylsl's liblsl is unavailable ({type(exc).__name__}: {exc})"
        skip_or_fail(msg, msg + "; under CI=true it must be installed (pip install 'rigctl[lsl]')")
    return pylsl


@pytest.fixture(scope="session")
def build_tools() -> None:
    """The firmware's build tools (:data:`rigctl.firmware.BUILD_TOOLS`) are on the PATH: a skip naming the missing
    ones, a failure under ``CI=true`` (scripts/test.sh installs the Debian toolchain)."""
    from rigctl.firmware import missing_build_tools

    missing = missing_build_tools()
    if missing:
        skip_or_fail(f"{', '.join(missing)} not installed (scripts/test.sh installs the Debian toolchain)")


@pytest.fixture
def lsl():
    """pylsl (LSLAPICFG set to the machine-local :data:`LSL_API_CFG`), or a skip / CI failure."""
    return require_lsl()


@pytest.fixture(scope="session")
def rigctl_cmd(tmp_path_factory):
    """The argv prefix of a ``rigctl`` command run by this worker's preloaded interpreter (tests/launcher.py: the
    real command line, forked from a process that has imported rigctl once, without ~3-5 s of CPU to start each),
    to be used where ``[sys.executable, "-m", "rigctl"]`` would be; signals sent to it reach the command."""
    from .launcher import Launcher

    launcher = Launcher(tmp_path_factory.mktemp("launcher"))
    yield launcher.command
    launcher.close()


@pytest.fixture(autouse=True)
def _preloaded_rigctl(request):
    """A test module that declares ``RIGCTL: list[str] = []`` gets it filled with :func:`rigctl_cmd` (its commands
    then run through this worker's preloaded interpreter)."""
    target = getattr(request.module, "RIGCTL", None)
    if isinstance(target, list) and not target:
        target[:] = request.getfixturevalue("rigctl_cmd")


@pytest.fixture(scope="session")
def scratch() -> Path:
    """:func:`scratch_dir`, created: for what a test keeps between runs (never the checkout)."""
    path = scratch_dir()
    path.mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture
def fabricslide_dir() -> Path:
    """``../shared/data/fabricslide`` (skip if missing, fail under CI=true)."""
    return shared_path("data", "fabricslide")


@pytest.fixture
def paper_path() -> Path:
    return shared_path("paper", "000_e930b09eb5eda72e.txt")


@pytest.fixture(scope="session")
def cli_commands():
    """Every command of ``rigctl`` as (words after ``rigctl``, click command), groups that run on their own
    (``rigctl sim``) included, in ``rigctl --help``'s order: what a test that must cover every command iterates."""
    import click

    from rigctl.cli import main

    found = []

    def walk(cmd, words, ctx):
        if not isinstance(cmd, click.Group) or cmd.invoke_without_command:
            found.append((tuple(words), cmd))
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                walk(sub, [*words, name], click.Context(sub, parent=ctx, info_name=name))

    walk(main, [], click.Context(main, info_name="rigctl"))
    return [(words, cmd) for words, cmd in found if words]


#: the out-of-tree rig plugin the tests install (docs/guides/my-hardware.md shows its source)
CSVBOARD_PLUGIN = Path(__file__).resolve().parent / "plugins" / "rigctl-csvboard"


@pytest.fixture(scope="session")
def csvboard_plugin(tmp_path_factory) -> Path:
    """The folder tests/plugins/rigctl-csvboard is installed into (``pip install --no-deps --no-build-isolation
    --target``, from a copy: nothing is built in the checkout; a few seconds), beside a broken plugin's metadata
    (``broken``: its module does not exist). Put it on ``PYTHONPATH`` (a subprocess) or ``sys.path``
    (:func:`installed_plugins`) and rigctl finds both rigs through their entry points."""
    import shutil
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("plugins")
    src = shutil.copytree(CSVBOARD_PLUGIN, root / "src", ignore=shutil.ignore_patterns("build", "*.egg-info"))
    target = root / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-warn-script-location", "--disable-pip-version-check", "--target", str(target), str(src)],
                   check=True, capture_output=True, text=True, cwd=root)
    broken = target / "rigctl_broken-0.1.0.dist-info"
    broken.mkdir()
    (broken / "METADATA").write_text("Metadata-Version: 2.1\nName: rigctl-broken\nVersion: 0.1.0\n")
    (broken / "entry_points.txt").write_text("[rigctl.rigs]\nbroken = rigctl_broken_missing:open_rig\n")
    return target


@pytest.fixture
def installed_plugins(csvboard_plugin, monkeypatch):
    """:func:`csvboard_plugin` on this process's ``sys.path`` for one test (rigctl's list of rigs read again before
    and after it)."""
    from rigctl.core.rig_plugins import rig_entries

    monkeypatch.syspath_prepend(str(csvboard_plugin))
    rig_entries.cache_clear()
    yield csvboard_plugin
    monkeypatch.undo()
    rig_entries.cache_clear()


def small_handheld_protocol(*textures: str) -> str:
    """A handheld protocol's TOML (issue 37's tests): ``textures`` (default B, L), one scan of each with the profiles
    fast (120 mm/s) and slow-to-fast (40 -> 120 mm/s)."""
    labels = ", ".join(f'"{t}"' for t in (textures or ("B", "L")))
    return f"""
name = "handheld_small"
rig = "handheld"
textures = [{labels}]
forces_g = [500]
trials_per_condition = 1
travel_mm = 200

[[profiles]]
name = "fast"
kind = "constant"
speed_mm_s = 120

[[profiles]]
name = "slow-to-fast"
kind = "ramp"
start_mm_s = 40
end_mm_s = 120
"""
