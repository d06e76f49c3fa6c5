"""How big an encoding is before it starts: the output file and the memory of one batch, estimated from the session's
header and plan alone (no trial is read), so an absurd option is refused with the figure in well under a second.

Features: ``2 x n_channels`` trains x windows x 4 bytes (float32) per trial and variant (:mod:`rigctl.encoding.features`;
unscaled variants use ``n_windows_unscaled``, speed-scaled ones ``n_windows_scaled``, real-time ones
``n_windows_realtime`` on the first layer). Spike trains: :data:`SPIKES_PER_S` per train and second, 4-byte ticks,
for the stored variants. A batch holds its readings as float64 three times over (input, SA, RA state) plus its
feature rows.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.encoding.speed import WINDOW_S
from rigctl.storage.encoded import ALL_VARIANTS, MAIN_VARIANTS, VARIANTS
from rigctl.storage.validate import MAX_RATE_HZ, MAX_TRIAL_S

__all__ = ["EncodeSize", "SPIKES_PER_S", "available_memory_bytes", "estimate_encode", "windows_for"]

#: spikes per train and second assumed for the size of the stored spike trains (the SA neurons' mean rate on the
#: paper's readings is 40-60 spikes/s, docs/results.md 1c; RA fire less)
SPIKES_PER_S = 60.0


def windows_for(duration_s: float, window_s: float = WINDOW_S) -> int:
    """Windows of ``window_s`` covering ``duration_s`` (s): ``ceil(duration_s / window_s)``, at least 1."""
    return max(1, int(np.ceil(round(float(duration_s) / float(window_s), 9))))


@dataclass(frozen=True)
class EncodeSize:
    """Estimated sizes, bytes: ``out_bytes`` (the encoded file), ``batch_bytes`` (memory of one batch);
    ``n_trials``, ``n_windows_unscaled`` as they would be used."""

    out_bytes: int
    batch_bytes: int
    n_trials: int
    n_windows_unscaled: int


def available_memory_bytes() -> int | None:
    """Memory a process can have now without swapping, bytes: Linux's ``MemAvailable`` (``/proc/meminfo``: the free
    pages plus the page cache and what else the kernel reclaims at once), else the free pages (``SC_AVPHYS_PAGES``),
    or None where unknown. (The free pages alone leave the page cache out: after the paper's 4 GB dataset was
    written they were 0.2 GB of a 24 GB machine with 21 GB available, and ``rigctl encode`` refused its batch.)"""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # (kB)
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def estimate_encode(session: Any, *, window_s: float = WINDOW_S, n_windows_unscaled: int | None = None,
                    n_windows_scaled: int | None = 20, n_windows_realtime: int = 20,
                    variants: Any = None, store_spikes: Any = MAIN_VARIANTS, batch_trials: int = 256) -> EncodeSize:
    """Sizes of encoding ``session`` (an open :class:`rigctl.storage.session.Session`) with these parameters
    (:class:`rigctl.encoding.pipeline.EncodeParams`' names), from its plan: complete trials, their planned
    durations, the sensor's channels and rate (schema 4: of the trials the validator does not refuse before reading
    their data, :func:`rigctl.storage.validate.precheck`: a trial declaring a size it does not hold sizes nothing)."""
    plan = session.plan
    done = plan[plan["status"] == 1]  # TrialStatus.COMPLETE
    if getattr(session, "_flat", False):
        from rigctl.storage.validate import precheck

        done = done[np.isin(done["trial_id"], precheck(session))]
    n = int(done.size)
    durations = np.asarray(done["duration_s"], np.float64) if n else np.zeros(0)
    # impossible values are the trial validator's to exclude (rigctl.storage.validate), not to size the work by
    durations = durations[np.isfinite(durations) & (durations > 0) & (durations <= MAX_TRIAL_S)]
    longest = float(durations.max()) if durations.size else 0.0
    n_ch = int(session.layout.n_channels)
    wu = int(n_windows_unscaled) if n_windows_unscaled is not None else windows_for(longest, window_s)
    ws = int(n_windows_scaled) if n_windows_scaled is not None else wu
    trains = 2 * n_ch
    per_trial = 0
    for v in ALL_VARIANTS if variants is None else variants:
        info = VARIANTS[v]
        if info.realtime:
            per_trial += trains * int(n_windows_realtime)
        else:
            per_trial += trains * (ws if info.speed_scaled else wu)
    features = n * per_trial * 4
    stored = [v for v in store_spikes if variants is None or v in variants]
    seconds = float(durations.sum())
    spikes = int(len(stored) * trains * seconds * SPIKES_PER_S * 4)
    batch = min(int(batch_trials), max(n, 1))
    rate = float(session.layout.sample_rate_hz)
    samples = longest * rate if 0 < rate <= MAX_RATE_HZ else 0.0
    batch_bytes = int(batch * (samples * n_ch * 8 * 3 + per_trial * 4))
    return EncodeSize(out_bytes=int(features + spikes + 256 * 1024), batch_bytes=batch_bytes, n_trials=n,
                      n_windows_unscaled=wu)
