"""The commit helper of a writing process: one detached ``python -I -S journal_replay.py --serve FD`` per process,
which makes the in-place writes of every commit (:func:`rigctl.storage.journal.apply_journal`).

A helper per commit cost a new interpreter each time (~10-15 ms of CPU: a session of 100 trials started 100). This
one is started at the process's first commit, in its own session (a ``kill -9`` of the writer or of its process
group, or a Ctrl-C, does not reach it), and kept: each commit sends it the locked file's descriptor (``SCM_RIGHTS``
over a ``SOCK_SEQPACKET`` socket pair: the helper holds the same open file, so the lock stays held until it has
finished) with the journal's path, and waits for its answer. The helper closes its copy of the descriptor before it
answers. It exits when the writer's end of the socket closes: at the writer's exit (or kill), or when a forked child
drops the copy it inherited (a child starts a helper of its own). Where the platform cannot pass descriptors (no
``socket.send_fds``), or the helper cannot be started or dies, :func:`serve_commit` says so and the caller applies
the journal another way.
"""

from __future__ import annotations

import atexit
import os
import select
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from rigctl.storage import journal_replay

__all__ = ["serve_commit"]

_lock = threading.Lock()
_state: dict[str, object] = {}  # "pid", "sock", "proc", "seq": this process's helper (none before the first commit)


def _drop() -> None:
    """Forget this process's helper, closing our end of its socket (it then exits, once its last commit is done)."""
    sock = _state.pop("sock", None)
    _state.clear()
    if isinstance(sock, socket.socket):
        try:
            sock.close()
        except OSError:  # pragma: no cover
            pass


def _at_exit() -> None:
    proc = _state.get("proc")
    _drop()
    if isinstance(proc, subprocess.Popen):
        try:
            proc.wait(timeout=5.0)  # it exits at once: the end of its socket is closed
        except subprocess.TimeoutExpired:  # pragma: no cover - still applying a commit: it finishes on its own
            pass


def _start() -> socket.socket | None:
    """This process's helper, started now (None: it cannot be)."""
    if not hasattr(socket, "send_fds") or not sys.executable or getattr(sys, "frozen", False):
        return None  # pragma: no cover - no descriptor passing, or a frozen app (its executable is not Python)
    try:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    except (OSError, AttributeError):  # pragma: no cover - no such sockets here
        return None
    try:
        cmd = [sys.executable, "-I", "-S", os.path.abspath(journal_replay.__file__), "--serve", str(theirs.fileno())]
        proc = subprocess.Popen(cmd, pass_fds=(theirs.fileno(),), start_new_session=True, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, close_fds=True)
    except (OSError, ValueError):  # pragma: no cover - cannot start processes (or pass fds) here
        ours.close()
        return None
    finally:
        theirs.close()
    _state.update(pid=os.getpid(), sock=ours, proc=proc, seq=0)
    return ours


#: after a Ctrl-C, how long the writer waits in one step for the helper's answer before it looks for the journal, s
_INTERRUPTED_POLL_S = 0.05
#: after a Ctrl-C, once the journal is gone (the helper replayed it), how long its answer may still take, s
_ANSWER_AFTER_REPLAY_S = 0.5


def _request(sock: socket.socket, fd: int, message: bytes, seq: int,
             replayed: Callable[[], bool]) -> tuple[bool, BaseException | None]:
    """Send one commit and wait for its answer (a Ctrl-C meanwhile is held and returned). (answered, interrupt).

    A Ctrl-C can land after ``recv`` has taken the answer and before it is looked at (a signal that came in just
    before the call is raised as the call returns): the answer is then gone, and a blocking ``recv`` would wait
    forever (a loaded CI run: the writer still waiting after 60 s). So after a Ctrl-C the writer waits in short steps
    and also asks ``replayed()`` (the journal gone: the helper removes it once the in-place writes are made); an
    answer left unread is skipped by the next commit (its sequence number is not that commit's)."""
    interrupted: BaseException | None = None
    sent = False
    replayed_at: float | None = None
    while True:
        try:
            if not sent:
                socket.send_fds(sock, [message], [fd])
                sent = True
            if interrupted is not None and not select.select([sock], [], [], _INTERRUPTED_POLL_S)[0]:
                if replayed_at is None:
                    if replayed():
                        replayed_at = time.monotonic()
                elif time.monotonic() - replayed_at > _ANSWER_AFTER_REPLAY_S:
                    return True, interrupted  # its answer was taken by the interrupted recv
                continue
            reply = sock.recv(64)
            if not reply:
                return False, interrupted  # the helper is gone
            if reply == str(seq).encode():
                return True, interrupted
        except KeyboardInterrupt as exc:  # a commit is never abandoned half way: wait for it, then re-raise
            interrupted = exc
        except OSError:
            return False, interrupted


def serve_commit(fd: int, jpath: Path, durable: bool, delay_s: float, gate: str) -> tuple[bool, BaseException | None]:
    """Have this process's helper replay the committed journal ``jpath`` onto the open, locked ``fd``
    (:func:`rigctl.storage.journal_replay.replay` with ``durable``, ``delay_s``, ``gate``), starting the helper if
    needed; returns once it has answered. Returns (whether the helper answered, a KeyboardInterrupt held while
    waiting, or None). Not answered (no helper here, or it died): the caller checks the journal and applies it."""
    with _lock:
        if _state.get("pid") != os.getpid():
            _state.clear()  # (a forked child's copy was closed at the fork)
        sock = _state.get("sock")
        if not isinstance(sock, socket.socket):
            sock = _start()
            if sock is None:
                return False, None
        seq = int(_state["seq"]) + 1  # type: ignore[call-overload]
        _state["seq"] = seq
        message = b"\0".join([str(seq).encode(), os.fsencode(str(jpath)), b"1" if durable else b"0",
                              repr(float(delay_s)).encode(), os.fsencode(gate)])
        answered, interrupted = _request(sock, fd, message, seq, lambda: not jpath.exists())
        if not answered:
            _drop()  # the next commit starts a new helper
        return answered, interrupted


def _after_fork_in_child() -> None:
    global _lock
    _lock = threading.Lock()  # (another thread of the parent may have held it at the fork)
    _drop()


atexit.register(_at_exit)
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)
