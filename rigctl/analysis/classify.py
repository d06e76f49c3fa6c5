"""PCA + LDA texture classification with nested principal components.

The paper (Materials and Methods, "Tactile Texture Dataset - Statistical Analysis") classifies textures with linear
discriminant analysis (LDA) on the first ``n`` principal components (PCs) of the spiking feature matrix, for every
``n`` from 1 to 50. Fitting 50 PCAs and 50 LDAs per split is wasteful, because both are nested:

* PCA is fitted **once** per split with the largest PC count; PCs ``1..n`` are the first ``n`` columns of that one
  transform (the principal axes of a smaller PCA are the leading axes of a larger one).
* LDA with a pooled within-class covariance (the Bayes rule with shared covariance, which is what scikit-learn's
  :class:`~sklearn.discriminant_analysis.LinearDiscriminantAnalysis` with the default ``solver='svd'`` computes) on the
  first ``n`` PCs only needs the top-left ``n x n`` block of the within-class covariance ``S`` of the 50-PC scores.
  With the Cholesky factor ``S = L L^T``, the factor of that block is the top-left block of ``L``; whitening the scores
  and the class means once by ``L^-1`` (forward substitution, whose first ``n`` outputs depend only on the first ``n``
  inputs) turns every discriminant for every ``n`` into a cumulative sum over the whitened coordinates::

      delta_k(x; n) = sum_{j<n} xw_j mw_kj - 1/2 sum_{j<n} mw_kj^2 + log(prior_k)

  so all 50 LDA fits share one computation (:class:`NestedLDA`). ``tests/analysis/test_ana_classify.py`` checks the
  predictions against one scikit-learn ``LinearDiscriminantAnalysis`` fit per PC count.

:class:`TextureClassifier` bundles both as a scikit-learn classifier (``BaseEstimator`` + ``ClassifierMixin``: it
clones, and passes scikit-learn's estimator checks), the last step of the raw-trials-to-label pipeline that
``rigctl analyze --save-model`` writes and the GUI's real-time view loads (:mod:`rigctl.analysis.model`), with the
mean-centering calibration of the real-time experiment (Methods "Real-time Texture Classification - Protocol").
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

from rigctl.analysis.nested_lda import COMPILED_MIN, NestedLDA, fit_pca

__all__ = ["COMPILED_MIN", "fit_pca", "NestedLDA", "nested_pc_predictions", "TextureClassifier"]


def nested_pc_predictions(train_features, train_labels, test_features, n_pcs, *, random_state=0, pca=None):
    """Fit PCA once on the training split, then LDA for PCs ``1..n_pcs``; predict the test split for each.

    Parameters
    ----------
    train_features : array_like, shape (n_train, n_features)
    train_labels : array_like, shape (n_train,)
    test_features : array_like, shape (n_test, n_features)
    n_pcs : int
        Largest PC count (the paper: 50); clipped to what the training split supports.
    random_state : int
        Seed of the randomized PCA.
    pca : sklearn.decomposition.PCA, optional
        An already fitted PCA on ``train_features`` (shared between tasks with the same split).

    Returns
    -------
    predictions : ndarray, shape (n_pcs_used, n_test)
        ``predictions[n - 1]`` uses the first ``n`` PCs.
    pca : sklearn.decomposition.PCA
    """
    if pca is None:
        pca = fit_pca(train_features, n_pcs, random_state=random_state)
    n_used = min(int(n_pcs), pca.n_components_)
    z_train = pca.transform(train_features)[:, :n_used]
    z_test = pca.transform(test_features)[:, :n_used]
    lda = NestedLDA().fit(z_train, train_labels)
    return lda.predict_all(z_test, n_used), pca


class TextureClassifier(ClassifierMixin, BaseEstimator):
    """PCA + LDA texture classifier on spiking features: the last step of the raw-trials-to-label pipeline
    (:func:`rigctl.analysis.model.texture_pipeline`) and the GUI's real-time classifier (Fig. 4).

    Parameters
    ----------
    variant : str or None
        The feature variant it classifies (e.g. ``"speed_scaled"``). ``fit`` / ``predict`` take a feature matrix,
        or a mapping ``{variant: matrix}`` (e.g. :attr:`rigctl.analysis.data.FeatureSet.features`) from which this
        variant is used (None: a matrix is required).
    n_pcs : int
        PCs used by :meth:`predict` (the real-time experiment: 25); clipped to what the training data supports
        (``n_pcs_``). PCA keeps ``max(n_pcs, max_pcs)`` components so :meth:`predict_all` can ask for others.
    max_pcs : int
        Largest PC count available to :meth:`predict_all`.
    random_state : int

    Attributes
    ----------
    pca_ : sklearn.decomposition.PCA
    lda_ : NestedLDA
    center_ : ndarray (n_features,) float64
        Mean vector subtracted before projecting (the PCA mean after :meth:`fit`; replaced by :meth:`calibrate`).
    classes_ : ndarray
    n_pcs_ : int, the PC count :meth:`predict` uses (``min(n_pcs, n_components_)``).
    n_features_in_ : int

    Examples
    --------
    >>> clf = TextureClassifier("speed_scaled", n_pcs=25).fit(train_x, train_y)   # doctest: +SKIP
    >>> clf.calibrate(calibration_x)   # mean-centering calibration                 # doctest: +SKIP
    >>> clf.predict(live_x)                                                        # doctest: +SKIP
    """

    def __init__(self, variant=None, n_pcs=25, max_pcs=50, random_state=0):
        self.variant = variant
        self.n_pcs = n_pcs
        self.max_pcs = max_pcs
        self.random_state = random_state

    def _select(self, features):
        if isinstance(features, Mapping) and not hasattr(features, "shape"):  # not a sparse dok matrix
            if self.variant is None or self.variant not in features:
                raise KeyError(f"variant {self.variant!r} not among the features given ({', '.join(features)})")
            return features[self.variant]
        return features

    def fit(self, X, y):
        """Fit PCA (once, ``max(n_pcs, max_pcs)`` components) and the nested LDA.

        Parameters
        ----------
        X : array_like, shape (n_trials, n_features), or a mapping {variant: array} (see ``variant``)
        y : array_like, shape (n_trials,)

        Returns
        -------
        self

        Raises
        ------
        ValueError
            Mismatched shapes, non-finite features, or fewer than two classes.
        """
        x, y = validate_data(self, self._select(X), y, dtype=[np.float64, np.float32])
        check_classification_targets(y)
        if np.unique(y).size < 2:
            raise ValueError("TextureClassifier needs at least two classes (textures) to fit; got 1 class")
        if x.shape[0] < 3:
            raise ValueError(f"TextureClassifier needs at least 3 trials, got {x.shape[0]}")
        self.pca_ = fit_pca(x, max(int(self.n_pcs), int(self.max_pcs)), random_state=self.random_state)
        self.center_ = np.asarray(self.pca_.mean_, dtype=np.float64).copy()
        self.lda_ = NestedLDA().fit(self._project(x), y)
        self.classes_ = self.lda_.classes_
        self.n_pcs_ = max(1, min(int(self.n_pcs), self.lda_.n_features_in_))
        return self

    @property
    def n_components_(self):
        """Number of PCs available (int)."""
        return self.lda_.n_features_in_

    def _project(self, features):
        x = np.asarray(features, dtype=np.float64)
        if x.ndim == 1:
            x = x[None, :]
        return (x - self.center_) @ np.asarray(self.pca_.components_, dtype=np.float64).T

    def _check(self, features):
        check_is_fitted(self, "lda_")
        return validate_data(self, self._select(features), reset=False, dtype=[np.float64, np.float32])

    def calibrate(self, features):
        """Mean-centering calibration: centre new data on the mean of calibration trials (Methods, real-time protocol).

        Parameters
        ----------
        features : array_like, shape (n_calibration_trials, n_features)
            Feature vectors recorded in the new session (the paper: 10 trials per texture).

        Returns
        -------
        self
        """
        x = np.asarray(self._select(features), dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_features_in_:
            raise ValueError(f"calibration features must be (n, {self.n_features_in_}), got {x.shape}")
        self.center_ = x.mean(axis=0)
        return self

    def reset_calibration(self):
        """Return to the training mean (undo :meth:`calibrate`)."""
        self.center_ = np.asarray(self.pca_.mean_, dtype=np.float64).copy()
        return self

    def _n(self, n_pcs):
        n = self.n_pcs_ if n_pcs is None else int(n_pcs)
        if not 1 <= n <= self.n_components_:
            raise ValueError(f"n_pcs must be in 1..{self.n_components_}, got {n}")
        return n

    def pc_scores(self, X, n_pcs=None):
        """PC scores, shape ``(n_trials, n_pcs)`` float64."""
        x = self._check(X)
        return self._project(x)[:, : self._n(n_pcs)]

    def predict(self, X, n_pcs=None):
        """Predicted texture labels, shape ``(n_trials,)``, using ``n_pcs`` PCs (default: ``n_pcs_``).

        Raises
        ------
        ValueError
            If ``n_pcs`` exceeds the fitted number of components, or the features do not match the training's.
        """
        x = self._check(X)
        n = self._n(n_pcs)
        return self.lda_.predict_all(self._project(x), n)[n - 1]

    def predict_all(self, X, n_max=None):
        """Predictions for PCs 1..n_max: shape ``(n_max, n_trials)``."""
        return self.lda_.predict_all(self._project(self._check(X)), n_max)

    def _decisions(self, X, n_pcs):
        x = self._check(X)
        n = self._n(n_pcs)
        return self.lda_.decision_all(self._project(x), n)[n - 1]

    def decision_function(self, X, n_pcs=None):
        """LDA discriminants, shape ``(n_trials, n_classes)`` float64 (larger = more likely); for two classes
        ``(n_trials,)``, positive for ``classes_[1]`` (scikit-learn's convention)."""
        d = self._decisions(X, n_pcs)
        return d[:, 1] - d[:, 0] if d.shape[1] == 2 else d

    def predict_proba(self, X, n_pcs=None):
        """Posterior class probabilities (softmax of the discriminants), shape ``(n_trials, n_classes)``."""
        d = self._decisions(X, n_pcs)
        d = d - d.max(axis=1, keepdims=True)
        p = np.exp(d)
        return p / p.sum(axis=1, keepdims=True)

    def score(self, X, y, sample_weight=None, n_pcs=None):
        """Accuracy (fraction correct, float)."""
        return float(np.average(self.predict(X, n_pcs) == np.asarray(y), weights=sample_weight))
