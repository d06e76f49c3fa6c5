"""Ctrl-C and the worker processes a command starts: the command takes it, its workers never do.

A terminal's Ctrl-C sends SIGINT to the whole foreground process group, a pool's workers included. A worker that
ignores it from its first instruction leaves the command to stop the pool and say one line; a worker that is still
starting when it lands (forked, not yet at its initializer) raises KeyboardInterrupt there and prints ``Process
ForkPoolWorker-N:`` and a traceback beside the command's line (tests/core/test_core_worker_signals.py shows it; on a
loaded machine a worker of ``rigctl sim dataset`` may be slow to reach its initializer). So the pool is made
with SIGINT blocked (:func:`ctrl_c_held`): its workers start with it blocked, ignore it
(:func:`worker_ignores_ctrl_c`, their initializer's first step) and only then unblock it, which drops one that came
meanwhile; the command keeps its own pending and takes it when the block ends. POSIX: a fork's child inherits the
signal mask (and an exec keeps it), not the parent's pending signals; setting a signal to SIG_IGN discards it where
it is pending.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def ctrl_c_held() -> Iterator[None]:
    """SIGINT blocked in this thread for the block's duration (for making a process pool in it): the processes and
    threads started meanwhile inherit the block (the pool's own threads keep it, and so do the workers they start
    later); a Ctrl-C that comes meanwhile is this process's as soon as the block ends (KeyboardInterrupt raised on
    leaving the block: nothing lost). A no-op off the main thread (which alone takes Python's signals) and where the
    platform has no ``pthread_sigmask``."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def worker_ignores_ctrl_c() -> None:
    """A worker's first step (its pool's initializer): SIGINT ignored, then unblocked (a Ctrl-C that came while it
    started, held by :func:`ctrl_c_held`, is dropped): Ctrl-C is the command's, which stops the pool."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
