"""Ranges of the numeric options every command shares, checked by click before any work (exit 2, the option named).

One home for each: a seed is what :class:`numpy.random.SeedSequence` and the simulators take (0 .. 2**32 - 1); a
worker count is 1 .. :data:`MAX_WORKERS`; a sample rate is above 0 and at most 1 MHz (no taxel sensor samples
faster: :data:`rigctl.storage.validate.MAX_RATE_HZ`); feature windows per spike train at most :data:`MAX_WINDOWS`.
"""

from __future__ import annotations

import click

from rigctl.storage.validate import MAX_RATE_HZ

__all__ = ["MAX_SEED", "MAX_WORKERS", "MAX_WINDOWS", "SEED", "WORKERS", "WORKERS_OR_0", "RATE_HZ"]

MAX_SEED = 2**32 - 1
#: more worker processes than any machine here has cores by far (each is a Python process of its own)
MAX_WORKERS = 1024
#: windows per spike train (100,000 x 100 ms = 10,000 s of trial)
MAX_WINDOWS = 100_000

SEED = click.IntRange(0, MAX_SEED)
WORKERS = click.IntRange(1, MAX_WORKERS)
WORKERS_OR_0 = click.IntRange(0, MAX_WORKERS)
RATE_HZ = click.FloatRange(0, MAX_RATE_HZ, min_open=True)
