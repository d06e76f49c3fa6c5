"""A Ctrl-C that lands in a callback from C code (numba's kernel cache calls Python through ctypes while a command
starts) ends the command as any Ctrl-C does, with no traceback (rigctl.cli.interrupts); a loaded CI run met the
opposite: ``rigctl sim dataset`` interrupted 0.8 s after its start printed "Exception ignored on calling ctypes
callback function", a traceback, and then wrote its whole dataset."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

#: C code (libc's qsort) calls a Python comparison; a Ctrl-C arrives while it runs
CALLBACK_INTERRUPTED = """
import ctypes, signal, sys, time
if sys.argv[1] == "kept":
    from rigctl.cli.interrupts import keep_ctrl_c
    keep_ctrl_c()
libc = ctypes.CDLL(None)
CMP = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
def compare(a, b):
    signal.raise_signal(signal.SIGINT)
    return a[0] - b[0]
numbers = (ctypes.c_int * 2)(2, 1)
try:
    libc.qsort(numbers, 2, ctypes.sizeof(ctypes.c_int), CMP(compare))
    print("back from C", flush=True)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        time.sleep(0.01)
    print("the Ctrl-C was lost")
except KeyboardInterrupt:
    print("interrupted after the callback")
"""

#: numba compiles a kernel; a Ctrl-C arrives while llvmlite's C++ calls numba's hook for the compiled object (as in
#: the CI run), and a fresh kernel cache (so the hook is called)
KERNEL_INTERRUPTED = """
import signal, sys
if sys.argv[1] == "kept":
    from rigctl.cli.interrupts import keep_ctrl_c
    keep_ctrl_c()
from numba.core import codegen
original = codegen.CPUCodeLibrary._object_compiled_hook.__func__
def notify(cls, ll_module, buf):
    signal.raise_signal(signal.SIGINT)
    return original(cls, ll_module, buf)
codegen.CPUCodeLibrary._object_compiled_hook = classmethod(notify)
import numba
@numba.njit(cache=True)
def add_one(x):
    return x + 1
try:
    print("ran:", add_one(1), "- the Ctrl-C was lost")
except KeyboardInterrupt:
    print("interrupted while the kernel compiled")
"""


def _run(mode: str, script: str = CALLBACK_INTERRUPTED, where: Path | None = None, **env: str
         ) -> subprocess.CompletedProcess:
    """``script`` run with ``mode`` (plain: Python's own behaviour; kept: rigctl's hook), from a file in ``where``
    where given (numba caches only kernels defined in a file)."""
    argv = [sys.executable, "-c", script]
    if where is not None:
        (where / f"{mode}.py").write_text(script)
        argv = [sys.executable, str(where / f"{mode}.py")]
    return subprocess.run([*argv, mode], capture_output=True, text=True, timeout=120, env={**os.environ, **env})


def test_a_ctrl_c_while_numba_hands_over_a_compiled_kernel_interrupts_the_compile(tmp_path):
    """The CI run's case on numba's real hook: without :func:`keep_ctrl_c` the interrupt is printed as ignored and the
    compile then fails with numba's "no compiled object yet" (a command would report an internal error); with it, a
    plain ``KeyboardInterrupt`` reaches the code that asked for the kernel."""
    plain = _run("plain", KERNEL_INTERRUPTED, tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "plain"))
    assert "Exception ignored" in plain.stderr and "no compiled object yet" in plain.stderr, plain
    kept = _run("kept", KERNEL_INTERRUPTED, tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "kept"))
    assert kept.stdout.strip() == "interrupted while the kernel compiled" and kept.stderr == "", kept


def test_a_ctrl_c_in_a_callback_from_c_is_raised_again_once_it_has_returned():
    plain = _run("plain")  # Python's own behaviour, which the hook is for
    assert "Exception ignored on calling ctypes callback function" in plain.stderr, plain
    assert "the Ctrl-C was lost" in plain.stdout, plain
    kept = _run("kept")
    # raised in the code that called C, once C returned: at its next call of a builtin (the print) at the latest
    assert kept.stdout.split() == ["interrupted", "after", "the", "callback"], kept
    assert kept.stderr == "", kept  # no traceback, no "Exception ignored"


def test_the_hook_is_installed_once_and_passes_other_exceptions_on(monkeypatch):
    from rigctl.cli.interrupts import keep_ctrl_c

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: seen.append(u.exc_type))
    keep_ctrl_c()
    hook = sys.unraisablehook
    keep_ctrl_c()
    assert sys.unraisablehook is hook

    class Args:
        exc_type, exc_value, exc_traceback, err_msg, object = ValueError, ValueError("x"), None, None, None

    hook(Args())
    assert seen == [ValueError]
