"""Taxel frames for the drum controller's firmware under simavr run alone (``HilRig(with_uno=False)``): the fault
campaign's hil cases of the Mega's faults (issue 80 item 4).

A simulated Uno costs more than the Mega it sits beside (measured on this 2-core machine: 0.21-0.24 CPU-s a simulated
second for the Uno's core, 0.10 for the Mega's, ~0.2 for the host reading its 1 kHz frames; a campaign case is 19-50 s
of simulated time), and none of the Mega's faults reaches the taxels: the host's run needs the frames only to record
its trials, aligned on the drum's index pulse. :class:`IndexFrames` gives it those frames from the rig's one clock:
one a millisecond of the world's time, every taxel at mid-scale, ``SYNC_IN`` on the frame that ends after each index
pulse the Mega's harness reports (its ``IDX`` lines: the pin the Uno's sync-in is wired to). Nothing in them is a
measurement: a rig built so names its taxels ``index-frames`` (:attr:`IndexFrames.banner`), and the Uno's own faults
(``taxel-link-drop``, ``taxel-ohm``) run with both boards.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence

import numpy as np

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.shared_clock import SharedClock
from rigctl.devices import wire
from rigctl.devices.taxel_stream import Capture, StreamStats

__all__ = ["IndexFrames", "MID_SCALE"]

#: every taxel's count in the frames (the 10-bit ADC's mid-scale)
MID_SCALE = 512


class IndexFrames:
    """:class:`rigctl.core.interfaces.TaxelSource` on ``clock`` (the simulated rig's :class:`SharedClock`, s): frame
    ``k`` of the stream ends at ``k / rate`` s of the world's time; ``index_times_s()`` gives the Mega's index pulses
    so far (s, the same clock). The host times of a capture are that clock's (as the drum client's status times)."""

    def __init__(self, clock: SharedClock, index_times_s: Callable[[], Sequence[float]],
                 layout: SensorLayout = PAPER_SENSOR) -> None:
        self.clock = clock
        self.port = "index-frames"
        self._index_times_s = index_times_s
        self._layout = layout
        self._rate = float(layout.sample_rate_hz)
        self._lock = threading.Lock()
        self.banner: dict | None = None
        self._start_k: int | None = None  # the stream's first frame (None: not streaming)
        self._capture_k: int | None = None  # the capture's first frame

    @property
    def layout(self) -> SensorLayout:
        return self._layout

    def _k_now(self) -> int:
        """The last frame ended by now."""
        return int(math.floor(self.clock.now() * self._rate))

    @property
    def stats(self) -> StreamStats:
        with self._lock:
            start = self._start_k
        frames = 0 if start is None else max(0, self._k_now() - start + 1)
        return StreamStats(frames=frames, frames_per_s=self._rate if start is not None else 0.0, connected=True)

    def open(self) -> dict:
        lay = self._layout
        self.banner = {"firmware": wire.UNO_FIRMWARE_VERSION, "channels": lay.n_channels, "ch": lay.n_channels,
                       "rate_hz": lay.sample_rate_hz, "bits": lay.adc_bits, "baud": 0,
                       "line": "index-frames: no Uno; mid-scale frames marked at the Mega's index pulses"}
        return self.banner

    def start(self) -> None:
        with self._lock:
            self._start_k = self._k_now() + 1

    def stop(self) -> None:
        with self._lock:
            self._start_k = None

    def close(self) -> None:
        self.stop()

    def begin_capture(self) -> None:
        with self._lock:
            self._capture_k = self._k_now() + 1

    def _captured(self) -> tuple[int, int]:
        """The capture's first frame and how many frames it holds now (0, 0 without one)."""
        with self._lock:
            first = self._capture_k
        if first is None:
            return 0, 0
        return first, max(0, self._k_now() - first + 1)

    def wait_capture(self, n_frames: int, timeout_s: float) -> bool:
        """Wait on the clock until the capture holds ``n_frames`` frames (True) or ``timeout_s`` s passed (False)."""
        deadline = self.clock.now() + max(0.0, timeout_s)
        while True:
            first, n = self._captured()
            if self._capture_k is None:
                return False
            if n >= n_frames:
                return True
            now = self.clock.now()
            if now >= deadline:
                return False
            self.clock.sleep(min(deadline - now, (n_frames - n) / self._rate))

    def _sync_frames(self, first: int, n: int) -> np.ndarray:
        """Positions in the capture (frames ``first`` .. ``first + n - 1``) of the frames flagged SYNC_IN: each the
        first frame ending at or after an index pulse."""
        t = np.asarray(list(self._index_times_s()), dtype=float)
        k = np.ceil(t * self._rate).astype(np.int64) - first
        return np.unique(k[(k >= 0) & (k < n)])

    def capture_flag_index(self, mask: int) -> int | None:
        """Position of the first frame of the running capture with a bit of ``mask`` in its flags (None: none yet)."""
        first, n = self._captured()
        if not mask & int(wire.FrameFlag.SYNC_IN) or n == 0:
            return None
        hits = self._sync_frames(first, n)
        return int(hits[0]) if hits.size else None

    def capture_seq_index(self, seq: int) -> int | None:
        """Position of the first frame of the running capture of wire sequence number ``seq`` (None: none yet)."""
        first, n = self._captured()
        with self._lock:
            start = self._start_k
        if start is None or n == 0:
            return None
        at = (int(seq) - (first - start)) % 65536
        return at if at < n else None

    def end_capture(self) -> Capture:
        first, n = self._captured()
        with self._lock:
            start = self._start_k if self._start_k is not None else first
            self._capture_k = None
        k = first + np.arange(n, dtype=np.int64)
        flags = np.zeros(n, np.uint8)
        flags[self._sync_frames(first, n)] |= int(wire.FrameFlag.SYNC_IN)
        if n and first == start:
            flags[0] |= int(wire.FrameFlag.STREAMING_START)
        samples = np.full((n, self._layout.n_channels), MID_SCALE, np.uint16)
        return Capture(samples=samples, seq=((k - start) % 65536).astype(np.uint16), flags=flags,
                       host_time_s=k / self._rate)
