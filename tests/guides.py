"""The runnable blocks of the guides (README.md, docs/my-sensor.md, docs/guides/*.md) and the shell that runs them.

A guide's fenced ``sh`` blocks run in one bash shell, in order, in an empty folder, exactly as written; its
``python`` blocks run there too (``python FILE``: later commands read what they write), and a ``toml`` / ``json`` /
``ini`` block whose first line is a comment naming a file (``# groups.toml``) is written to that file, as is a
``python`` block whose first line names a ``.py`` file (``# rigctl_csvboard/__init__.py``: a module, not run). An HTML
comment on the lines just before a block changes that, visibly in the page's source:

- ``<!-- not-run: REASON -->``: not run here (a real rig's ports, root, a window, a service that runs until Ctrl-C);
  tests/test_guides.py lists every such block with its reason;
- ``<!-- run-by: tests/FILE.py::TEST -->``: run by that test (the install sequences: tests/test_packaging.py);
- ``<!-- small: OLD => NEW | OLD2 => NEW2 -->``: the block runs with OLD replaced by NEW, a smaller size of an option
  the page's text itself shows (the test checks that OLD is in the block and NEW's option is in the page).

A block fails the test when a command in it fails (even the first of ``a && b``) or the output holds a traceback.
"""

from __future__ import annotations

import fcntl
import functools
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import launcher

REPO = Path(__file__).resolve().parents[1]

#: the pages whose blocks run
PAGES = ("README.md", "docs/my-sensor.md", "docs/config.md", *sorted(p.relative_to(REPO).as_posix()
                                                   for p in (REPO / "docs" / "guides").glob("*.md")))

_FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[ \t]*$")
_MARKER = re.compile(r"^\s*<!--\s*(?P<kind>not-run|run-by|small)\s*:\s*(?P<text>.*?)\s*-->\s*$")
_FILE_LANGS = ("toml", "json", "ini", "python")
_FILE_NAME = re.compile(r"^\s*[#;]\s*(?P<name>\w[\w.-]*(?:/\w[\w.-]*)*\.(toml|json|ini|cfg|py))\s*$")


@dataclass
class Block:
    """One fenced block of a page: its language, text (dedented), first line number and markers."""

    page: str
    line: int
    lang: str
    text: str
    markers: dict[str, str] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.page}:{self.line}"

    @property
    def file_name(self) -> str | None:
        """The file a ``toml``/``json``/``ini`` block declares on its first line (``# groups.toml``), else None."""
        if self.lang not in _FILE_LANGS:
            return None
        m = _FILE_NAME.match(self.text.splitlines()[0]) if self.text.strip() else None
        return m.group("name") if m else None

    @property
    def runs_here(self) -> bool:
        """Whether the guide's own test runs this block (an ``sh`` or ``python`` block, or a named file)."""
        if "not-run" in self.markers or "run-by" in self.markers:
            return False
        return self.lang in ("sh", "python") or self.file_name is not None

    def substitutions(self) -> list[tuple[str, str]]:
        """The ``small`` marker's ``(old, new)`` pairs."""
        text = self.markers.get("small", "")
        pairs = []
        for part in filter(None, (p.strip() for p in text.split("|"))):
            old, sep, new = part.partition("=>")
            assert sep, f"{self.name}: a small marker's part needs OLD => NEW: {part!r}"
            pairs.append((old.strip(), new.strip()))
        return pairs

    def as_run(self) -> str:
        """The text as the test runs it (the ``small`` substitutions made)."""
        text = self.text
        for old, new in self.substitutions():
            assert old in text, f"{self.name}: the small marker's {old!r} is not in the block"
            text = text.replace(old, new)
        return text


