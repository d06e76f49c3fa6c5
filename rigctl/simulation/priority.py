"""The simulated boards' share of the CPU: a virtual board stands for hardware with a processor of its own, which a
busy host computer cannot slow down. Its threads (the paced clocks, the Modbus server, the pty bridge) and the simavr
harness processes ask the operating system for a higher scheduling priority than the host code beside them, so a
machine loaded by other programs (a shared CI runner, a lab PC compiling, the test suite's own analyses) delays the
host, as a real bench's host is delayed, not the board's clock.

Linux only, and only where the process may raise priorities (root, ``CAP_SYS_NICE`` or ``RLIMIT_NICE``); elsewhere
nothing changes and nothing is said (the simulation then runs at the host's priority, as before). Linux's
``setpriority(PRIO_PROCESS, tid)`` applies to one thread: the rest of the process keeps its priority."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_R = TypeVar("_R")

#: nice levels a board's thread or harness process is raised above the process that starts it (CFS weights: each
#: level is ~1.25x the CPU share, 5 levels ~3x)
BOARD_NICE_STEP = 5


def _raise(who: int) -> bool:
    try:
        now = os.getpriority(os.PRIO_PROCESS, who)
        os.setpriority(os.PRIO_PROCESS, who, max(-20, now - BOARD_NICE_STEP))
    except (OSError, AttributeError):  # not permitted (an ordinary user), or not Linux
        return False
    return True


def raise_board_thread() -> bool:
    """Raise the calling thread's priority by :data:`BOARD_NICE_STEP` nice levels relative to the process's (call it
    first thing in a board's thread). Returns whether the operating system allowed it; never raises."""
    # (the thread's own nice level starts as the process's; Linux numbers a thread by its native id)
    return _raise(threading.get_native_id())


def raise_board_process(pid: int) -> bool:
    """Raise a board's process (a simavr harness just started) by :data:`BOARD_NICE_STEP` nice levels; its threads
    started later inherit it. Returns whether the operating system allowed it; never raises."""
    return _raise(pid)


def board_thread(target: Callable[_P, _R]) -> Callable[_P, _R]:
    """``target`` wrapped to call :func:`raise_board_thread` first: ``threading.Thread(target=board_thread(f), ...)``."""

    def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        raise_board_thread()
        return target(*args, **kwargs)

    run.__name__ = getattr(target, "__name__", "board_thread")
    return run
