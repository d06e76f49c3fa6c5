"""Clock alignment: the host <-> device clock mapping fitted online from the taxel board's sequence numbers against
host receive times (:class:`DeviceClockFit`), and the host <-> LSL clock offset (:func:`measure_clock_offset`).

The taxel board counts frames on its own crystal (the Uno's 16 MHz resonator: +-0.5 % by its tolerance, a few
hundred ppm in practice), so ``sample_index / nominal_rate`` drifts from host time by up to ~0.5 ms per second; the
host stamps each frame when the reader receives it, i.e. the true time plus a delay that is never negative (USB
polling and batching, the reader's chunks, scheduling; long stalls on a loaded host). The mapping is therefore
fitted on the lower envelope: the frames are unwrapped into a running frame count (``seq`` wraps at 65536), grouped
in blocks of :attr:`DeviceClockFit.block_s` seconds, each block reduced to its least-delayed frame, and a straight
line ``host_time = offset + count * period`` is fitted through the block minima with iterative outlier rejection
(residuals beyond ``max(reject_mad * 1.4826 * MAD, reject_floor_s)`` dropped, refitted). A device reset (the count
restarting, a residual beyond :attr:`reset_s`) starts a new segment. Memory is bounded (the newest
``max_blocks`` blocks), so the fit follows a crystal's slow drift with temperature.

Every sample then has a time on the host clock (:meth:`DeviceClockFit.host_time`), and through the host <-> LSL
offset on the shared LSL clock. Imports nothing else of rigctl's.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["ClockMapping", "DeviceClockFit", "measure_clock_offset"]

_WRAP = 65536
#: the most a device's rate may be off its nominal rate, as a fraction (a ceramic resonator's +-0.5 % four times
#: over): a steeper or flatter fit is not the device's clock but frames of a few blocks received in one burst (a
#: reader starved for seconds), and the nominal rate through the least-delayed block stands instead
MAX_RATE_ERROR = 0.02


@dataclass(frozen=True)
class ClockMapping:
    """A fitted host <-> device mapping: ``host_time_s = offset_s + (count - count_origin) * period_s``.

    Attributes
    ----------
    offset_s : host time (s, the host monotonic clock) of frame ``count_origin``
    period_s : host seconds per device frame (1 / the device's true rate on the host clock)
    count_origin : the running frame count the offset refers to (the segment's first frame: 0)
    nominal_rate_hz : the rate the device announces, Hz
    drift_ppm : ``(nominal period / fitted period - 1) * 1e6``: how fast the device's clock runs, ppm (+: fast)
    residual_s : robust spread (1.4826 MAD) of the kept block minima about the line, s
    n_blocks, n_rejected : block minima used and rejected as outliers
    span_s : host time covered by the fit, s
    segment : how many times the fit restarted (device resets) before this mapping
    """

    offset_s: float
    period_s: float
    count_origin: int
    nominal_rate_hz: float
    drift_ppm: float
    residual_s: float
    n_blocks: int
    n_rejected: int
    span_s: float
    segment: int

    def host_time(self, count: np.ndarray | float) -> np.ndarray:
        """Host times (s) of running frame counts ``count`` (any shape)."""
        return self.offset_s + (np.asarray(count, dtype=np.float64) - self.count_origin) * self.period_s

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class DeviceClockFit:
    """The host <-> device clock mapping, fitted online (module docstring).

    Parameters
    ----------
    nominal_rate_hz : the device's announced frame rate, Hz (the layout's ``sample_rate_hz``)
    block_s : length of a lower-envelope block, s (one minimum per block)
    max_blocks : blocks kept (oldest dropped): the fit's memory, ``max_blocks * block_s`` s
    reject_mad, reject_floor_s : the outlier threshold (see the module docstring)
    reset_s : a new frame further than this from the current fit (its count restarted: a device reset, or a gap no
        count can explain) starts a new segment, s

    Notes
    -----
    Feed it with :meth:`add` (``seq`` uint16 as received, host receive times); :meth:`mapping` fits; the running
    count of the last frame added is :attr:`count`.
    """

    def __init__(self, nominal_rate_hz: float, *, block_s: float = 1.0, max_blocks: int = 3600,
                 reject_mad: float = 4.0, reject_floor_s: float = 200e-6, reset_s: float = 0.25) -> None:
        if not nominal_rate_hz > 0:
            raise ValueError(f"nominal_rate_hz must be > 0, got {nominal_rate_hz}")
        self.nominal_rate_hz = float(nominal_rate_hz)
        self.block_frames = max(1, int(round(block_s * self.nominal_rate_hz)))
        self.max_blocks = int(max_blocks)
        self.reject_mad, self.reject_floor_s, self.reset_s = float(reject_mad), float(reject_floor_s), float(reset_s)
        self.segment = 0
        self._clear()

    def _clear(self) -> None:
        self.count: int | None = None  # running frame count of the last frame added
        self._last_seq = 0
        self._last_t = math.nan
        self._blocks: dict[int, tuple[float, int, float]] = {}  # block -> (lag, count, host time) of its minimum
        self._cached: ClockMapping | None = None  # the last fit and the blocks it was made of
        self._cached_key: tuple[Any, ...] | None = None

    # ----------------------------------------------------------------------------------------------- feeding
    def _unwrap(self, seq: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Running counts of ``seq``: consecutive steps mod 65536; across a gap longer than the counter's wrap, the
        number of wraps the host time elapsed predicts."""
        s = seq.astype(np.int64)
        prev_seq = self._last_seq if self.count is not None else int(s[0])
        prev_t = self._last_t if self.count is not None else float(t[0])
        prev_count = self.count if self.count is not None else 0
        steps = (np.diff(np.concatenate(([prev_seq], s))) & (_WRAP - 1)).astype(np.int64)
        dt = np.diff(np.concatenate(([prev_t], t)))
        period = self._period()
        long = dt * self.nominal_rate_hz > _WRAP / 2
        if np.any(long):  # how many wraps the host time says went by
            expected = dt[long] / period
            steps[long] += np.round((expected - steps[long]) / _WRAP).astype(np.int64) * _WRAP
        if self.count is None:
            steps[0] = 0
        return prev_count + np.cumsum(steps)

    def _period(self) -> float:
        m = self._cached
        return m.period_s if m is not None else 1.0 / self.nominal_rate_hz

    def add(self, seq: np.ndarray, host_time_s: np.ndarray) -> np.ndarray:
        """Feed frames (``seq`` (n,) uint16 as received, ``host_time_s`` (n,) host receive times, s, in order);
        returns their running frame counts (n,) int64 (a device reset restarts the segment: counts from 0 again)."""
        seq = np.asarray(seq)
        t = np.asarray(host_time_s, dtype=np.float64)
        if len(seq) == 0:
            return np.zeros(0, dtype=np.int64)
        counts = self._unwrap(seq, t)
        m = self.mapping() if len(self._blocks) >= 3 else None
        if m is not None:  # received well before the fit says it was sent (a delay is never negative): the
            # count restarted (a device reset) or a gap was miscounted
            if (m.host_time(counts) - t).max() > self.reset_s:
                self.segment += 1
                self._clear()
                counts = self._unwrap(seq, t)
        self.count, self._last_seq, self._last_t = int(counts[-1]), int(seq[-1]), float(t[-1])
        lag = t - counts / self.nominal_rate_hz
        blocks = counts // self.block_frames
        # the least-delayed frame of each block in this chunk, merged with what the block held
        order = np.lexsort((lag, blocks))
        first = np.ones(len(order), dtype=bool)
        first[1:] = blocks[order][1:] != blocks[order][:-1]
        for i in order[first]:
            b = int(blocks[i])
            held = self._blocks.get(b)
            if held is None or lag[i] < held[0]:
                self._blocks[b] = (float(lag[i]), int(counts[i]), float(t[i]))
        if len(self._blocks) > self.max_blocks:
            for b in sorted(self._blocks)[:len(self._blocks) - self.max_blocks]:
                del self._blocks[b]
        return counts

    def preview(self, seq: np.ndarray, host_time_s: np.ndarray) -> np.ndarray:
        """The fitted host times (s, (n,)) that frames (as for :meth:`add`) would get were they added next, NaN
        before a fit exists; the fit itself is left as it was (a source asking whether a frame of a given time has
        arrived yet, before it takes the frames once for good)."""
        trial = copy.copy(self)
        trial._blocks = dict(self._blocks)
        return trial.host_time(trial.add(seq, host_time_s))

    # ----------------------------------------------------------------------------------------------- fitting
    def mapping(self) -> ClockMapping | None:
        """The fitted mapping, or None before two blocks were seen. The fit takes the complete blocks (the block
        still filling joins once it is complete; while fewer than two are complete, every block takes part: its
        minimum is still a time the frame arrived after), so it is refitted once per block, not per call."""
        if len(self._blocks) < 2 or self.count is None:
            return None
        current = self.count // self.block_frames
        done = [b for b in self._blocks if b < current]
        use = done if len(done) >= 2 else list(self._blocks)
        key = (len(use), use[-1] if done else None, self.segment) if len(done) >= 2 else None
        if key is not None and self._cached is not None and key == self._cached_key:
            return self._cached
        pts = np.array([self._blocks[b] for b in use], dtype=np.float64)  # lag, count, t
        c, t = pts[:, 1], pts[:, 2]
        keep = np.ones(len(c), dtype=bool)
        for _ in range(5):
            slope, icpt = np.polyfit(c[keep], t[keep], 1) if keep.sum() >= 2 else (1.0 / self.nominal_rate_hz, t[0])
            r = t - (icpt + slope * c)
            med = float(np.median(r[keep]))  # about the median: an outlier drags the line, not the median
            mad = float(np.median(np.abs(r[keep] - med))) * 1.4826
            new = np.abs(r - med) <= max(self.reject_mad * mad, self.reject_floor_s)
            if new.sum() < 2 or np.array_equal(new, keep):
                break
            keep = new
        if abs(slope * self.nominal_rate_hz - 1.0) > MAX_RATE_ERROR:
            slope = 1.0 / self.nominal_rate_hz
            icpt = float(np.min(t[keep] - slope * c[keep]))
        r = t[keep] - (icpt + slope * c[keep])
        self._cached = ClockMapping(
            offset_s=float(icpt), period_s=float(slope), count_origin=0, nominal_rate_hz=self.nominal_rate_hz,
            drift_ppm=float((1.0 / self.nominal_rate_hz / slope - 1.0) * 1e6),
            residual_s=float(np.median(np.abs(r - np.median(r))) * 1.4826), n_blocks=int(keep.sum()),
            n_rejected=int((~keep).sum()), span_s=float(t.max() - t.min()), segment=self.segment)
        self._cached_key = key
        return self._cached

    def host_time(self, counts: np.ndarray) -> np.ndarray:
        """Fitted host times (s) of running counts (from :meth:`add`); NaN before a fit exists."""
        m = self.mapping()
        if m is None:
            return np.full(np.shape(counts), np.nan)
        return m.host_time(counts)


def measure_clock_offset(other: Callable[[], float], host: Callable[[], float] = time.monotonic, *,
                         rounds: int = 15) -> tuple[float, float]:
    """The offset of the clock ``other`` (e.g. ``pylsl.local_clock``) from ``host`` (default the host monotonic
    clock, the clock frames are stamped on): ``other() - host()`` at the same instant, s, and its uncertainty (half
    the shortest bracket of host reads around one ``other`` read), s. The best of ``rounds`` brackets (NTP's
    minimum-delay rule)."""
    best = (math.inf, 0.0)
    for _ in range(max(1, rounds)):
        a = host()
        o = other()
        b = host()
        if b - a < best[0]:
            best = (b - a, o - (a + b) / 2)
    return best[1], best[0] / 2
