"""The trained readout as one affine map: a fitted :class:`~rigctl.analysis.classify.TextureClassifier` (PCA, then
the nested-PC LDA on its first ``n_pcs`` scores) gives, for a feature vector ``x`` (spike rates and counts per window,
:class:`~rigctl.encoding.estimators.FeatureExtractor`), the class scores ``W @ x + b``; the predicted texture is the
class of the largest score. This is what a neuromorphic chip can run after counting spikes in windows (``rigctl
export nir`` writes it as a NIR graph: :mod:`rigctl.storage.nir_export`).

Derivation (:meth:`rigctl.analysis.nested_lda.NestedLDA.decision_all`): with ``P`` the first ``n`` principal axes,
``c`` the centre (training mean, or a calibration's), ``L`` the first ``n`` rows and columns of the within-class
covariance's Cholesky factor (lower: the first ``n`` whitened scores depend on the first ``n`` scores only), ``M``
the whitened class means' first ``n`` columns, ``h`` half their squared norms and ``log p`` the log priors,
``scores = M L^-1 P (x - c) - h + log p``: ``W = M L^-1 P`` and ``b = -W c - h + log p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

__all__ = ["AffineReadout", "affine_readout"]


@dataclass(frozen=True)
class AffineReadout:
    """Class scores as ``features @ weight.T + bias``.

    Attributes
    ----------
    weight : (n_classes, n_features) float64
    bias : (n_classes,) float64
    classes : (n_classes,) the texture labels, in the scores' order
    n_pcs : int, the principal components the classifier's decision used
    """

    weight: np.ndarray
    bias: np.ndarray
    classes: np.ndarray
    n_pcs: int

    def scores(self, features: np.ndarray) -> np.ndarray:
        """(n_trials, n_classes) float64 class scores of (n_trials, n_features) features."""
        return np.asarray(features, dtype=np.float64) @ self.weight.T + self.bias

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(n_trials,) the label of each trial's largest score (ties to the first class, as the classifier's)."""
        return self.classes[np.argmax(self.scores(features), axis=1)]


def affine_readout(classifier: object, n_pcs: int | None = None) -> AffineReadout:
    """The affine map of a fitted :class:`~rigctl.analysis.classify.TextureClassifier` (or a pipeline ending in
    one, e.g. a model file's) with ``n_pcs`` components (default: the classifier's ``n_pcs_``).

    Raises
    ------
    TypeError
        Not a fitted TextureClassifier (nor a pipeline ending in one).
    ValueError
        ``n_pcs`` outside 1 .. the fitted component count.
    """
    from sklearn.pipeline import Pipeline

    from rigctl.analysis.classify import TextureClassifier

    clf = classifier[-1] if isinstance(classifier, Pipeline) else classifier
    if not isinstance(clf, TextureClassifier) or not hasattr(clf, "lda_"):
        raise TypeError(f"not a fitted texture classifier: {type(clf).__name__}")
    n = clf._n(n_pcs)
    lda = clf.lda_
    axes = np.asarray(clf.pca_.components_, dtype=np.float64)[:n]  # (n, n_features)
    whitened_axes = solve_triangular(lda.chol_[:n, :n], axes, lower=True)  # L^-1 P
    weight = lda._means_w[:, :n] @ whitened_axes  # (n_classes, n_features)
    bias = -weight @ np.asarray(clf.center_, dtype=np.float64) - lda._half_norm[:, n - 1] + lda._log_prior
    return AffineReadout(weight=weight, bias=bias, classes=np.asarray(clf.classes_), n_pcs=n)
