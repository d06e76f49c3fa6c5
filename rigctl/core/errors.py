"""How an error reads in one line, the one home of that format: a status line, a run's error list, an event, a
refusal quoting what a library raised. Used by every layer and face (the CLI's last line of defence,
:mod:`rigctl.cli.errors`, builds on :func:`one_line`)."""

from __future__ import annotations

__all__ = ["describe_error", "one_line"]


def one_line(text: object, max_chars: int | None = None) -> str:
    """``str(text)`` on one line: runs of whitespace (newlines included) become one space; longer than
    ``max_chars`` (if given, >= 4), cut to ``max_chars`` characters ending in ``...``."""
    line = " ".join(str(text).split())
    if max_chars is not None and len(line) > max_chars:
        return line[:max_chars - 3] + "..."
    return line


def describe_error(exc: BaseException, max_chars: int | None = None) -> str:
    """``"TypeName: message"`` for ``exc`` on one line (the message through :func:`one_line`, cut at
    ``max_chars``); just ``"TypeName"`` when the message is empty (``TimeoutError()``)."""
    message = one_line(exc, max_chars)
    return f"{type(exc).__name__}: {message}" if message else type(exc).__name__
