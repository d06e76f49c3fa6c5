"""One simavr harness process of :class:`rigctl.simulation.hil.HilRig` (``arduino/simavr/rigctl_simavr.c``, one per
board): started with its image and options, its stdout lines handed to a callback from a reader thread, stdin
commands sent; and :class:`HilError`.

A bench action sent as a command (a mass on the load cell, the e-stop, a wire broken: :data:`ACKNOWLEDGED`) reaches
the firmware's world when the host sends it, not when the pipe hands it on: on the rig's shared clock the host waits
for the harness's ``OK``/``ERR`` line with the world standing (at most :data:`rigctl.core.shared_clock.LEAD_S` past
the host's time), as a person's hand acts at once. The command pipe is a kernel hop like a pty's: a CI run at load 11
placed a mass while the world ran on, after the actuator's back-off had ended that the test meant it to land in
(test_drum_conformance's push during a back-off, hil).
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from pathlib import Path

from rigctl.core.shared_clock import KERNEL_HOP_MAX_S, SharedClock
from rigctl.simulation.priority import board_thread, raise_board_process

__all__ = ["HilError"]

log = logging.getLogger(__name__)

#: the harness's commands it answers with ``OK <word>`` or ``ERR <word>`` (rigctl_simavr.c's stdin thread), by their
#: first word
ACKNOWLEDGED = frozenset({"bump", "estop", "hang", "homeswitch", "hx711", "spring-k", "actuator", "drum", "link",
                          "polarity", "rxlog", "taxel_ohm", "taxel_aa", "wave", "cell", "coupling", "steps", "driver"})


class HilError(RuntimeError):
    """The firmware or the harness could not be built or started."""


class _Harness:
    """One rigctl_simavr process: start, read its stdout in a thread, send stdin commands."""

    def __init__(self, exe: Path, board: str, elf: Path, args: list[str], on_line, clock: SharedClock | None = None):
        self.board = board
        self.clock = clock
        self._acks: dict[str, int] = {}  # OK/ERR lines read, by their command's word
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
                words = line.split(maxsplit=2)
                if len(words) > 1 and words[0] in ("OK", "ERR"):
                    self._acks[words[1]] = self._acks.get(words[1], 0) + 1
                try:
                    self._on_line(line.rstrip("\n"))
                except Exception:  # a bad line must not kill the reader (the pipe would fill and stall the sim)
                    log.exception("HIL %s: cannot handle %r", self.board, line)
        except (ValueError, OSError):  # stdout closed by close()
            pass

    def send(self, text: str) -> bool:
        """Send a stdin command; one the harness acknowledges (:data:`ACKNOWLEDGED`), sent on the rig's clock from
        any thread but the reader's, returns once the harness has it, the world standing meanwhile (module doc; at
        most ``KERNEL_HOP_MAX_S`` of wall time: a harness that never answers). Returns False when the harness is
        gone, its stdin closed, or an acknowledged command it was waited for did not come back in that time."""
        word = text.split(maxsplit=1)[0] if text.strip() else ""
        wait = self.clock is not None and word in ACKNOWLEDGED and threading.current_thread() is not self._thread
        with self._lock:
            acks = self._acks.get(word, 0)
            if self.proc.poll() is None:
                try:
                    self._stdin.write(text + "\n")
                    self._stdin.flush()
                except (BrokenPipeError, ValueError):
                    return False
            else:
                return False
        if wait and self.clock is not None:
            return self.clock.wait_for(lambda: self._acks.get(word, 0) > acks, 0.0, min_wall_s=KERNEL_HOP_MAX_S)
        return True

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
