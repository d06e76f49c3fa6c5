"""The simulated boards' share of the CPU: a virtual board stands for hardware with a processor of its own. Its threads
(the paced clocks, the Modbus server, the pty bridge) and the simavr harness processes ask the operating system for a
higher scheduling priority than the host code beside them, but **never above nice 0**, the priority of the kernel's
own workers: a pty hands a writer's bytes to its reader through a kernel worker at nice 0 (a USB-serial adapter's
driver works the same way), and threads above it starve it. Measured on this 2-core machine (Linux 6.18, EEVDF) beside
two CPU hogs, 8-byte hops over a pty with twelve short-sleeping threads beside them: at nice -15 a median of 0.1 ms
and a maximum of 3.6-4.7 s; the same threads at nice 0, 0.07-0.09 ms and 30-40 ms. Raised 5 levels above a suite
run at nice -10, the boards' own requests and answers sat seconds in the kernel and the host's answer timeouts ran
out (DrumTimeout "no answer" in the conformance tests, three loaded CI runs in a row). A starved host no longer needs
the boards to outrun it: on a simulated rig the host and the boards share one clock (docs/architecture.md, "Time on a
simulated rig"), and the world waits for its host.

So a process started at nice 0 (the usual) runs its boards at 0; one started lower (``nice -n 10 rigctl ...``) gets
its boards raised back towards 0, at most :data:`BOARD_NICE_STEP` levels. Linux only, and only where the process may
raise priorities (root, ``CAP_SYS_NICE`` or ``RLIMIT_NICE``); elsewhere nothing changes and nothing is said. Linux's
``setpriority(PRIO_PROCESS, tid)`` applies to one thread: the rest of the process keeps its priority."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_R = TypeVar("_R")

#: nice levels a board's thread or harness process is raised above the process that starts it, at most (CFS weights:
#: each level is ~1.25x the CPU share, 5 levels ~3x)
BOARD_NICE_STEP = 5
#: the highest priority a board's thread or process asks for: the kernel's workers' (module doc)
BOARD_NICE_FLOOR = 0


def _raise(who: int) -> bool:
    try:
        now = os.getpriority(os.PRIO_PROCESS, who)
        target = max(BOARD_NICE_FLOOR, now - BOARD_NICE_STEP)
        if target < now:
            os.setpriority(os.PRIO_PROCESS, who, target)
    except (OSError, AttributeError):  # not permitted (an ordinary user), or not Linux
        return False
    return True


def raise_board_thread() -> bool:
    """Raise the calling thread's priority by :data:`BOARD_NICE_STEP` nice levels relative to the process's, no
    higher than :data:`BOARD_NICE_FLOOR` (call it first thing in a board's thread). Returns False where the
    operating system refused it; never raises."""
    # (the thread's own nice level starts as the process's; Linux numbers a thread by its native id)
    return _raise(threading.get_native_id())


def raise_board_process(pid: int) -> bool:
    """Raise a board's process (a simavr harness just started) by :data:`BOARD_NICE_STEP` nice levels, no higher than
    :data:`BOARD_NICE_FLOOR`; its threads started later inherit it. Returns False where the operating system refused
    it; never raises."""
    return _raise(pid)


def board_thread(target: Callable[_P, _R]) -> Callable[_P, _R]:
    """``target`` wrapped to call :func:`raise_board_thread` first: ``threading.Thread(target=board_thread(f), ...)``."""

    def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        raise_board_thread()
        return target(*args, **kwargs)

    run.__name__ = getattr(target, "__name__", "board_thread")
    return run
