"""One simavr harness process of :class:`rigctl.simulation.hil.HilRig` (``arduino/simavr/rigctl_simavr.c``, one per
board): started with its image and options, its stdout lines handed to a callback from a reader thread, stdin
commands sent; and :class:`HilError`."""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from pathlib import Path

from rigctl.simulation.priority import board_thread, raise_board_process

__all__ = ["HilError"]

log = logging.getLogger(__name__)


class HilError(RuntimeError):
    """The firmware or the harness could not be built or started."""


class _Harness:
    """One rigctl_simavr process: start, read its stdout in a thread, send stdin commands."""

    def __init__(self, exe: Path, board: str, elf: Path, args: list[str], on_line):
        self.board = board
        self._lock = threading.Lock()
        self.proc = subprocess.Popen([str(exe), "--board", board, *args, str(elf)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        raise_board_process(self.proc.pid)
        assert self.proc.stdin is not None and self.proc.stdout is not None and self.proc.stderr is not None
        self._stdin, self._stdout, self._stderr = self.proc.stdin, self.proc.stdout, self.proc.stderr  # all piped
        port, deadline = None, time.monotonic() + 10.0
        while time.monotonic() < deadline:
            line = self._stdout.readline()
            if not line:
                raise HilError(f"simavr harness for the {board} exited at start: {self._stderr.read().strip()}")
            if line.startswith("PTY "):
                port = line.split()[1]
                break
        if port is None:
            self.close()
            raise HilError(f"simavr harness for the {board} did not report its pty")
        self.port: str = port
        self._on_line = on_line
        self._thread = threading.Thread(target=board_thread(self._read), name=f"hil-{board}", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for line in self._stdout:
                try:
                    self._on_line(line.rstrip("\n"))
                except Exception:  # a bad line must not kill the reader (the pipe would fill and stall the sim)
                    log.exception("HIL %s: cannot handle %r", self.board, line)
        except (ValueError, OSError):  # stdout closed by close()
            pass

    def send(self, text: str) -> None:
        with self._lock:
            if self.proc.poll() is None:
                try:
                    self._stdin.write(text + "\n")
                    self._stdin.flush()
                except (BrokenPipeError, ValueError):
                    pass

    def close(self) -> None:
        try:
            with self._lock:
                self._stdin.close()
        except Exception:
            pass
        try:
            self.proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._thread.join(timeout=2)  # the reader ends at EOF once the process is gone
        for f in (self._stdout, self._stderr):
            try:
                f.close()
            except Exception:
                pass
