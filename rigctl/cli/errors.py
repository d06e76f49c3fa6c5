"""The command line's last line of defence: an error reaches the user as one line, never as a traceback.

:func:`as_click_error` turns an exception that escaped a command into a :class:`click.ClickException`:

- rigctl's own error types (any exception class defined in a ``rigctl.`` module: ``SessionError``, ``DrumError``,
  ``CalibrationError``, ``ProtocolError``, ``TextureSetError``, ``RigError``, ``FileBusy``, ...) and operating-system
  errors (``OSError``: a file that cannot be read or written, a full disk) become ``Error: <message>`` (exit 1);
- anything else is a bug: it becomes ``Error: internal error (a bug in rigctl): <type>: <message> at <file:line>;
  run with --debug for the traceback`` (exit 1), so it stays visible without a wall of text.

``rigctl --debug ...`` (or ``RIGCTL_DEBUG=1``) lets every exception through with its traceback.
"""

from __future__ import annotations

import os
import re
import traceback

import click

from rigctl.core.errors import one_line as core_one_line

__all__ = ["as_click_error", "is_rigctl_error", "one_line", "plain_numbers"]

#: the repr of a numpy scalar (numpy >= 2): np.float64(1.5), np.int64(3), np.str_('A'), np.True_
_NUMPY_REPR = re.compile(r"\bnp\.(?:float|int|uint|complex|longdouble|str_|bytes_)\w*\(([^()]*)\)|\bnp\.(True|False)_")


def plain_numbers(text: str) -> str:
    """``text`` with numpy scalar reprs (``np.float64(1.5)``) shown as their values (``1.5``): a message from
    code that formatted a numpy value with ``!r`` or inside a list still reads as plain numbers."""
    return _NUMPY_REPR.sub(lambda m: m.group(1) if m.group(1) is not None else m.group(2), text)


def one_line(text: object) -> str:
    """``text`` on one line (runs of whitespace, newlines included, become one space), numpy reprs as plain
    values."""
    return plain_numbers(core_one_line(text))


def is_rigctl_error(exc: BaseException) -> bool:
    """True if ``exc`` is (a subclass of) an exception type defined by rigctl itself."""
    return any(getattr(cls, "__module__", "").startswith("rigctl.") for cls in type(exc).__mro__)


def _message(exc: BaseException) -> str:
    if isinstance(exc, KeyError) and exc.args:  # str(KeyError) is the repr of its key
        return one_line(exc.args[0])
    return one_line(exc) or type(exc).__name__


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    f = frames[-1]
    return f" at {os.path.basename(f.filename)}:{f.lineno}"


def as_click_error(exc: Exception) -> click.ClickException:
    """The one-line :class:`click.ClickException` shown for ``exc`` (see the module docstring)."""
    from rigctl.storage.outputs import OutputError

    if isinstance(exc, OutputError):  # an output refused before any work: a usage error
        from rigctl.cli.outputs import UsageProblem

        return UsageProblem(_message(exc))
    if is_rigctl_error(exc):
        return click.ClickException(_message(exc))
    if isinstance(exc, OSError):
        msg = _message(exc)
        if exc.filename is not None and str(exc.filename) not in msg:
            msg = f"{exc.filename}: {msg}"
        return click.ClickException(msg)
    return click.ClickException(f"internal error (a bug in rigctl): {type(exc).__name__}: {_message(exc)}"
                                f"{_where(exc)}; run `rigctl --debug ...` for the traceback")
