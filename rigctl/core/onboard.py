"""What a taxel board that encodes on board (the Uno encoder image, docs/wire-protocol.md 1.5) gives for one scan:
:class:`OnboardEncoding`, the trial's record in place of its raw taxels (:attr:`rigctl.core.trial.TrialData.onboard`).
Imports nothing else of rigctl's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["OnboardEncoding"]


def _ints(dtype: type) -> np.ndarray:
    return np.zeros(0, dtype=dtype)


@dataclass
class OnboardEncoding:
    """One scan encoded on the taxel board: its spikes, its counts frame, the speeds it scaled with, its flags.

    Attributes
    ----------
    spike_sample : (s,) int64, the sample of each spike, counted from the first sample the board encoded (sample 0
        is the one after ENCODE; the board samples at ``rate_hz``).
    spike_taxel : (s,) uint8, the taxel of each spike (0-8: the top layer, row-major).
    counts : (n_taxels, n_windows) uint16, the counts frame: spikes per taxel and 100 ms scaled-time window.
    speeds_mm_s : (w,) float64, the speed each real-time 100 ms window was scaled with on the board (mm/s; a held
        window's is the window before's).
    held_windows : (h,) int64, the real-time windows the board scaled with the last speed (theirs came late).
    samples : the samples the board encoded.
    dropped_samples : samples the board's queue lost (the counts frame's ``dropped``).
    queue_max : the deepest the board's sample queue was.
    rate_hz : the board's sample rate, Hz.
    """

    spike_sample: np.ndarray = field(default_factory=lambda: _ints(np.int64))
    spike_taxel: np.ndarray = field(default_factory=lambda: _ints(np.uint8))
    counts: np.ndarray = field(default_factory=lambda: np.zeros((9, 20), np.uint16))
    speeds_mm_s: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))
    held_windows: np.ndarray = field(default_factory=lambda: _ints(np.int64))
    samples: int = 0
    dropped_samples: int = 0
    queue_max: int = 0
    rate_hz: float = 1000.0

    def __post_init__(self) -> None:
        self.spike_sample = np.asarray(self.spike_sample, np.int64).reshape(-1)
        self.spike_taxel = np.asarray(self.spike_taxel, np.uint8).reshape(-1)
        self.counts = np.asarray(self.counts, np.uint16)
        self.speeds_mm_s = np.asarray(self.speeds_mm_s, np.float64).reshape(-1)
        self.held_windows = np.asarray(self.held_windows, np.int64).reshape(-1)
        if self.spike_sample.shape != self.spike_taxel.shape:
            raise ValueError(f"spike_sample {self.spike_sample.shape} and spike_taxel {self.spike_taxel.shape} must "
                             "have the same length")
        if self.counts.ndim != 2:
            raise ValueError(f"counts must be (n_taxels, n_windows), got {self.counts.shape}")
        self.samples, self.dropped_samples, self.queue_max = (int(self.samples), int(self.dropped_samples),
                                                              int(self.queue_max))
        self.rate_hz = float(self.rate_hz)

    @classmethod
    def from_raster(cls, raster: np.ndarray, **fields: object) -> "OnboardEncoding":
        """From a spike raster ``(n_samples, n_taxels)`` (1 = a spike at that sample), ``samples`` its rows unless
        given; ``fields`` the other attributes."""
        r = np.asarray(raster)
        sample, taxel = np.nonzero(r)
        fields.setdefault("samples", int(r.shape[0]))
        return cls(spike_sample=sample, spike_taxel=taxel, **fields)  # type: ignore[arg-type]

    def spike_times_s(self, taxel: int) -> np.ndarray:
        """Taxel ``taxel``'s spike times, s from the first encoded sample."""
        return self.spike_sample[self.spike_taxel == taxel] / self.rate_hz

    @property
    def duration_s(self) -> float:
        """The encoded span, s (``samples / rate_hz``)."""
        return self.samples / self.rate_hz
