"""Where the libraries' log records go: to the log file, not the operator's terminal, unless ``rigctl --verbose``.

pymodbus logs every retry, timeout and (at debug level) every frame as a hex dump; with no handler of its own its
warnings and errors reached the terminal through Python's last-resort handler ("No response received after 0
retries" beside rigctl's own one-line error), and liblsl (C, under pylsl) printed its INFO lines. :func:`route_library_logs`
gives each library logger of :data:`LIBRARY_LOGGERS` one handler: the log file :func:`log_path` (opened on the first
record, appended), or with ``verbose`` the terminal (stderr, as it is when the record comes); and, unless
``verbose``, has liblsl keep its terminal output to its errors (:func:`rigctl.core.lsl.require_pylsl`). rigctl's own
warnings are not touched.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

__all__ = ["LIBRARY_LOGGERS", "log_path", "route_library_logs"]

#: the loggers of libraries whose records are kept off the terminal unless --verbose
LIBRARY_LOGGERS = ("pymodbus",)
_TAG = "_rigctl_route"


def log_path() -> Path:
    """``$RIGCTL_LOG``, else ``$XDG_STATE_HOME/rigctl/rigctl.log`` (``~/.local/state/rigctl/rigctl.log``)."""
    env = os.environ.get("RIGCTL_LOG")
    if env:
        return Path(env)
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rigctl" / "rigctl.log"


class _Stderr(logging.StreamHandler):
    """The terminal as it is when a record comes (a test runner swaps sys.stderr)."""

    @property
    def stream(self):  # noqa: ANN201 - logging's own attribute
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # noqa: ANN001 - StreamHandler.__init__ sets it
        pass


class _LogFile(logging.FileHandler):
    """The log file, made (with its folder) on the first record; a file that cannot be written drops the records."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            Path(self.baseFilename).parent.mkdir(parents=True, exist_ok=True)
        except OSError:
            return
        super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 - logging's name
        pass  # never a traceback on the terminal for a log file that cannot be written


def route_library_logs(verbose: bool = False) -> None:
    """Give each of :data:`LIBRARY_LOGGERS` one handler (replacing the one given before: the CLI may run many times
    in one process): the terminal with ``verbose`` (their INFO and above), else the log file (WARNING and above);
    their records no longer reach the root logger or Python's last-resort handler."""
    fmt = logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s")
    for name in LIBRARY_LOGGERS:
        logger = logging.getLogger(name)
        for h in [h for h in logger.handlers if getattr(h, _TAG, False)]:
            logger.removeHandler(h)
            h.close()
        handler: logging.Handler = _Stderr() if verbose else _LogFile(log_path(), delay=True, encoding="utf-8")
        handler.setFormatter(fmt)
        handler.setLevel(logging.INFO if verbose else logging.WARNING)
        setattr(handler, _TAG, True)
        logger.addHandler(handler)
        logger.propagate = False
    from rigctl.core.lsl import LIBRARY_LOG_ENV  # liblsl (C) takes its log level from its configuration

    if verbose:
        os.environ.pop(LIBRARY_LOG_ENV, None)
    else:
        os.environ[LIBRARY_LOG_ENV] = str(log_path())
