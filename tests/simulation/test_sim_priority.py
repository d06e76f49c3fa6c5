"""The simulated boards' threads and harness processes run above the host code beside them where the OS allows it
(rigctl.simulation.priority), and nothing changes (nor fails) where it does not."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

from rigctl.simulation.priority import BOARD_NICE_STEP, board_thread, raise_board_process


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
        assert seen["b"] == max(-20, process_before - BOARD_NICE_STEP)
    else:  # an ordinary user: the board runs at the process's priority, and nothing failed
        assert seen["b"] == process_before
    assert board_thread(board)("x") == "x"  # the wrapped target's result and arguments pass through


def test_a_harness_process_is_raised_where_allowed():
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        before = os.getpriority(os.PRIO_PROCESS, child.pid)
        allowed = raise_board_process(child.pid)
        after = os.getpriority(os.PRIO_PROCESS, child.pid)
        assert allowed == _may_raise()
        assert after == (max(-20, before - BOARD_NICE_STEP) if allowed else before)
    finally:
        child.communicate(b"", timeout=60)
