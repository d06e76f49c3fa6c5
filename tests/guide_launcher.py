"""A preloaded ``rigctl`` for the guides' shells: each command forks an interpreter that has already imported rigctl.

A ``rigctl`` command pays ~5 s of CPU to start (numpy, scipy, scikit-learn, h5py, numba and its cached kernels, the
CLI) before any work, and on the guides' small sizes that start is most of its cost: ~30 commands over the guides
would spend ~150 s of CPU importing. ``python guide_launcher.py serve SOCKET`` imports all of it once and listens on
a Unix socket; the ``rigctl`` the guide's shell finds first on its PATH (:func:`write_client`, a few lines of the
standard library) sends its arguments, working folder, environment and its stdin/stdout/stderr (SCM_RIGHTS) there;
the server forks, the child runs ``rigctl.cli.main`` exactly as the console script does with them, and its exit
status comes back. The command lines are the guide's, unchanged; the installed console script itself is run by
the packaging tests (tests/test_packaging.py).
"""

from __future__ import annotations

import json
import os
import socket
import sys
from pathlib import Path

#: what the server imports before it forks (the CLI and what its commands load)
PRELOAD = ("rigctl.cli", "rigctl.cli.errors", "rigctl.cli.progress", "rigctl.operations", "rigctl.encoding.pipeline",
           "rigctl.encoding.fused", "rigctl.analysis.tasks", "rigctl.analysis.classify", "rigctl.analysis.report",
           "rigctl.simulation.dataset", "rigctl.storage.importers", "rigctl.storage.session", "rigctl.storage.encoded",
           "sklearn.discriminant_analysis", "sklearn.decomposition", "matplotlib.pyplot")

_CLIENT = '''#!{python} -S
import json, os, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.connect({sock!r})
socket.send_fds(s, [json.dumps([sys.argv[1:], os.getcwd(), dict(os.environ)]).encode()], [0, 1, 2])
s.shutdown(socket.SHUT_WR)
status = b"".join(iter(lambda: s.recv(64), b""))
sys.exit(int(status or b"70"))
'''


def write_client(bin_dir: Path, sock: Path) -> Path:
    """Write the ``rigctl`` client into ``bin_dir`` (to be first on the guide shell's PATH); returns its path."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    path = bin_dir / "rigctl"
    path.write_text(_CLIENT.format(python=sys.executable, sock=str(sock)))
    path.chmod(0o755)
    return path


def _receive(conn: socket.socket) -> tuple[list[str], str, dict[str, str], list[int]]:
    chunks, fds = [], []
    while True:
        data, got, _flags, _addr = socket.recv_fds(conn, 1 << 20, 3)
        fds += got
        if not data:
            break
        chunks.append(data)
    argv, cwd, env = json.loads(b"".join(chunks))
    return argv, cwd, env, fds


def _child(argv: list[str], cwd: str, env: dict[str, str], fds: list[int]) -> int:
    """In the forked child: become the command (its folder, environment and stdio) and run the console script."""
    import signal

    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    # the command's PYTHONPATH, as a fresh interpreter would take it (a guide installs a plugin into a folder on it)
    sys.path[:0] = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p not in sys.path]
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    from rigctl.cli import main

    sys.argv = ["rigctl", *argv]
    try:
        code = main()
    except SystemExit as exc:
        code = exc.code
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def serve(sock: Path) -> None:
    """Import :data:`PRELOAD`, then run each command a client sends in a child of its own, one at a time."""
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock))
    server.listen(4)
    print("ready", flush=True)
    while True:
        conn, _ = server.accept()
        argv, cwd, env, fds = _receive(conn)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child
            server.close()
            code = 70
            try:
                code = _child(argv, cwd, env, fds)
            finally:
                import atexit

                atexit._run_exitfuncs()
                conn.sendall(str(code).encode())
                os._exit(code)
        for fd in fds:
            os.close(fd)
        _, status = os.waitpid(pid, 0)
        try:  # a child killed by a signal answers nothing: say so
            if os.WIFSIGNALED(status):
                conn.sendall(str(128 + os.WTERMSIG(status)).encode())
        finally:
            conn.close()


if __name__ == "__main__":
    serve(Path(sys.argv[2]))