def blocks(page: str) -> list[Block]:
    """Every fenced block of ``page`` (a path relative to the repo) with the markers just before it."""
    lines = (REPO / page).read_text().splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m or not m.group("lang"):
            i += 1
            continue
        indent, start = m.group("indent"), i
        end = next(j for j in range(i + 1, len(lines)) if lines[j].strip() == "```")
        markers: dict[str, str] = {}
        k = start - 1
        while k >= 0 and (not lines[k].strip() or _MARKER.match(lines[k])):
            mm = _MARKER.match(lines[k])
            if mm:
                markers[mm.group("kind")] = mm.group("text")
            k -= 1
        body = "\n".join(line[len(indent):] if line.startswith(indent) else line for line in lines[start + 1:end])
        out.append(Block(page, start + 1, m.group("lang"), textwrap.dedent(body) + "\n", markers))
        i = end + 1
    return out


def run_by(test: str) -> list[Block]:
    """The blocks of every page marked ``<!-- run-by: TEST -->`` (``tests/FILE.py::NAME``)."""
    return [b for page in PAGES for b in blocks(page) if b.markers.get("run-by") == test]


@dataclass
class BlockRun:
    """What one block printed (stdout and stderr together) and how long it took."""

    block: Block
    output: str
    seconds: float


_TRAP = ('trap \'__s=$?; if [ $__s -ne 0 ]; then echo "@@guide-failed status $__s" >&2; exit 97; fi\' DEBUG\n')


def script(runnable: list[Block], work: Path) -> str:
    """One bash script running ``runnable`` in order, each announced by a ``@@guide-block N`` line; a failing
    command ends it (``set -e`` and a DEBUG trap, which also catches the first command of ``a && b``)."""
    parts = ["set -eo pipefail", _TRAP.strip()]
    for n, b in enumerate(runnable):
        parts.append(f"echo '@@guide-block {n}'")
        if b.file_name:
            (work / b.file_name).parent.mkdir(parents=True, exist_ok=True)
            (work / b.file_name).write_text(b.text)
        elif b.lang == "python":
            name = f".guide-block-{n}.py"
            (work / name).write_text(b.as_run())
            parts.append(f"python {name}")
        else:
            parts.append(b.as_run())
    parts.append("echo '@@guide-block end'")
    return "\n".join(parts) + "\n"


#: what is not the project's source (build output, caches, environments, version control): not copied for the build
_NOT_SOURCE = shutil.ignore_patterns(".git", ".venv*", "build", "dist", "*.egg-info", "__pycache__", ".*_cache",
                                     ".hypothesis", "site")


def copy_of_the_sources(into: Path) -> Path:
    """A copy of the checkout's sources in ``into/rigctl`` (setuptools writes build/ and *.egg-info beside them: never
    into the checkout)."""
    src = into / "rigctl"
    shutil.copytree(REPO, src, symlinks=True, ignore=_NOT_SOURCE)
    return src


#: the extras the guides' own pages install (labrecorder.md's `pip install 'rigctl[lsl]'`, which the handheld
#: page's tracker stream needs too; spiking-networks.md's `pip install 'rigctl[nir]'`): none of the test extras
GUIDE_EXTRAS = ("lsl", "nir")


@dataclass(frozen=True)
class ReadmeEnv:
    """A virtual environment made as the README makes it (``python3 -m venv .venv``: the interpreter's own pip and,
    on 3.11, setuptools), holding the wheel built from the sources with rigctl's dependencies and the guides' own
    extras (:data:`GUIDE_EXTRAS`), none of the test extras; ``seconds`` and ``cpu_s`` its build's cost."""

    venv: Path
    python: Path
    seconds: float
    cpu_s: float

    @property
    def bin(self) -> Path:
        return self.venv / "bin"


