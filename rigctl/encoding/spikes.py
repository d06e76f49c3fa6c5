"""Spike trains stored NWB-style: one flat ``spike_times`` array plus ``spike_times_index`` of row ends.

The paper represents every spike train as "an ordered list of spike times" (Results, spiking activity encoding
module; Fig. 2D). Many trains (trials x taxels x SA/RA) are kept together as one ragged array, the layout of the
NWB ``Units`` table (``spike_times`` + ``spike_times_index``; stored so in encoded files by
:mod:`rigctl.storage.encoded`): row ``r`` holds
``spike_times[index[r-1]:index[r]]`` (``index[-1]`` taken as 0). Rows are ordered trial-major: row
``trial * n_trains + train``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from rigctl.core.encoding_model import SPIKE_TICK_RTOL

__all__ = ["SpikeTrains"]


#: serial builds (no ``parallel=True`` build: ~2x the compile time, 0.9 against 0.55 s of CPU for the window counts,
#: 0.46 against 0.14 for the gather, on every installation's first analysis), for the same CPU time (the window counts
#: of 4.3 million spikes in 21,600 trains: 14 ms either way, on one core instead of all)
@numba.njit(cache=True, nogil=True)
def _window_counts(times, ends, scale, window_s, n_windows, out):  # pragma: no cover - compiled by numba
    """out[r, w] += spikes of row r (``times[ends[r-1]:ends[r]]``, each times ``scale[r]``: the product
    :meth:`SpikeTrains.scale_times` makes, 1 exact) in window w = floor(round(t / window_s, 9)), numpy's round
    (x * 1e9, rint, / 1e9) so a time k * window_s lands in window k despite float error (the rounding moves the
    quotient by less than 1e-9, so it is done only within 1e-6 of an edge)."""
    for r in range(ends.size):
        start = ends[r - 1] if r > 0 else 0
        for i in range(start, ends[r]):
            q = times[i] * scale[r] / window_s
            b = np.floor(q)
            f = q - b
            if not (1e-6 < f < 1.0 - 1e-6):  # near a window edge: the rounded quotient decides (else it is b)
                b = np.floor(np.rint(q * 1e9) / 1e9)
            if b >= 0 and b < n_windows:
                out[r, int(b)] += 1.0


@numba.njit(cache=True, nogil=True)
def _gather(times, starts, lengths, ends, out):  # pragma: no cover - compiled by numba
    """out[ends[r] - lengths[r]:ends[r]] = times[starts[r]:starts[r] + lengths[r]] for every output row r."""
    for r in range(starts.size):
        o = ends[r] - lengths[r]
        s = starts[r]
        for i in range(lengths[r]):
            out[o + i] = times[s + i]


@numba.njit(cache=True, nogil=True)
def _gather_ticks(times, starts, lengths, ends, tick_s, rtol, out):  # pragma: no cover - compiled by numba
    """:func:`_gather` into uint32 ticks of ``tick_s``: ``out[...] = rint(t / tick_s)``; False (the rest of ``out``
    unset) at the first time off the tick grid (``|ticks * tick_s - t| > rtol |t|``) or outside uint32's range."""
    for r in range(starts.size):
        o = ends[r] - lengths[r]
        s = starts[r]
        for i in range(lengths[r]):
            t = times[s + i]
            k = np.rint(t / tick_s)
            if not (k >= 0.0 and k <= 4294967295.0 and abs(k * tick_s - t) <= rtol * abs(t)):
                return False
            out[o + i] = np.uint32(k)
    return True


