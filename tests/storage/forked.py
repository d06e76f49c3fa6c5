"""A ``python -c`` child forked from the test process: for the storage tests whose point is a process of its own (a
writer killed with -9, a crash inside HDF5, a lock held by another pid), not a fresh interpreter. The children here
use numpy, h5py and rigctl's storage, never numba's threads (which a forked child of a process that ran them could
not use)."""

from __future__ import annotations

import os
import signal
import sys
import time


class PythonC:
    """``python -c CODE ARGS`` as a child forked from this process instead of a new interpreter (which paid ~0.25
    CPU-s of imports, numpy and h5py, for each child): ``CODE`` runs with ``sys.argv = ["-c", *ARGS]``, the exit
    status as the interpreter's (an exception: its traceback and 1; ``-N``: ended by signal N). ``stdout``: a pipe,
    read as :attr:`stdout`; ``new_session``: the child leads a session (and process group) of its own."""

    def __init__(self, code: str, *args: str, stdout: bool = False, new_session: bool = False) -> None:
        r, w = os.pipe() if stdout else (-1, -1)
        self.returncode: int | None = None
        self.pid = os.fork()
        if self.pid == 0:  # pragma: no cover - the child
            status = 1
            try:
                signal.signal(signal.SIGINT, signal.default_int_handler)  # as a fresh interpreter has them
                for sig in (signal.SIGTERM, signal.SIGHUP):
                    signal.signal(sig, signal.SIG_DFL)
                if new_session:
                    os.setsid()
                if stdout:
                    os.close(r)
                    os.dup2(w, 1)
                sys.stdout = open(1, "w", buffering=1, closefd=False)
                sys.argv = ["-c", *args]
                exec(compile(code, "<string>", "exec"), {"__name__": "__main__"})
                status = 0
            except SystemExit as exc:
                status = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
            except BaseException:
                import traceback

                traceback.print_exc()
            finally:
                sys.stdout.flush()
                os._exit(status)
        self.stdout = None
        if stdout:
            os.close(w)
            self.stdout = open(r)

    def _reaped(self, flags: int) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, flags)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def poll(self) -> int | None:
        return self._reaped(os.WNOHANG)

    def wait(self, timeout_s: float = 120.0) -> int:
        """The exit status; AssertionError if the child still runs after ``timeout_s`` (it is then killed)."""
        deadline = time.monotonic() + timeout_s
        while self.poll() is None:
            if time.monotonic() > deadline:
                os.kill(self.pid, signal.SIGKILL)
                self.wait()
                raise AssertionError(f"the child {self.pid} still ran after {timeout_s} s")
            time.sleep(0.005)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        os.kill(self.pid, sig)
