"""A deterministic taxel source for link tests and the soak benchmark: every recorded sample can be checked.

Sample ``k`` (counted from the board's start) holds ``(k * 7 + channel) % 1024`` on each of the 18 channels, and
every 500th sample is an index (SYNC_IN) sample. A frame recorded intact therefore satisfies
``(samples[ch] - samples[0]) % 1024 == ch`` for every channel, and a frame whose bytes were damaged on the way
(a bad CRC that got through) almost never does; the sample number of a frame of a stream started at sample ``s``
with sequence number ``seq`` is ``s + seq``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CountingSource", "counting_samples", "intact_frames"]

_N = 18


def counting_samples(k: np.ndarray, n_channels: int = _N) -> np.ndarray:
    """``(len(k), n_channels)`` uint16: the counting source's samples number ``k`` (int64 sample numbers)."""
    k = np.asarray(k, dtype=np.int64)
    return ((k[:, None] * 7 + np.arange(n_channels)[None, :]) % 1024).astype(np.uint16)


def intact_frames(samples: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: which of ``(n, n_channels)`` recorded samples are a counting-source sample, undamaged."""
    s = np.asarray(samples, dtype=np.int64)
    return np.all((s - s[:, :1]) % 1024 == np.arange(s.shape[1])[None, :], axis=1)


class CountingSource:
    """Source for :meth:`rigctl.simulation.virtual_uno.VirtualUno.run_paced`: ``source(n) -> (samples, sync)``,
    ``(n, 18)`` uint16 counting samples and ``(n,)`` bool index flags (every 500th sample)."""

    def __init__(self):
        self.k = 0

    def __call__(self, n: int):
        k = self.k + np.arange(n)
        self.k += n
        return counting_samples(k), (k % 500) == 0
