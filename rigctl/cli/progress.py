"""tqdm bars on stderr from the library's progress events (:mod:`rigctl.core.progress`): the command line's one
adapter, handed as ``progress=`` to the long functions it calls."""

from __future__ import annotations

import contextlib
import sys
import time
from typing import Any

from rigctl.core.progress import ProgressEvent

__all__ = ["TqdmProgress", "bars"]

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


def bars(enabled: bool = True, **kw):
    """``with bars(enabled) as progress:`` -> a :class:`TqdmProgress` when ``enabled`` (the command's ``--progress``
    / not ``--quiet``), else None (no bars); the last bar is closed on leaving the block."""
    return TqdmProgress(**kw) if enabled else contextlib.nullcontext(None)
