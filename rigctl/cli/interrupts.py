"""A Ctrl-C is never lost in a callback from C code.

Python raises a Ctrl-C's ``KeyboardInterrupt`` in whatever Python code the main thread runs at that moment. When that
is a callback that C code called through ctypes (numba's compiled-kernel cache: llvmlite's
``ExecutionEngine._raw_object_cache_notify``, called while a command loads or compiles its kernels), the exception
cannot pass through the C frames: Python prints "Exception ignored on calling ctypes callback function" with a
traceback and the program goes on. A loaded CI run met it: ``rigctl sim dataset`` interrupted 0.8 s after its start
printed that traceback and then wrote its whole dataset.

:func:`keep_ctrl_c` raises such an interrupt again, silently, in the Python code that called the C function, as soon
as control is back there (a profile function, ``sys.setprofile``, on that frame's next event): the C code has
returned, and the command ends as a Ctrl-C ends it anywhere else (one line; its partial output removed, or kept
resumable, as the command says). An interrupt swallowed outside the main thread, or with no Python caller, is raised
again in the main thread a moment later (``_thread.interrupt_main``).

C code can also turn a Ctrl-C into an error of its own: a Cython module whose import was interrupted raises
``ImportError: Failed to import 'zlib.decompress' - cannot initialise module strings`` (the ``KeyboardInterrupt``
cleared, not chained), which a loaded CI run met as ``rigctl sim dataset``'s "internal error (a bug in rigctl)" after
a Ctrl-C in its first second. :func:`keep_ctrl_c` also counts each Ctrl-C as it is delivered (its ``SIGINT`` handler
raises the ``KeyboardInterrupt`` as Python's does), and :func:`is_interrupt` takes any exception that ends a command
after one as the Ctrl-C: the command ends as interrupted, in one line.
"""

from __future__ import annotations

import _thread
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType
from typing import Literal

__all__ = ["keep_ctrl_c", "is_interrupt", "stop_on_sigterm", "REDELIVER_S"]

#: a profile function's events (``sys.setprofile``)
ProfileEvent = Literal["call", "return", "c_call", "c_return", "c_exception"]

#: how long after a swallowed Ctrl-C it is raised again in the main thread where its caller cannot be found (s)
REDELIVER_S = 0.01


#: Ctrl-Cs delivered to this process since :func:`keep_ctrl_c` (its SIGINT handler counts them)
_CTRL_C = {"delivered": 0}


def _count_and_raise(signum: int, frame: FrameType | None) -> None:
    """SIGINT: counted, then Python's own handler (``KeyboardInterrupt`` in the main thread's running code)."""
    _CTRL_C["delivered"] += 1
    signal.default_int_handler(signum, frame)


def is_interrupt(exc: BaseException) -> bool:
    """True when ``exc`` ends a command because of a Ctrl-C: a ``KeyboardInterrupt``, or any exception raised once a
    Ctrl-C has been delivered to this process (see the module's text: C code may have turned it into its own
    error). Without :func:`keep_ctrl_c` (an in-process run) only the first."""
    return isinstance(exc, KeyboardInterrupt) or _CTRL_C["delivered"] > 0


def _raise_on_return_to(target: FrameType) -> None:
    """Raise ``KeyboardInterrupt`` at the main thread's next profile event in ``target`` (a builtin it calls or its own
    return): the first moment its Python code runs again."""
    previous = sys.getprofile()

    def profile(frame: FrameType, event: ProfileEvent, arg: object) -> None:
        if frame is target and event in ("c_call", "c_return", "return"):
            sys.setprofile(previous)
            raise KeyboardInterrupt
        if previous is not None:
            previous(frame, event, arg)

    sys.setprofile(profile)


def _redeliver_later() -> None:
    timer = threading.Timer(REDELIVER_S, _thread.interrupt_main)
    timer.daemon = True
    timer.start()


def _sigterm_as_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def stop_on_sigterm() -> None:
    """SIGTERM (a service manager, ``kill``) ends the command as a Ctrl-C does: its ``finally`` blocks run (a rig left
    safe, a partial output and its lock removed) instead of the process dying where it stands. Main thread only."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _sigterm_as_interrupt)


def keep_ctrl_c() -> None:
    """Install the hook (``sys.unraisablehook``, wrapping the one in place): an unraisable ``KeyboardInterrupt`` is
    not printed but raised again once C code has returned to its Python caller (see the module's text); every other
    unraisable exception goes to the previous hook. And, in the main thread where SIGINT has Python's own handler,
    the handler that counts each Ctrl-C (:func:`is_interrupt`). Idempotent. Called by the ``rigctl`` entries (the console script,
    ``python -m rigctl``, the tests' preloaded launcher), not by in-process runs."""
    if threading.current_thread() is threading.main_thread() \
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _count_and_raise)
    previous: Callable[[sys.UnraisableHookArgs], object] = sys.unraisablehook
    if getattr(previous, "_rigctl_keeps_ctrl_c", False):
        return

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if unraisable.exc_type is None or not issubclass(unraisable.exc_type, KeyboardInterrupt):
            previous(unraisable)
            return
        try:  # the Python code that called the C code whose callback swallowed the interrupt
            caller = sys._getframe(1)
        except ValueError:  # none: the hook was called from C alone
            _redeliver_later()
            return
        if threading.current_thread() is threading.main_thread():
            _raise_on_return_to(caller)
        else:
            _redeliver_later()

    hook._rigctl_keeps_ctrl_c = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook
