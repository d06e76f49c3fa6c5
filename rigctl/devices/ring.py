"""A fixed-size, thread-safe ring buffer of taxel frames for live consumers (GUI, monitors).

One writer (the :class:`rigctl.devices.taxel_stream.TaxelStream` reader thread) appends; any number of readers each
keep their own cursor (an absolute frame count) and call :meth:`RingBuffer.read_since`.
"""

from __future__ import annotations

import threading

import numpy as np

from rigctl.devices import wire


class RingBuffer:
    """Ring of the last ``capacity`` frames: samples ``(capacity, n_channels) uint16`` ADC counts, ``seq`` uint16,
    ``flags`` uint8 and host receive time ``float64`` s (``time.monotonic`` clock).

    Parameters
    ----------
    capacity : int
        Number of frames kept (e.g. 30 s x 1000 frames/s). Must be >= 1; ``ValueError`` otherwise.
    n_channels : int
        Channels per frame (the stream's ``layout.n_channels``; 18 for the paper's sensor). >= 1.
    """

    def __init__(self, capacity: int, n_channels: int = wire.N_TAXELS) -> None:
        capacity = int(capacity)
        if capacity < 1:
            raise ValueError(f"ring capacity must be >= 1 frame, got {capacity}")
        if int(n_channels) < 1:
            raise ValueError(f"ring frames need at least one channel, got {n_channels}")
        self.capacity = capacity
        self.n_channels = int(n_channels)
        self._samples = np.zeros((capacity, self.n_channels), np.uint16)
        self._seq = np.zeros(capacity, np.uint16)
        self._flags = np.zeros(capacity, np.uint8)
        self._time = np.zeros(capacity, np.float64)
        self._total = 0  # frames ever written
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        """Frames written since creation (the cursor of a reader that is up to date)."""
        return self._total

    def write(self, samples: np.ndarray, seq: np.ndarray, flags: np.ndarray, host_time_s: np.ndarray) -> None:
        """Append n frames: ``samples (n, n_channels)``, ``seq (n,)``, ``flags (n,)``, ``host_time_s (n,)``."""
        n = len(seq)
        if n == 0:
            return
        if n > self.capacity:  # only the newest fit
            cut = n - self.capacity
            samples, seq, flags, host_time_s = samples[cut:], seq[cut:], flags[cut:], host_time_s[cut:]
            skipped, n = cut, self.capacity
        else:
            skipped = 0
        with self._lock:
            start = (self._total + skipped) % self.capacity
            first = min(n, self.capacity - start)  # up to the ring's end, then the rest from its start
            for lo, hi, at in ((0, first, start), (first, n, 0)):
                if hi > lo:
                    self._samples[at:at + hi - lo] = samples[lo:hi]
                    self._seq[at:at + hi - lo] = seq[lo:hi]
                    self._flags[at:at + hi - lo] = flags[lo:hi]
                    self._time[at:at + hi - lo] = host_time_s[lo:hi]
            self._total += skipped + n

    def _window(self, cursor: int, max_frames: int | None) -> tuple[int, np.ndarray]:
        """(total, ring indices of the frames after ``cursor``, oldest first); call with the lock held."""
        total = self._total
        start = max(int(cursor), total - self.capacity, 0)
        if max_frames is not None:
            start = max(start, total - int(max_frames))
        return total, (start + np.arange(total - start)) % self.capacity

    def read_since(self, cursor: int, max_frames: int | None = None) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """Frames written after ``cursor`` (a value returned by an earlier call, or 0).

        Returns
        -------
        (cursor, samples, seq, host_time_s):
            the new cursor (pass it to the next call), ``(n, n_channels) uint16`` ADC counts, ``(n,) uint16`` device
            sequence numbers and ``(n,) float64`` host receive times in s. If the reader fell more than
            ``capacity`` frames behind, the oldest frames are gone and only the last ``capacity`` are returned.
            ``max_frames`` limits n to the newest ``max_frames`` frames.
        """
        with self._lock:
            total, idx = self._window(cursor, max_frames)
            return total, self._samples[idx].copy(), self._seq[idx].copy(), self._time[idx].copy()

    def timing_since(self, cursor: int, max_frames: int | None = None) -> tuple[int, np.ndarray, np.ndarray]:
        """:meth:`read_since` without the samples: ``(cursor, seq (n,) uint16, host_time_s (n,) float64)`` (a rate
        estimate over the ring's history needs no ADC counts)."""
        with self._lock:
            total, idx = self._window(cursor, max_frames)
            return total, self._seq[idx].copy(), self._time[idx].copy()

    def latest(self, n: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The newest ``n`` frames (or fewer): same tuple as :meth:`read_since`."""
        return self.read_since(0, max_frames=n)
