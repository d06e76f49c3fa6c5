"""Run the Qt event loop until a condition holds (used by the screenshot driver and the GUI tests)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_for(app, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Process ``app``'s events until ``predicate()`` is true or ``timeout_s`` (s) passes; returns the last value."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        app.processEvents()
        if predicate():
            return True
        time.sleep(0.01)
    return bool(predicate())
