"""The simulated boards' threads and harness processes run above the host code beside them where the OS allows it,
never above nice 0, the kernel's workers' priority (rigctl.simulation.priority), and nothing changes (nor fails)
where it does not."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

from rigctl.simulation.priority import BOARD_NICE_FLOOR, BOARD_NICE_STEP, board_thread, raise_board_process


def _may_raise() -> bool:
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0))
        probe = subprocess.run([sys.executable, "-c", "import os; os.setpriority(os.PRIO_PROCESS, 0, os.getpriority("
                                "os.PRIO_PROCESS, 0) - 1)"], capture_output=True, timeout=60)
    except OSError:
        return False
    return probe.returncode == 0


def test_a_board_thread_runs_above_its_process_and_the_process_is_unchanged():
    seen = {}

    def board(tag):
        seen[tag] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return tag

    process_before = os.getpriority(os.PRIO_PROCESS, 0)
    t = threading.Thread(target=board_thread(board), args=("b",))
    t.start()
    t.join()
    assert os.getpriority(os.PRIO_PROCESS, 0) == process_before  # only the board's thread moved
    if _may_raise():
        assert seen["b"] == min(process_before, max(BOARD_NICE_FLOOR, process_before - BOARD_NICE_STEP))
    else:  # an ordinary user: the board runs at the process's priority, and nothing failed
        assert seen["b"] == process_before
    assert board_thread(board)("x") == "x"  # the wrapped target's result and arguments pass through


def test_a_harness_process_is_raised_where_allowed_but_never_above_the_kernels_workers():
    """A harness started at nice 10 is raised towards 0 where allowed; one at nice 0 (or above it) is left there: a
    board above the kernel's workers (nice 0) starves the pty's hand-over of its own bytes (the module doc)."""
    for start_nice in (10, 3, 0):
        child = subprocess.Popen(["nice", "-n", str(start_nice), sys.executable, "-c", "import sys; sys.stdin.read()"],
                                 stdin=subprocess.PIPE)
        try:
            before = os.getpriority(os.PRIO_PROCESS, child.pid)
            allowed = raise_board_process(child.pid)
            after = os.getpriority(os.PRIO_PROCESS, child.pid)
            if before <= BOARD_NICE_FLOOR:
                assert after == before and allowed
            elif _may_raise():
                assert allowed and after == max(BOARD_NICE_FLOOR, before - BOARD_NICE_STEP)
            else:
                assert not allowed and after == before
            assert after >= min(before, BOARD_NICE_FLOOR)
        finally:
            child.communicate(b"", timeout=60)
