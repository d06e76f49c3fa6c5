"""A preloaded ``rigctl`` for the tests and the guides' shells: each command forks an interpreter that has already
imported rigctl.

A ``rigctl`` command pays ~3-5 s of CPU to start (numpy, scipy, scikit-learn, h5py, numba and its cached kernels,
the CLI) before any work, and on the tests' small sizes that start is most of its cost: the suite runs a few hundred
commands. ``python launcher.py serve SOCKET`` imports it once (some of it once the first command that needs it comes:
:data:`ON_DEMAND`) and listens on a Unix socket; a client (the
``rigctl`` script :func:`write_client` writes, a few lines of the standard library started with ``python -S``) sends
its arguments, working folder, environment and its stdin/stdout/stderr (SCM_RIGHTS); the server forks, the child runs
``rigctl.cli.main`` exactly as the console script does with them, and its exit status comes back (128 + N when a
signal N ended it). Commands run side by side (a test may start a ``rigctl sim`` and then an ``acquire`` beside it).

The client stands for the command to the test: SIGINT, SIGTERM and SIGHUP sent to it are passed on to the command
(a test's Ctrl-C), and a client that dies (a test's kill -9 or its timeout) takes the command with it (SIGKILL, to
the command's process group: the simulated boards a ``--sim`` command started go too). The command lines are the
real ones, unchanged; the installed console script itself is run by the packaging tests (tests/test_packaging.py).
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

#: what the server imports before it forks (the CLI and what its commands load)
PRELOAD = ("rigctl.cli", "rigctl.cli.errors", "rigctl.cli.progress", "rigctl.operations", "rigctl.encoding.pipeline",
           "rigctl.encoding.fused", "rigctl.simulation.dataset", "rigctl.storage.importers", "rigctl.storage.session",
           "rigctl.storage.encoded")
#: imported by the server before it forks the first command whose arguments hold one of the words (not at its start:
#: most servers, a test worker's or a guide page's, never run such a command): the analyses (scikit-learn, scipy.stats,
#: matplotlib; ~1.8 CPU-s) for ``rigctl analyze`` and the handheld's live classifier, and scipy.signal (~0.5 CPU-s)
#: for ``--resample`` (not the encoder, the dataset renderer or the operator model: their filters need no scipy; a
#: session the encoder resamples, at another rate than 1 kHz, has its command import scipy.signal itself)
ANALYSIS = ("rigctl.analysis.tasks", "rigctl.analysis.classify", "rigctl.analysis.report",
            "rigctl.analysis.realtime_model", "sklearn.discriminant_analysis", "sklearn.decomposition",
            "matplotlib.pyplot")
ON_DEMAND: dict[str, tuple[str, ...]] = {
    **dict.fromkeys(("analyze", "--classify"), ANALYSIS),
    "--resample": ("scipy.signal",),
}

_CLIENT = '''#!{python} -S
import json, os, signal, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.connect({sock!r})
msg = json.dumps([sys.argv[1:], os.getcwd(), dict(os.environ)]).encode()
socket.send_fds(s, [len(msg).to_bytes(4, "big") + msg], [0, 1, 2])
f = s.makefile("rb")
pid = int(f.readline() or b"0")
def forward(sig, _frame):
    try:
        os.kill(pid, sig)
    except OSError:
        pass
if pid:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, forward)
status = f.readline()
sys.exit(int(status or b"70"))
'''


def write_client(bin_dir: Path, sock: Path) -> Path:
    """Write the ``rigctl`` client into ``bin_dir`` (to be first on a shell's PATH); returns its path."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    path = bin_dir / "rigctl"
    path.write_text(_CLIENT.format(python=sys.executable, sock=str(sock)))
    path.chmod(0o755)
    return path


def _receive(conn: socket.socket) -> tuple[list[str], str, dict[str, str], list[int]]:
    """One request: a 4-byte length, that much JSON ([argv, cwd, env]), and the client's three descriptors."""
    data, fds, _flags, _addr = socket.recv_fds(conn, 1 << 20, 3)
    while len(data) < 4 or len(data) < 4 + int.from_bytes(data[:4], "big"):
        more = conn.recv(1 << 20)
        if not more:
            raise ConnectionError("the client left mid-request")
        data += more
    argv, cwd, env = json.loads(data[4:])
    return argv, cwd, env, fds


def _child(argv: list[str], cwd: str, env: dict[str, str], fds: list[int]) -> int:
    """In the forked child: become the command (its folder, environment and stdio) and run the console script."""
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    tempfile.tempdir = None  # the command's TMPDIR, as a fresh interpreter takes it (not the server's, cached)
    # the command's PYTHONPATH, as a fresh interpreter would take it (a guide installs a plugin into a folder on it)
    sys.path[:0] = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p not in sys.path]
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    # buffered as a fresh interpreter's would be on these descriptors, in this environment (PYTHONUNBUFFERED)
    unbuffered = bool(env.get("PYTHONUNBUFFERED"))
    sys.stdout.reconfigure(line_buffering=os.isatty(1), write_through=unbuffered)
    sys.stderr.reconfigure(line_buffering=True, write_through=unbuffered)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
        signal.signal(sig, signal.SIG_DFL)
    from rigctl.cli import main
    from rigctl.cli.interrupts import keep_ctrl_c

    keep_ctrl_c()  # as the console script does (rigctl_launch)
    sys.argv = ["rigctl", *argv]
    try:
        code = main()
    except SystemExit as exc:
        code = exc.code
    except KeyboardInterrupt:  # as an interpreter ends on an unhandled Ctrl-C
        code = 130
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _watch(pid: int, conn: socket.socket) -> None:
    """Wait for the command ``pid`` to end and send its status; if the client goes first, end the command."""
    pidfd = os.pidfd_open(pid)
    try:
        while True:
            ready, _, _ = select.select([pidfd, conn], [], [])
            if pidfd in ready:
                break
            if conn.recv(1) == b"":  # the client is gone: so is its command
                for kill in (os.killpg, os.kill):
                    try:
                        kill(pid, signal.SIGKILL)
                    except OSError:
                        pass
                break
        _, status = os.waitpid(pid, 0)
        code = os.WEXITSTATUS(status) if os.WIFEXITED(status) else 128 + os.WTERMSIG(status)
        try:
            conn.sendall(f"{code}\n".encode())
        except OSError:
            pass
    finally:
        os.close(pidfd)
        conn.close()


