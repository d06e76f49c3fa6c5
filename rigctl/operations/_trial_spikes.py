"""One recorded trial encoded on the fly, as a trial browser shows it (the GUI's analysis tab): its raw readings and
its SA and RA spike trains, normalised with the per-taxel range over the whole session (the paper normalises over the
whole data set), at the session's rate. The encoding is :mod:`rigctl.encoding.izhikevich`'s, one pass of the fused
kernel for both populations."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from rigctl.core.normalisation import TaxelRange

__all__ = ["TrialSpikes", "session_taxel_range", "trial_spikes"]


@dataclass(frozen=True)
class TrialSpikes:
    """A trial's readings and spikes.

    Attributes
    ----------
    trial_id : the trial's id in its session.
    readings : ``(n_samples, n_taxels)`` uint16 ADC counts.
    sa, ra : one array of spike times (s since the trial's start) per taxel, SA (tonic, on the reading) and RA (on
        its low-passed derivative).
    duration_s : the trial's length, s (``n_samples`` / the session's sample rate).
    """

    trial_id: int
    readings: np.ndarray
    sa: list[np.ndarray]
    ra: list[np.ndarray]
    duration_s: float


def session_taxel_range(session_path: str | os.PathLike[str]) -> TaxelRange:
    """The per-taxel min/max of every recorded trial of a session file (reads each trial once). SessionError /
    OSError when the file cannot be read."""
    from rigctl.storage.session import open_session

    rng = TaxelRange()
    with open_session(session_path) as s:
        for t in s.iter_trials():
            rng.update(t.taxels)
    return rng


def trial_spikes(session_path: str | os.PathLike[str], trial_id: int, *,
                 taxel_range: TaxelRange | None = None) -> TrialSpikes:
    """Read trial ``trial_id`` of a session file and encode it into SA and RA spikes, normalised with
    ``taxel_range`` (default: :func:`session_taxel_range`, which reads the whole session: pass it again when browsing
    several trials). KeyError for a trial the session does not hold; SessionError naming the reason for a trial the
    trial validator excludes (:meth:`rigctl.storage.session.Session.usable_trial`); SessionError / OSError from the
    file."""
    from rigctl.encoding.izhikevich import encode_trials
    from rigctl.storage.session import open_session

    rng = taxel_range if taxel_range is not None else session_taxel_range(session_path)
    with open_session(session_path) as s:
        trial = s.usable_trial(int(trial_id))  # the one validator: an excluded trial is not shown
    x = trial.taxels
    fs_hz = float(trial.layout.sample_rate_hz)  # one model step per sample, at the session's rate
    trains = encode_trials(x[None], normalise=rng, fs=fs_hz)  # SA taxels first, then RA
    n = x.shape[1]
    return TrialSpikes(int(trial_id), x, [trains.train(0, k) for k in range(n)],
                       [trains.train(0, n + k) for k in range(n)], len(x) / fs_hz)