def readme_env(root: Path, base_python: str, name: str = "py", *, kernels: bool = True) -> ReadmeEnv:
    """The :class:`ReadmeEnv` of ``base_python`` in ``root/readme-<name>``, built by the first test process that asks
    (the others wait on its lock and reuse it; ``root`` is shared by a run's workers): a copy of the sources, the
    wheel built from it as ``pip install .`` builds it (setup.py's step compiles the model rig's C into it), ``python3
    -m venv``, and the wheel with its dependencies installed into it. The packages come from uv's cache when it holds
    them (the test environment's install put them there: offline, seconds) and from the package index otherwise (a
    first Python 3.12 run); the same packages pip would install. Then (``kernels``) numba's kernels of the installed
    package are compiled into $NUMBA_CACHE_DIR once (scripts/compile_kernels.py run by the new interpreter, whose stamp
    is the test environment's on the same Python), before any guide."""
    folder = root / f"readme-{name}"
    folder.mkdir(parents=True, exist_ok=True)
    venv = folder / ".venv"
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = folder / "ready"
        if not done.is_file():
            t0, cpu0 = time.monotonic(), _children_cpu_s()
            shutil.rmtree(folder / "src", ignore_errors=True)
            src = copy_of_the_sources(folder / "src")
            quiet = dict(capture_output=True, text=True, timeout=900)
            env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PIP_NO_INDEX",
                                                                        "PIP_FIND_LINKS")}
            steps = [
                [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                 str(folder / "wheels"), str(src)],
                [base_python, "-m", "venv", str(venv)],
            ]
            for argv in steps:
                r = subprocess.run(argv, env=env, **quiet)  # type: ignore[call-overload]
                assert r.returncode == 0, (argv, r.stdout[-2000:], r.stderr[-3000:])
            (wheel,) = (folder / "wheels").glob("rigctl-*.whl")
            install = [sys.executable, "-m", "uv", "pip", "install", "-q", "--python", str(venv / "bin" / "python"),
                       f"{wheel}[{','.join(GUIDE_EXTRAS)}]"]
            r = subprocess.run([*install[:5], "--offline", *install[5:]], env=env, **quiet)  # type: ignore
            if r.returncode != 0:  # not all in uv's cache (another Python's wheels): from the index
                r = subprocess.run(install, env=env, **quiet)  # type: ignore[call-overload]
            assert r.returncode == 0, (install, r.stdout[-2000:], r.stderr[-3000:])
            if kernels:
                r = subprocess.run([str(venv / "bin" / "python"), str(REPO / "scripts" / "compile_kernels.py")],
                                   env=env, cwd=folder, **quiet)  # type: ignore[call-overload]
                assert r.returncode == 0, r.stderr[-3000:]
            done.write_text(f"{time.monotonic() - t0:.1f} {_children_cpu_s() - cpu0:.1f}\n")
        seconds, cpu_s = (float(x) for x in done.read_text().split())
    return ReadmeEnv(venv, venv / "bin" / "python", seconds, cpu_s)


