"""A replay source read at its own rate by a simulated taxel board that steps in milliseconds of physics.

The simulated rig (:class:`rigctl.simulation.rig.SimulatedRig`, on ptys) and the in-process rig
(:class:`rigctl.simulation.inprocess.InProcessTaxels`) both stream a source (a recording, a live LSL stream, a
sensor-only plugin's :class:`rigctl.core.rig_plugins.SampleSource`) instead of the model's sensor: each physics step
of ``n_ms`` ms asks :meth:`SourcePacer.step` for the source's samples due by then.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout

__all__ = ["SourcePacer", "source_reader", "source_layout"]


def source_reader(source: Any) -> Callable[[int], Any]:
    """``n -> (n, ch) uint16`` of a replay source (an object with ``read(n)``, or a callable); TypeError otherwise."""
    if hasattr(source, "read"):
        return source.read
    if callable(source):
        return source
    raise TypeError(f"source must have read(n) or be callable, got {type(source).__name__}")


def source_layout(source: Any) -> SensorLayout:
    """The sensor a source streams: its ``layout`` (TypeError when it is not a SensorLayout), else the paper's."""
    layout = getattr(source, "layout", None)
    if layout is not None and not isinstance(layout, SensorLayout):
        raise TypeError(f"source.layout must be a SensorLayout, got {type(layout).__name__}")
    return layout or PAPER_SENSOR


class SourcePacer:
    """The samples of ``source`` (``read(n)``) at ``layout.sample_rate_hz``, stepped by whole milliseconds.

    :meth:`step` gives the samples due in the next ``n_ms`` ms (sample j is due at ``j / rate``) with the index
    pulse (SYNC_IN) of the step on its last sample; a pulse in a step with no sample due goes on the next sample.
    A live source behind the board's clock (:class:`rigctl.simulation.lsl_replay.LslReplay`) gives fewer rows than
    asked: the periods it had no sample for are the step's last, ``unsent`` (the board sends no frame for them).
    """

    def __init__(self, source: Any, layout: SensorLayout) -> None:
        self.read = source_reader(source)
        self.layout = layout
        self._ms_total = 0
        self._samples_total = 0
        self._pulse_pending = False

    def step(self, n_ms: int, sync_in: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, int]:
        """``(samples (n, ch) uint16, sync_in (n,) bool or None, unsent)`` of the next ``n_ms`` ms (``sync_in``:
        the model's index pulse per millisecond, or None; ``unsent``: how many of the last rows the source had no
        sample for, filled, not to be sent)."""
        ch = self.layout.n_channels
        rate = self.layout.sample_rate_hz
        if rate == 1000.0:  # one sample per simulated millisecond, the index pulse of each
            n = n_ms
        else:  # the source's own rate
            self._ms_total += n_ms
            due = int(self._ms_total * rate / 1000.0)
            n = due - self._samples_total
            self._samples_total = due
            self._pulse_pending |= sync_in is not None and bool(np.any(sync_in))
            sync_in = None
            if n > 0 and self._pulse_pending:  # an index pulse since the last sample marks this step's last one
                sync_in = np.zeros(n, bool)
                sync_in[-1] = True
                self._pulse_pending = False
        if n <= 0:
            return np.zeros((0, ch), np.uint16), None, 0
        got = np.asarray(self.read(n), dtype=np.uint16).reshape(-1, ch)
        unsent = n - len(got)
        if unsent > 0:
            got = np.concatenate([got, np.zeros((unsent, ch), np.uint16)])
        return got, sync_in, max(unsent, 0)
