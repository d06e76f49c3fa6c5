"""tqdm bars on stderr from the library's progress events (:mod:`rigctl.core.progress`): the command line's one
adapter, handed as ``progress=`` to the long functions it calls."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable
from typing import Any

import click

from rigctl.core.progress import ProgressEvent

__all__ = ["PROGRESS_HELP", "TqdmProgress", "bars", "progress_option", "show_bars"]

#: a bar is redrawn at most this often, s (tqdm's own default ``mininterval``)
REDRAW_S = 0.1


class TqdmProgress:
    """A ``progress`` callback drawing one tqdm bar per stage (the previous stage's bar closes when a new stage
    starts); a message without a count is written above the bars. Use as a context manager (closes the last bar)."""

    def __init__(self, *, leave: bool = True):
        self.leave = leave
        self._bar: Any = None  # a tqdm bar (tqdm ships no type information)
        self._stage: str | None = None
        self._drawn = -float("inf")  # time.monotonic() of the last redraw

    def __call__(self, event: ProgressEvent) -> None:
        from tqdm import tqdm

        if event.total is None:
            if event.stage != self._stage:  # a note of the next stage: the finished bar is drawn once, not again
                self.close()
            if event.message:
                tqdm.write(event.message, file=sys.stderr)
            return
        if self._bar is None or event.stage != self._stage:
            self.close()
            self._stage = event.stage
            self._bar = tqdm(total=event.total, initial=event.done, desc=event.stage, unit=event.unit,
                             leave=self.leave)
        if self._bar.total != event.total:
            self._bar.total = event.total
        self._bar.n = event.done
        if event.message:
            self._bar.set_postfix_str(event.message, refresh=False)
        now = time.monotonic()
        # drawn at most every REDRAW_S (an export sends an event per trial: 48,000 redraws at the paper's size), and
        # always at a stage's end and with a message
        if event.message or event.done >= event.total or now - self._drawn >= REDRAW_S:
            self._bar.refresh()
            self._drawn = now

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._bar, self._stage = None, None

    def __enter__(self) -> "TqdmProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


PROGRESS_HELP = ("Progress bars on stderr (default: on when stderr is a terminal, off when it is a file or a pipe, "
                 "so logs get no bar updates).")


def _quiet(ctx: click.Context, param: click.Parameter, value: bool) -> bool:
    if value:
        ctx.meta["rigctl.no_progress"] = True
    return value


def progress_option(f: Callable[..., Any]) -> Callable[..., Any]:
    """The ``--progress/--no-progress`` option of a long command (parameter ``progress``: True, False or None for
    "not said": :func:`show_bars` decides), with ``--quiet`` kept as another spelling of ``--no-progress``."""
    f = click.option("--quiet", is_flag=True, expose_value=False, callback=_quiet,
                     help="Same as --no-progress.")(f)
    return click.option("--progress/--no-progress", "progress", default=None, help=PROGRESS_HELP)(f)


def show_bars(progress: bool | None) -> bool:
    """Whether to draw bars: ``--no-progress`` / ``--quiet`` no, ``--progress`` yes, else only on a terminal."""
    ctx = click.get_current_context(silent=True)
    if ctx is not None and ctx.meta.get("rigctl.no_progress"):
        return False
    if progress is not None:
        return bool(progress)
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stderr
        return False


def bars(enabled: bool = True, **kw):
    """``with bars(enabled) as progress:`` -> a :class:`TqdmProgress` when ``enabled`` (:func:`show_bars` of the
    command's ``--progress``), else None (no bars); the last bar is closed on leaving the block."""
    return TqdmProgress(**kw) if enabled else contextlib.nullcontext(None)
