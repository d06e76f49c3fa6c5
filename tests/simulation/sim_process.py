"""``rigctl sim`` in a process of its own, for tests that drive it as hardware (issue 51 item 7): started with its port
folder and truth log, faults injected through ``rigctl sim inject``, its truth log read while it runs."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np

from rigctl.simulation.sim_control import request
from rigctl.simulation.truth import TRUTH_COLUMNS

#: bounds a hang only: a starved machine takes tens of seconds to start (imports) or stop a sim
HANG_S = 300.0


def read_truth(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """The truth log's columns by name (:data:`TRUTH_COLUMNS`), whole rows only (a row being written is left out)."""
    text = Path(path).read_text()
    lines = text.split("\n")
    assert tuple(lines[0].split(",")) == TRUTH_COLUMNS, lines[0]
    rows = [line.split(",") for line in lines[1:-1]]  # the last piece: "" after a whole row, else a partial one
    data = np.array(rows, float).reshape(-1, len(TRUTH_COLUMNS))
    return {name: data[:, i] for i, name in enumerate(TRUTH_COLUMNS)}


class SimProcess:
    """``rigctl sim --port-dir DIR --truth-log FILE`` running in a child process in ``folder`` (``command``: the
    ``rigctl`` command line; ``args``: its arguments, default ports and truth.csv in ``folder``); :meth:`stop`
    (Ctrl-C) or :meth:`kill` ends it."""

    def __init__(self, command: list[str], folder: Path, *, seed: int = 0, env: dict[str, str] | None = None,
                 args: list[str] | None = None):
        if args is None:
            args = ["sim", "--seed", str(seed), "--port-dir", "ports", "--truth-log", "truth.csv"]
        self.dir = folder / args[args.index("--port-dir") + 1]
        self.truth_path = folder / args[args.index("--truth-log") + 1]
        self.command = command
        self.err_path = folder / "sim.err"  # (its log: a pipe nobody reads would fill and block it)
        with open(self.err_path, "w") as err:  # (run in ``folder``: the args' paths are relative to it)
            self.proc = subprocess.Popen([*command, *args], stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                                         cwd=folder)
        out = ""
        assert self.proc.stdout is not None
        while "Ctrl-C stops" not in out:
            line = self.proc.stdout.readline()
            if not line:
                self.proc.kill()
                self.proc.communicate()
                raise AssertionError(f"rigctl sim did not start: {out}{self.err_path.read_text()}")
            out += line
        self.banner = out
        self.drum_port, self.taxel_port = str(self.dir / "drum"), str(self.dir / "taxel")

    def inject(self, *specs: str) -> subprocess.CompletedProcess:
        """``rigctl sim inject --port-dir DIR SPEC...`` (its output and exit status)."""
        return subprocess.run([*self.command, "sim", "inject", "--port-dir", str(self.dir), *specs],
                              capture_output=True, text=True, timeout=HANG_S)

    def status(self) -> dict:
        """The running rig's clock and active faults (its control socket)."""
        return request(self.dir, {"status": True})

    def truth(self) -> dict[str, np.ndarray]:
        return read_truth(self.truth_path)

    def wait_truth(self, time_s: float) -> dict[str, np.ndarray]:
        """The truth log once its rows reach ``time_s`` of the rig's clock (HANG_S bounds a hang)."""
        deadline = time.monotonic() + HANG_S
        while True:
            t = self.truth()
            if len(t["time_s"]) and t["time_s"][-1] >= time_s:
                return t
            assert self.proc.poll() is None and time.monotonic() < deadline, "the truth log stopped growing"
            time.sleep(0.1)

    def stop(self) -> str:
        """Ctrl-C: the rig stops cleanly; what it printed after its banner."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        out, _err = self.proc.communicate(timeout=HANG_S)
        return out

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=HANG_S)

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None:
            self.stop()
