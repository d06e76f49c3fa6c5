"""The trials a scikit-learn pipeline of the encoding passes from step to step (:class:`TrialBatch`).

A pipeline starts from raw trials, a list of :class:`rigctl.core.trial.TrialData` (ADC counts at the sensor's rate;
``attrs`` give each trial's speed and force setpoints, and its texture when known, as session files store them);
:func:`as_trial_batch` brings them to the model's 1 kHz step (:mod:`rigctl.encoding.rate`) once, and each step of
:mod:`rigctl.encoding.estimators` returns the batch with its part filled in (normalisation, force gains, spike
trains). A list of trials indexes like any sequence, so scikit-learn's cross-validation splits it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from rigctl.encoding.izhikevich import Ragged, _at_model_rate, as_ragged
from rigctl.encoding.rate import MODEL_RATE_HZ
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["TrialBatch", "as_trial_batch"]


@dataclasses.dataclass(frozen=True)
class TrialBatch:
    """Trials on their way through the encoding steps.

    Attributes
    ----------
    readings : :class:`~rigctl.encoding.izhikevich.Ragged` (n_trials trials of (n_i, n_channels)): the model input
        at ``rate_hz`` (ADC counts; ``(x - offset) * scale`` is the 0-1 normalised reading).
    speed_mm_s, force_g : (n_trials,) float64 setpoints (mm/s, g); NaN when unknown.
    texture : (n_trials,) str labels the trials carry, or None (new trials: the label is what is predicted).
    rate_hz : the model's rate, Hz (1 kHz: one Izhikevich step per sample).
    offset, scale : (n_channels,) normalisation (after :class:`~rigctl.encoding.estimators.TaxelNormaliser`).
    gains : (n_trials, n_channels) SA input gains, the force coefficients of eq. 1 (after
        :class:`~rigctl.encoding.estimators.ForceScaler`), or None (C = 1).
    sa, ra : :class:`~rigctl.encoding.spikes.SpikeTrains` (n_trials, n_channels) (after
        :class:`~rigctl.encoding.estimators.SpikeEncoder`), or None.
    """

    readings: Ragged
    speed_mm_s: np.ndarray
    force_g: np.ndarray
    texture: np.ndarray | None = None
    rate_hz: float = MODEL_RATE_HZ
    offset: Any = 0.0
    scale: Any = 1.0
    gains: np.ndarray | None = None
    sa: SpikeTrains | None = None
    ra: SpikeTrains | None = None

    @property
    def n_trials(self) -> int:
        return self.readings.n_trials

    @property
    def n_channels(self) -> int:
        return self.readings.n_channels

    def __len__(self) -> int:
        return self.n_trials


def _attr(trial, name: str) -> float:
    value = trial.attrs.get(name)
    try:
        return math.nan if value is None else float(value)
    except (TypeError, ValueError):
        return math.nan


def as_trial_batch(X, model_rate_hz: float = MODEL_RATE_HZ) -> TrialBatch:
    """Raw trials -> a :class:`TrialBatch` at the model's rate (a batch is returned as it is).

    Parameters
    ----------
    X : TrialBatch, or a sequence of :class:`rigctl.core.trial.TrialData` of one sensor and rate: ``taxels``
        ``(n_i, n_channels)`` uint16 ADC counts; ``attrs["speed_mm_s"]`` (else the mean of the speed trace, else
        NaN), ``attrs["force_g"]`` (else NaN), ``attrs["texture"]`` (the label, if every trial has one).

    Raises
    ------
    ValueError
        No trials, trials of different channel counts or rates, or a rate the model cannot be resampled from.
    TypeError
        Anything else than trials (e.g. a bare feature matrix).
    """
    if isinstance(X, TrialBatch):
        return X
    trials = list(X) if not isinstance(X, np.ndarray) else None
    if not trials or not all(hasattr(t, "taxels") and hasattr(t, "layout") for t in trials):
        raise TypeError("the encoding steps take raw trials (a list of rigctl.core.trial.TrialData) or a TrialBatch, "
                        f"got {type(X).__name__}")
    rates = {float(t.layout.sample_rate_hz) for t in trials}
    channels = {int(t.taxels.shape[1]) for t in trials}
    if len(rates) > 1 or len(channels) > 1:
        raise ValueError(f"trials of one sensor and rate expected, got rates {sorted(rates)} Hz and channel counts "
                         f"{sorted(channels)}")
    rg, rate = _at_model_rate(as_ragged([np.asarray(t.taxels) for t in trials]), rates.pop(), model_rate_hz)
    speed = np.array([_attr(t, "speed_mm_s") for t in trials])
    for i, t in enumerate(trials):
        if math.isnan(speed[i]) and t.speed_mm_s.size:
            speed[i] = float(np.mean(t.speed_mm_s))
    labels = [t.attrs.get("texture") for t in trials]
    texture = np.array([str(x) for x in labels]) if all(x is not None for x in labels) else None
    return TrialBatch(rg, speed, np.array([_attr(t, "force_g") for t in trials]), texture, rate)
