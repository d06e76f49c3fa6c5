"""The encoding as scikit-learn transformers, so raw trials -> texture label is one :class:`sklearn.pipeline.Pipeline`
(built by :func:`rigctl.analysis.model.texture_pipeline`; saved by ``rigctl analyze --save-model``).

Steps (paper Fig. 1B; Methods), each a ``BaseEstimator`` + ``TransformerMixin`` passing a
:class:`rigctl.encoding.batch.TrialBatch` on:

1. :class:`TaxelNormaliser` - per-taxel 0-1 normalisation, min and max over the training trials.
2. :class:`ForceScaler` - eq. (1) force coefficients (per texture: fitted with the labels;
   label-free: pooled over textures). Only in the pipelines of force-scaled variants.
3. :class:`SpikeEncoder` - Izhikevich SA (with the force gains) and RA spike trains (eqs. 3-5).
4. :class:`FeatureExtractor` - speed scaling (eq. 2) and SR/SC features of one variant: a 2-D feature matrix, as
   :func:`rigctl.encoding.pipeline.encode_session` writes it (:func:`rigctl.encoding.pipeline.trains_to_features`).

The first step takes raw trials (a list of :class:`rigctl.core.trial.TrialData`); ragged trial lists are not the
2-D arrays scikit-learn's generic estimator checks feed, so these steps are checked with the checks that take no data
(``tests/encoding/test_enc_estimators.py`` says which and why) plus clone and pipeline round trips.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted

from rigctl.encoding.batch import TrialBatch, as_trial_batch
from rigctl.encoding.batch_encode import _realtime_taxels, _sa_ra, trains_to_features
from rigctl.encoding.force import ForceCoefficients
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.sizing import windows_for
from rigctl.encoding.speed import speed_coefficient
from rigctl.storage.encoded import ALL_VARIANTS, VARIANTS

__all__ = ["TaxelNormaliser", "ForceScaler", "SpikeEncoder", "FeatureExtractor", "TrialBatch", "as_trial_batch"]



class ForceScaler(TransformerMixin, BaseEstimator, ForceCoefficients):
    """Eq. (1) as a scikit-learn transformer (:class:`rigctl.encoding.force.ForceCoefficients`, its parameters and
    attributes): ``fit`` finds the coefficients, ``transform`` gives each trial its coefficients (the SA input gains).

    ``X`` is a :class:`rigctl.encoding.batch.TrialBatch` (or raw trials: a list of
    :class:`rigctl.core.trial.TrialData`), whose records carry each trial's speed and force (the condition) and the
    normalisation (a :class:`TaxelNormaliser` before this step); ``y`` the texture labels.

    Notes
    -----
    Per texture, :meth:`transform` must know each trial's texture: it uses the labels the trials carry
    (``TrialBatch.texture``, from the records' ``attrs["texture"]``), as the paper did, which is a leak: the
    coefficients depend on the label the classifier is asked for. Trials without a label, or of a condition not
    seen in ``fit``, get C = 1. The label-free coefficients need no label.
    """

    def fit(self, X, y=None) -> "ForceScaler":
        """Fit the coefficients on trials ``X`` (records with speed and force) labelled ``y`` (textures).

        Parameters
        ----------
        X : TrialBatch or list of TrialData (:func:`rigctl.encoding.batch.as_trial_batch`).
        y : (n_trials,) texture labels; None: the labels the trials carry (needed unless ``label_free``).

        Raises
        ------
        ValueError
            if a (texture, speed) has no trial at the reference force, or no texture labels (per texture).
        """
        b = as_trial_batch(X)
        texture = b.texture if y is None else np.asarray(y).astype(str)
        if texture is None:
            if not self.label_free:
                raise ValueError("per-texture force coefficients need the texture labels: fit(X, y)")
            texture = np.full(b.n_trials, "*")
        return self.fit_labels(b.readings, texture, b.speed_mm_s, b.force_g, offset=b.offset, scale=b.scale)

    def transform(self, X):
        """``X`` (a TrialBatch or raw trials) with ``gains`` = each trial's coefficients, ``(n_trials, n_taxels)``
        float64 (C of eq. 1: the SA input scale of :class:`rigctl.encoding.estimators.SpikeEncoder`)."""
        check_is_fitted(self, "coeffs_")
        b = as_trial_batch(X)
        return dataclasses.replace(b, gains=self.coefficients_for(b.texture, b.speed_mm_s, b.force_g))

def _params(params):
    if isinstance(params, EncodeParams):
        return dataclasses.replace(params)
    return EncodeParams.from_dict(params)


class TaxelNormaliser(TransformerMixin, BaseEstimator):
    """Per-taxel normalisation to 0-1 (Methods: "minimum and maximum readings for each taxel from the whole
    dataset"): ``fit`` takes the training trials' per-taxel min and max; ``transform`` attaches the affine map the
    encoder applies on the fly (raw counts are never copied to floats).

    Attributes
    ----------
    taxel_min_, taxel_max_ : (n_channels,) float64, in the model input's units (ADC counts).
    n_channels_ : int.
    """

    def fit(self, X, y=None) -> "TaxelNormaliser":
        """X: raw trials (list of TrialData) or a TrialBatch."""
        b = as_trial_batch(X)
        rng = TaxelRange().update(b.readings.data)
        self.taxel_min_, self.taxel_max_ = rng.minimum, rng.maximum
        self.n_channels_ = b.n_channels
        return self

    def transform(self, X) -> TrialBatch:
        """The trials as a TrialBatch with ``offset``/``scale``; ValueError on another channel count."""
        check_is_fitted(self, "taxel_min_")
        b = as_trial_batch(X)
        if b.n_channels != self.n_channels_:
            raise ValueError(f"trials of {b.n_channels} channels; the normaliser was fitted on {self.n_channels_} "
                             "(another sensor)")
        offset, scale = TaxelRange(self.taxel_min_, self.taxel_max_).offset_scale()
        return dataclasses.replace(b, offset=offset, scale=scale)


class SpikeEncoder(TransformerMixin, BaseEstimator):
    """SA and RA spike trains (eqs. 3-5; SA input scaled by the batch's force gains, C = 1 without them).

    Parameters
    ----------
    params : dict or :class:`rigctl.encoding.pipeline.EncodeParams`, optional
        The model constants (``k_sa``, ``k_ra``, ``cutoff_hz``, ``rectify_ra``, ``izhikevich``); default the
        paper's. An encoded file's ``parameters`` encode new trials as the file was.
    """

    def __init__(self, params=None):
        self.params = params

    def fit(self, X, y=None) -> "SpikeEncoder":
        self.n_channels_ = as_trial_batch(X).n_channels
        return self

    def transform(self, X) -> TrialBatch:
        """The batch with ``sa`` and ``ra`` (n_trials, n_channels) spike trains, times in s."""
        check_is_fitted(self, "n_channels_")
        b = as_trial_batch(X)
        gains = np.ones((b.n_trials, b.n_channels)) if b.gains is None else b.gains
        sas, ra = _sa_ra(b.readings, b.offset, b.scale, [gains], _params(self.params))
        return dataclasses.replace(b, sa=sas[0], ra=ra)


class FeatureExtractor(TransformerMixin, BaseEstimator):
    """One variant's features of encoded trials: speed scaling (eq. 2) for speed-scaled variants, then spike rates
    and counts in windows (100 ms by default): ``(n_trials, n_features)`` float32.

    Parameters
    ----------
    variant : a name of :data:`rigctl.storage.encoded.VARIANTS` (``"speed_scaled"``: SA/RA x taxels x 20 windows
        x SR/SC); the force-scaled ones expect the SA trains to carry the force gains (a ForceScaler step before).
        ``realtime_speed_scaled`` scales each window by the trial's speed setpoint (``encode_session`` uses the
        measured speed trace when a trial has one).
    params : dict or EncodeParams, optional: windows (``window_s``, ``n_windows_*``) and constants. Window counts
        left None are taken from the longest training trial in :meth:`fit` (``params_``), so new trials always give
        the training's columns.

    Attributes
    ----------
    params_ : dict, the parameters used (window counts fixed).
    """

    def __init__(self, variant: str = "speed_scaled", params=None):
        self.variant = variant
        self.params = params

    def _features(self, b: TrialBatch, p) -> np.ndarray:
        if b.sa is None or b.ra is None:
            raise ValueError("FeatureExtractor needs spike trains: put a SpikeEncoder step before it")
        sa_by = {"none": b.sa, "force": b.sa, "lf": b.sa}
        feats, _ = trains_to_features(sa_by, b.ra, b.readings.lengths, b.speed_mm_s, variants=[self.variant],
                                      params=p)
        return feats[self.variant]

    def fit(self, X, y=None) -> "FeatureExtractor":
        """Fix the window counts from the training trials (the longest one, as ``encode_session`` does).

        Raises ValueError for an unknown variant."""
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose from {', '.join(ALL_VARIANTS)}")
        b = as_trial_batch(X)
        p = _params(self.params)
        longest = float(b.readings.lengths.max(initial=1)) / p.fs_hz
        if p.n_windows_unscaled is None:
            p.n_windows_unscaled = windows_for(longest, p.window_s)
        if p.n_windows_scaled is None:
            ok = np.isfinite(b.speed_mm_s) & (b.speed_mm_s > 0)
            dur = b.readings.lengths[ok] / p.fs_hz
            scaled = dur * speed_coefficient(b.speed_mm_s[ok], p.reference_speed_mm_s) if ok.any() else dur
            p.n_windows_scaled = windows_for(float(np.max(scaled, initial=longest)), p.window_s)
        if p.realtime_taxels is None:
            p.realtime_taxels = _realtime_taxels(p, b.n_channels)
        self.params_ = dataclasses.asdict(p)
        return self

    def transform(self, X) -> np.ndarray:
        check_is_fitted(self, "params_")
        feats = self._features(as_trial_batch(X), _params(self.params_))
        return np.asarray(feats, dtype=np.float32)
