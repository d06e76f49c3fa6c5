"""Ranges of the numeric options every command shares, checked by click before any work (exit 2, the option named).

One home for each: a seed is what :class:`numpy.random.SeedSequence` and the simulators take (0 .. 2**32 - 1); a
worker count is 1 .. :data:`MAX_WORKERS`; a sample rate is above 0 and at most 1 MHz (no taxel sensor samples
faster: :data:`rigctl.storage.validate.MAX_RATE_HZ`); feature windows per spike train at most :data:`MAX_WINDOWS`.
A float option is a :class:`FiniteRange` (:func:`floats`): click's ``FloatRange`` lets ``nan`` through every bound
(each comparison with NaN is false), which then failed deep inside the work ("cannot convert float NaN to integer").
"""

from __future__ import annotations

from typing import Any

import click

from rigctl.storage.validate import MAX_RATE_HZ

__all__ = ["MAX_SEED", "MAX_WORKERS", "MAX_WINDOWS", "MAX_VOLTS", "SEED", "WORKERS", "WORKERS_OR_0", "RATE_HZ",
           "FiniteRange", "floats"]

MAX_SEED = 2**32 - 1
#: more worker processes than any machine here has cores by far (each is a Python process of its own)
MAX_WORKERS = 1024
#: windows per spike train (100,000 x 100 ms = 10,000 s of trial)
MAX_WINDOWS = 100_000
#: an ADC's reference voltage: far above any data-acquisition input range (an AVR's is at most 5.5 V, a DAQ's 10 V)
MAX_VOLTS = 1000.0


class FiniteRange(click.FloatRange):
    """A ``FloatRange`` that also refuses ``nan`` (and so, with both bounds given, every non-finite value)."""

    name = "float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if rv != rv:  # NaN
            self.fail(f"{value!r} is not a number in the range {self._describe_range()}.", param, ctx)
        return rv


def floats(min: float, max: float, *, min_open: bool = False, max_open: bool = False) -> FiniteRange:
    """A float option's range: both bounds required, NaN refused."""
    return FiniteRange(min, max, min_open=min_open, max_open=max_open)


SEED = click.IntRange(0, MAX_SEED)
WORKERS = click.IntRange(1, MAX_WORKERS)
WORKERS_OR_0 = click.IntRange(0, MAX_WORKERS)
RATE_HZ = floats(0, MAX_RATE_HZ, min_open=True)
#: ``--lsl-wait SECONDS``: how long a run waits for a recorder on its marker stream (0: not at all; at most an hour)
LSL_WAIT_S = floats(0, 3600)


def comma_floats(text: str | None) -> list[float] | None:
    """``"40,60,80"`` -> ``[40.0, 60.0, 80.0]`` (None stays None): the lists of speeds and forces that ``analyze`` and
    the exports' splits take (``--train-speeds``, ``--train-forces``). Raises click.BadParameter (exit 2)."""
    if text is None:
        return None
    try:
        return [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated numbers, got '{text}'") from None
