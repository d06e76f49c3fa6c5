"""Positions of frames in a capture's parts (:class:`rigctl.devices.taxel_stream.TaxelStream`'s running capture, and
:class:`rigctl.simulation.inprocess.InProcessTaxels`'): tuples ``(samples, seq, flags, host_time_s)`` of arrays, in
the order the frames came."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["first_flagged", "first_with_seq"]


def first_flagged(parts: Any, mask: int) -> int | None:
    """Position of the first frame with a bit of ``mask`` in its flags, over capture parts ``(samples, seq, flags,
    host_time_s)`` in order; None if there is none."""
    at = 0
    for part in parts:
        hit = np.flatnonzero(part[2] & mask)
        if hit.size:
            return at + int(hit[0])
        at += len(part[2])
    return None


def first_with_seq(parts: Any, seq: int) -> int | None:
    """Position of the first frame whose wire sequence number is ``seq`` (mod 65536), over capture parts ``(samples,
    seq, flags, host_time_s)`` in order; None if there is none."""
    at, want = 0, int(seq) & 0xFFFF
    for part in parts:
        hit = np.flatnonzero((part[1].astype(np.int64) & 0xFFFF) == want)
        if hit.size:
            return at + int(hit[0])
        at += len(part[1])
    return None