def guide_env(work: Path, readme: ReadmeEnv | None = None) -> dict[str, str]:
    """The environment a guide runs in: the README's environment ``readme`` activated (its ``rigctl``, ``python`` and
    ``pip`` first on the PATH; None: this interpreter's environment's), the rig config and the user's config folder
    inside the scratch folder (never ``$HOME``'s)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    if readme is not None:
        outer = str(Path(sys.executable).parent)
        path = os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep) if p != outer)
        env.update(PATH=f"{readme.bin}{os.pathsep}{path}", VIRTUAL_ENV=str(readme.venv))
    else:
        env.update(PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    env.update(RIGCTL_CONFIG=str(work.parent / "rig.json"), XDG_CONFIG_HOME=str(work.parent / "config"),
               PYTHONUNBUFFERED="1", COLUMNS="120")
    # a guide's pip builds in an isolated environment as a user's does (never from this environment's build tools,
    # which a README environment lacks): its build tools from the wheelhouse scripts/test.sh downloaded, offline
    wheelhouse = os.environ.get("RIGCTL_TEST_WHEELHOUSE")
    if wheelhouse:
        env.update(PIP_NO_INDEX="1", PIP_FIND_LINKS=wheelhouse)
    elif os.environ.get("CI") == "true":
        raise AssertionError("RIGCTL_TEST_WHEELHOUSE is not set: scripts/test.sh downloads the guides' build tools")
    return env


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_page(page: str, work: Path, *, timeout_s: float = 900, preload: bool = True,
             client: Callable[[], Path] | None = None, readme: ReadmeEnv | None = None,
             select: Callable[[Block], bool] = lambda b: b.runs_here) -> list[BlockRun]:
    """Run the blocks of ``page`` that run here, in order, in one shell in ``work``; an AssertionError names the
    block that failed (or printed a traceback) with its output. ``preload``: the shell's ``rigctl`` is the preloaded
    one of tests/launcher.py (the same command lines, without ~2-5 s of CPU to start each): ``client()``'s (the
    ``rigctl`` client script of the test worker's server, started once for the worker's tests: each command runs in
    the page's folder and environment all the same) when the page runs a ``rigctl`` command, else a server of the
    page's own when it runs more than two (starting one costs about what one command's imports do). Whatever the
    page left running (a ``&`` job) ends with it. ``readme``: the README's environment the page runs in
    (:func:`guide_env`; ``client`` then a server of that environment's interpreter). ``select``: the blocks that run
    (default: those the page's own test runs)."""
    runnable = [b for b in blocks(page) if select(b)]
    work.mkdir(parents=True, exist_ok=True)
    path = work.parent / f".{Path(page).stem}.sh"
    path.write_text(script(runnable, work))
    t0 = time.monotonic()
    cpu0 = _children_cpu_s()
    env = guide_env(work, readme)
    server = None
    n_rigctl = sum(line.lstrip().startswith("rigctl ") for b in runnable for line in b.as_run().splitlines())
    if preload and (n_rigctl > 2 or client is not None and n_rigctl > 0):
        if client is None:
            server = launcher.Launcher(work.parent, env=env, python=readme.python if readme else None)
        rigctl = client() if client is not None else server.client  # type: ignore[union-attr]
        env["PATH"] = f"{rigctl.parent}{os.pathsep}{env['PATH']}"
    try:
        return _run_script(page, path, work, env, runnable, t0, cpu0, timeout_s)
    finally:
        if server is not None:
            server.close()


def _run_script(page: str, path: Path, work: Path, env: dict[str, str], runnable: list[Block], t0: float,
                cpu0: float, timeout_s: float) -> list[BlockRun]:
    proc = subprocess.Popen(["bash", str(path)], cwd=work, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    # the shell and what it started (its `&` jobs, the preloaded rigctl's clients: their commands go with them)
    end_all = functools.partial(_kill_group, proc.pid)
    killer = threading.Timer(timeout_s, end_all)  # a block that hangs without printing ends too
    killer.start()
    try:
        return _read_blocks(page, proc, runnable, t0, cpu0)
    finally:
        killer.cancel()
        end_all()


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _read_blocks(page: str, proc: subprocess.Popen, runnable: list[Block], t0: float,
                 cpu0: float) -> list[BlockRun]:
    runs: list[BlockRun] = []
    current: list[str] = []
    started = t0
    index = -1
    assert proc.stdout is not None
    for line in proc.stdout:  # the output in order, cut at the block markers (timed as they come)
        if line.startswith("@@guide-block "):
            if index >= 0:
                runs.append(BlockRun(runnable[index], "".join(current), time.monotonic() - started))
            current, started = [], time.monotonic()
            index = index + 1 if line.split()[1] != "end" else len(runnable)
            continue
        current.append(line)
    rc = proc.wait()
    # (CPU of the shell and the commands it started itself: a preloaded server's commands count in that server)
    print(f"{page}: {time.monotonic() - t0:.1f} s wall, {_children_cpu_s() - cpu0:.1f} s CPU")
    if index < len(runnable):
        failed = runnable[index] if index >= 0 else None
        where = failed.name if failed else page
        raise AssertionError(f"{where}: the block failed (exit {rc}):\n{failed.as_run() if failed else ''}\n"
                             f"--- output ---\n{''.join(current)[-4000:]}")
    for r in runs:
        assert "Traceback (most recent call last)" not in r.output, f"{r.block.name} printed a traceback:\n{r.output}"
    return runs