def load_rig_kernels() -> None:
    """Load the simulated rig's numba kernels (the taxel renderer and the mechanics: scripts/compile_kernels.py
    ``compile_rig``) into this process from numba's cache (compiled first if the cache lacks them): every command
    forked after it inherits them instead of loading its own (measured: ~0.35 of ~1.1 CPU-s of each ``acquire
    quick_check --inprocess``; ~0.25 CPU-s once here). Not the encoder's: a call of those starts numba's GNU OpenMP
    thread pool, and a process that forks with it running has its children refuse to run a parallel kernel."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / "compile_kernels.py"
    spec = importlib.util.spec_from_file_location("_rigctl_compile_kernels", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.compile_rig()


def serve(sock: Path) -> None:
    """Import :data:`PRELOAD` and load the simulated rig's kernels (:func:`load_rig_kernels`), then run each command
    a client sends in a child of its own, side by side."""
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    try:
        load_rig_kernels()
    except Exception:  # noqa: BLE001, S110 - only slower commands: each then loads (or compiles) its own
        pass
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock))
    server.listen(16)
    print("ready", flush=True)
    while True:
        conn, _ = server.accept()
        try:
            argv, cwd, env, fds = _receive(conn)
        except (ConnectionError, ValueError):
            conn.close()
            continue
        for name in (n for word in argv for n in ON_DEMAND.get(word, ())):
            try:  # once: then in sys.modules (a failure is the command's to report)
                importlib.import_module(name)
            except Exception:  # noqa: BLE001, S110 - ImportError or whatever the module raises
                pass
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child
            server.close()
            conn.close()
            os.setpgid(0, 0)  # a group of its own: the boards a --sim command starts end with it
            code = 70
            try:
                code = _child(argv, cwd, env, fds)
            finally:
                import atexit

                atexit._run_exitfuncs()
                os._exit(code)
        for fd in fds:
            os.close(fd)
        conn.sendall(f"{pid}\n".encode())
        threading.Thread(target=_watch, args=(pid, conn), daemon=True).start()


class Launcher:
    """One preloaded server (``python launcher.py serve``) and its client script, for a test session.

    ``command`` is the argv prefix that runs ``rigctl`` through it (``[*launcher.command, "info", path]``), to be used
    wherever ``[sys.executable, "-m", "rigctl"]`` would be, and ``client`` the ``rigctl`` script itself (for a shell's
    PATH); ``env`` is the server's environment (each command runs in its client's); :meth:`close` stops the server."""

    def __init__(self, folder: Path, env: dict[str, str] | None = None, python: Path | None = None) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        sock = folder / "rigctl.sock"
        # (``python``: another environment's interpreter, whose rigctl the commands then run: the guides' README one)
        self._server = subprocess.Popen([str(python or sys.executable), str(Path(__file__)), "serve", str(sock)],
                                        cwd=folder,
                                        env=env, stdout=subprocess.PIPE, text=True)
        assert self._server.stdout is not None
        line = self._server.stdout.readline().strip()
        if line != "ready":
            self._server.kill()
            raise RuntimeError(f"the preloaded rigctl did not start: {line!r}")
        self.client = write_client(folder / "bin", sock)
        self.command = [sys.executable, "-S", str(self.client)]

    def close(self) -> None:
        self._server.kill()
        self._server.wait()


if __name__ == "__main__":
    serve(Path(sys.argv[2]))
