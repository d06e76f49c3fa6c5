"""The simavr harness's lifetime (arduino/simavr/rigctl_simavr.c): it lives as long as the host *process*, whichever
of the host's threads started it, and it quits when that process dies even while another process still holds its
stdin (a forked child of the host). With PR_SET_PDEATHSIG, which fires when the starting *thread* ends, the desktop
app's boards vanished as soon as its connect worker finished (the GUI had no HIL source)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = pytest.mark.hil

HOST = textwrap.dedent("""
    import os, subprocess, sys, threading, time
    exe, elf = sys.argv[1], sys.argv[2]
    box = {}
    def start():  # the harness started from a worker thread that then ends, as the app's connect worker does
        box["p"] = subprocess.Popen([exe, "--board", "uno", elf], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                    text=True)
        line = ""
        while not line.startswith("PTY "):
            line = box["p"].stdout.readline()
        box["pty"] = line.split()[1]
    t = threading.Thread(target=start)
    t.start()
    t.join()
    if os.fork() == 0:  # a child of the host that keeps the harness's stdin open (inherited), and outlives the host
        time.sleep(60)
        os._exit(0)
    print(box["p"].pid, box["pty"], flush=True)
    time.sleep(60)
""")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_the_harness_outlives_the_starting_thread_and_quits_with_the_host_process(fw_build, tmp_path):
    host = subprocess.Popen([sys.executable, "-c", HOST, str(fw_build / "rigctl_simavr"),
                             str(fw_build / "uno_taxel.elf")], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        pid_text, pty = host.stdout.readline().split()
        harness = int(pid_text)
        time.sleep(1.0)  # the starting thread ended before the host printed: the harness must still run
        assert _alive(harness) and os.path.exists(pty)
        host.kill()  # the host process dies; its forked child still holds the harness's stdin
        host.wait(10)
        deadline = time.monotonic() + 10
        while _alive(harness) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(harness), "the harness outlived its host process"
    finally:
        try:
            os.killpg(host.pid, signal.SIGKILL)  # the forked child (and the harness, if it is still there)
        except ProcessLookupError:
            pass