@dataclass(frozen=True)
class SpikeTrains:
    """A ragged set of spike trains, ``shape = (n_trials, n_trains)`` logical rows.

    Parameters
    ----------
    spike_times : (n_spikes,) float64, seconds from each trial's first sample (sorted within a row).
    spike_times_index : (n_trials * n_trains,) int64, row ends into ``spike_times`` (NWB convention).
    n_trains : int, trains per trial (e.g. 18 taxels, or 36 = 18 SA + 18 RA).

    Raises
    ------
    ValueError
        if the index is not non-decreasing, does not end at ``len(spike_times)``, or is not a multiple of
        ``n_trains`` long.
    """

    spike_times: np.ndarray
    spike_times_index: np.ndarray
    n_trains: int

    def __post_init__(self):
        times = np.ascontiguousarray(self.spike_times, dtype=np.float64)
        index = np.ascontiguousarray(self.spike_times_index, dtype=np.int64)
        object.__setattr__(self, "spike_times", times)
        object.__setattr__(self, "spike_times_index", index)
        if times.ndim != 1 or index.ndim != 1:
            raise ValueError("spike_times and spike_times_index must be 1-D")
        if self.n_trains <= 0 or index.size % self.n_trains:
            raise ValueError(f"{index.size} rows is not a multiple of n_trains={self.n_trains}")
        if index.size and (np.any(np.diff(index) < 0) or index[0] < 0 or index[-1] != times.size):
            raise ValueError("spike_times_index must be non-decreasing row ends ending at len(spike_times)")
        if not index.size and times.size:
            raise ValueError("spike times without rows")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_counts(cls, spike_times: np.ndarray, counts: np.ndarray) -> "SpikeTrains":
        """Build from flat times and per-row counts ``(n_trials, n_trains)`` int."""
        counts = np.asarray(counts)
        return cls(spike_times, np.cumsum(counts.ravel(), dtype=np.int64), counts.shape[1])

    @classmethod
    def from_lists(cls, trains: list[list[np.ndarray]]) -> "SpikeTrains":
        """Build from nested lists ``trains[trial][train] -> (n,) seconds``."""
        n_trains = len(trains[0]) if trains else 1
        rows = [np.asarray(t, dtype=np.float64) for trial in trains for t in trial]
        if any(len(trial) != n_trains for trial in trains):
            raise ValueError("every trial needs the same number of trains")
        counts = np.array([r.size for r in rows], dtype=np.int64).reshape(len(trains), n_trains)
        times = np.concatenate(rows) if rows else np.zeros(0)
        return cls.from_counts(times, counts)

    @classmethod
    def empty(cls, n_trials: int, n_trains: int) -> "SpikeTrains":
        return cls(np.zeros(0), np.zeros(n_trials * n_trains, dtype=np.int64), n_trains)

    # ------------------------------------------------------------------ shape and access
    @property
    def n_rows(self) -> int:
        return self.spike_times_index.size

    @property
    def n_trials(self) -> int:
        return self.n_rows // self.n_trains

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_trials, self.n_trains)

    @property
    def row_starts(self) -> np.ndarray:
        """(n_rows,) int64 start of each row in ``spike_times``."""
        starts = np.empty_like(self.spike_times_index)
        if starts.size:
            starts[0] = 0
            starts[1:] = self.spike_times_index[:-1]
        return starts

    def counts(self) -> np.ndarray:
        """(n_trials, n_trains) int64 spike count of every train."""
        return np.diff(self.spike_times_index, prepend=0).reshape(self.shape)

    def train(self, trial: int, train: int) -> np.ndarray:
        """Spike times (s) of one train: a view into ``spike_times``."""
        if not (0 <= trial < self.n_trials and 0 <= train < self.n_trains):
            raise IndexError(f"train ({trial}, {train}) outside shape {self.shape}")
        row = trial * self.n_trains + train
        start = self.spike_times_index[row - 1] if row else 0
        return self.spike_times[start : self.spike_times_index[row]]

    def __getitem__(self, key):
        if isinstance(key, tuple):
            return self.train(*key)
        raise TypeError("index SpikeTrains with [trial, train]; use select_trials for subsets")

    def __len__(self) -> int:
        return self.n_trials

    def row_ids(self) -> np.ndarray:
        """(n_spikes,) int64 row of every spike."""
        return np.repeat(np.arange(self.n_rows, dtype=np.int64), np.diff(self.spike_times_index, prepend=0))

    # ------------------------------------------------------------------ transforms
    def _gather_rows(self, rows: np.ndarray, n_trains: int) -> "SpikeTrains":
        rows = np.asarray(rows, dtype=np.int64)
        starts = self.row_starts[rows]
        lengths = self.spike_times_index[rows] - starts
        ends = np.cumsum(lengths)
        out = np.empty(int(ends[-1]) if ends.size else 0, dtype=np.float64)
        _gather(self.spike_times, starts, lengths, ends, out)
        return SpikeTrains(out, ends, n_trains)

    def select_trials(self, trials) -> "SpikeTrains":
        """A new SpikeTrains with the given trials (int array or boolean mask), in that order."""
        trials = np.arange(self.n_trials)[trials]
        rows = (trials[:, None] * self.n_trains + np.arange(self.n_trains)[None, :]).ravel()
        return self._gather_rows(rows, self.n_trains)

    def select_trains(self, trains) -> "SpikeTrains":
        """A new SpikeTrains keeping only the given train columns of every trial."""
        trains = np.arange(self.n_trains)[trains]
        rows = (np.arange(self.n_trials)[:, None] * self.n_trains + trains[None, :]).ravel()
        return self._gather_rows(rows, trains.size)

    def scale_times(self, factor) -> "SpikeTrains":
        """Multiply every spike time of trial ``t`` by ``factor[t]`` (scalar or (n_trials,)); eq. (2) helper."""
        factor = np.broadcast_to(np.asarray(factor, dtype=np.float64), (self.n_trials,))
        per_spike = np.repeat(np.repeat(factor, self.n_trains), np.diff(self.spike_times_index, prepend=0))
        return SpikeTrains(self.spike_times * per_spike, self.spike_times_index, self.n_trains)

    def with_times(self, spike_times: np.ndarray) -> "SpikeTrains":
        """Same rows, new spike times (same length)."""
        return SpikeTrains(spike_times, self.spike_times_index, self.n_trains)

    @staticmethod
    def hstack(parts: list["SpikeTrains"]) -> "SpikeTrains":
        """Join trains side by side per trial (e.g. 18 SA + 18 RA -> 36 trains); trial counts must match."""
        n_trials = parts[0].n_trials
        if any(p.n_trials != n_trials for p in parts):
            raise ValueError("hstack needs the same number of trials in every part")
        joined = SpikeTrains.vstack_rows(parts)
        offsets = np.cumsum([0] + [p.n_rows for p in parts])
        rows = np.concatenate(
            [
                (offsets[i] + np.arange(n_trials)[:, None] * p.n_trains + np.arange(p.n_trains)[None, :])
                for i, p in enumerate(parts)
            ],
            axis=1,
        ).ravel()
        return joined._gather_rows(rows, sum(p.n_trains for p in parts))

    @staticmethod
    def hstack_ticks(parts: list["SpikeTrains"], tick_s: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`hstack` of ``parts`` as ticks of ``tick_s`` s, in one pass without the joined float64 times (what
        an encoded file stores: :meth:`rigctl.storage.encoded.EncodedWriter.append_spike_ticks`).

        Returns
        -------
        (ticks (n_spikes,) uint32 = ``rint(time / tick_s)``, row ends (n_trials * sum of the parts' n_trains,)
        int64) of the joined trains.

        Raises
        ------
        ValueError
            if the parts' trial counts differ, or a time is not a multiple of ``tick_s`` (within
            :data:`~rigctl.core.encoding_model.SPIKE_TICK_RTOL` relative)
            or its tick is outside uint32's range.
        """
        n_trials = parts[0].n_trials
        if any(p.n_trials != n_trials for p in parts):
            raise ValueError("hstack needs the same number of trials in every part")
        counts = np.concatenate([p.counts() for p in parts], axis=1)  # (n_trials, joined trains)
        ends = np.cumsum(counts.ravel(), dtype=np.int64)
        out = np.empty(int(ends[-1]) if ends.size else 0, dtype=np.uint32)
        col = 0
        for p in parts:  # part p's rows land in the joined columns col .. col + p.n_trains - 1 of every trial
            rows = (np.arange(n_trials)[:, None] * counts.shape[1] + col + np.arange(p.n_trains)[None, :]).ravel()
            lengths = np.diff(p.spike_times_index, prepend=0)
            if not _gather_ticks(p.spike_times, p.row_starts, lengths, ends[rows], float(tick_s),
                                 SPIKE_TICK_RTOL, out):
                raise ValueError(f"spike times are not multiples of tick_s = {tick_s:g} s")
            col += p.n_trains
        return out, ends

    @staticmethod
    def vstack_rows(parts: list["SpikeTrains"]) -> "SpikeTrains":
        """Concatenate raw rows (internal helper; trains per trial taken as 1)."""
        times = np.concatenate([p.spike_times for p in parts])
        offs = np.cumsum([0] + [p.spike_times.size for p in parts[:-1]])
        index = np.concatenate([p.spike_times_index + o for p, o in zip(parts, offs)])
        return SpikeTrains(times, index, 1)

    @staticmethod
    def concatenate(parts: list["SpikeTrains"]) -> "SpikeTrains":
        """Concatenate trials (all parts need the same ``n_trains``)."""
        if not parts:
            raise ValueError("nothing to concatenate")
        n_trains = parts[0].n_trains
        if any(p.n_trains != n_trains for p in parts):
            raise ValueError("concatenate needs the same n_trains in every part")
        joined = SpikeTrains.vstack_rows(parts)
        return SpikeTrains(joined.spike_times, joined.spike_times_index, n_trains)

    @staticmethod
    def concat_time(parts: list["SpikeTrains"]) -> "SpikeTrains":
        """Append successive time chunks of the same trains (streaming output) row by row."""
        shape = parts[0].shape
        if any(p.shape != shape for p in parts):
            raise ValueError("concat_time needs chunks of the same shape")
        counts = sum(p.counts() for p in parts)
        joined = SpikeTrains.vstack_rows(parts)
        n_rows = parts[0].n_rows
        rows = (np.arange(len(parts))[None, :] * n_rows + np.arange(n_rows)[:, None]).ravel()
        out = joined._gather_rows(rows, 1)
        return SpikeTrains.from_counts(out.spike_times, counts)  # type: ignore[arg-type]  # an array here

    def window_counts(self, window_s: float, n_windows: int, time_scale=None) -> np.ndarray:
        """(n_trials, n_trains, n_windows) float64 spike counts in non-overlapping windows ``[w*window_s, ...)``.

        Spikes at negative times or beyond ``n_windows * window_s`` are ignored. ``time_scale`` (scalar or
        (n_trials,)): count the times of ``scale_times(time_scale)`` (the same products), without making them.
        """
        out = np.zeros((self.n_rows, int(n_windows)), dtype=np.float64)
        scale = np.repeat(np.broadcast_to(np.asarray(1.0 if time_scale is None else time_scale, np.float64),
                                          (self.n_trials,)), self.n_trains)
        _window_counts(self.spike_times, self.spike_times_index, scale, float(window_s), int(n_windows), out)
        return out.reshape(self.n_trials, self.n_trains, int(n_windows))

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, SpikeTrains)
            and self.n_trains == other.n_trains
            and np.array_equal(self.spike_times_index, other.spike_times_index)
            and np.array_equal(self.spike_times, other.spike_times)
        )

    def __repr__(self) -> str:
        return f"SpikeTrains(n_trials={self.n_trials}, n_trains={self.n_trains}, n_spikes={self.spike_times.size})"
