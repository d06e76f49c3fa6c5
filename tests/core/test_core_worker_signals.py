"""A Ctrl-C that lands while a pool's worker starts (rigctl.core.worker_signals): with the pool made under
``ctrl_c_held``, the worker drops it and works, and the command takes it; without, the worker raises
KeyboardInterrupt before its initializer ignores it and prints ``Process ForkPoolWorker-N:`` (`rigctl sim dataset`
interrupted on a loaded machine). Each case runs in a process of its own, its Ctrl-C sent by the worker itself at
the worst moment: the first line of its initializer, before it ignores SIGINT."""

from __future__ import annotations

import subprocess
import sys

import pytest

SCRIPT = r"""
import multiprocessing as mp, os, signal, sys, time
from rigctl.core.worker_signals import ctrl_c_held, worker_ignores_ctrl_c

def init():
    os.kill(os.getpid(), signal.SIGINT)  # the Ctrl-C, while this worker starts
    worker_ignores_ctrl_c()

held = sys.argv[1] == "held"
ctx = mp.get_context("fork")
taken = False
try:
    if held:
        with ctrl_c_held():
            pool = ctx.Pool(1, initializer=init)
            os.kill(os.getpid(), signal.SIGINT)  # and one for the command meanwhile: taken once the block ends
    else:
        pool = ctx.Pool(1, initializer=init)
except KeyboardInterrupt:
    taken = True
try:
    if held:
        print("worker", pool.apply_async(os.getpid).get(timeout=60) > 0, "command took it", taken, flush=True)
    else:  # the first worker ends at its initializer (the pool's own list of its processes)
        first = pool._pool[0]
        deadline = time.monotonic() + 60
        while first.exitcode is None and time.monotonic() < deadline:  # (not join: the pool's thread reaps it too)
            time.sleep(0.01)
        print("first worker ended", first.exitcode, flush=True)
finally:
    pool.terminate()
"""


@pytest.mark.parametrize("held", [True, False])
def test_a_ctrl_c_while_a_worker_starts_is_the_commands(tmp_path, held):
    r = subprocess.run([sys.executable, "-c", SCRIPT, "held" if held else "plain"], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    if held:
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip() == "worker True command took it True", (r.stdout, r.stderr)
        assert r.stderr == ""
    else:  # the failure this guards against, shown: the worker's traceback, and no worker that works
        assert "Process ForkPoolWorker-1:" in r.stderr and "KeyboardInterrupt" in r.stderr, r.stderr
        assert r.stdout.strip() == "first worker ended 1", (r.stdout, r.stderr)
