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

:class:`TextureClassifier` bundles both for one data set (fit / predict / save / load), and is what the GUI's
real-time view uses (with the mean-centering calibration of the real-time experiment, Methods "Real-time Texture
Classification - Protocol").
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dpotrf
from sklearn.decomposition import PCA

__all__ = ["fit_pca", "NestedLDA", "nested_pc_predictions", "TextureClassifier"]

#: file-format tag of :meth:`TextureClassifier.save`
_MODEL_FORMAT = "rigctl.TextureClassifier/1"


def fit_pca(features, n_components, *, random_state=0, svd_solver="auto"):
    """Fit one PCA for a training split (its components are nested: PCs ``1..n`` are the first ``n`` columns).

    Parameters
    ----------
    features : array_like, shape (n_trials, n_features), float32 or float64
        Training feature matrix (spike rates / spike counts per 100 ms window).
    n_components : int
        Largest number of PCs needed; clipped to ``min(n_trials - 1, n_features)``.
    random_state : int
        Seed of the randomized solver.
    svd_solver : str
        ``"auto"`` picks ``"randomized"`` (fits the leading 50 components of paper-sized matrices in well under a
        second) when fewer than 80 % of the components are wanted of a matrix larger than 500 in both dimensions,
        else ``"full"`` (exact LAPACK SVD, faster on small matrices).

    Returns
    -------
    sklearn.decomposition.PCA
        The fitted PCA (float32 input stays float32 inside it).

    Raises
    ------
    ValueError
        If ``features`` is not 2-D or has fewer than 2 rows.
    """
    x = np.asarray(features)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"features must be (n_trials >= 2, n_features), got shape {x.shape}")
    n = int(min(n_components, x.shape[0] - 1, x.shape[1]))
    if n < 1:
        raise ValueError("need at least one principal component")
    if svd_solver == "auto":
        svd_solver = "randomized" if (n < 0.8 * min(x.shape) and min(x.shape) > 500) else "full"
    return PCA(n_components=n, svd_solver=svd_solver, random_state=random_state).fit(x)


class NestedLDA:
    """LDA (pooled within-class covariance) fitted once, predicting with the first ``n`` inputs for every ``n``.

    Parameters
    ----------
    priors : array_like of shape (n_classes,), optional
        Class priors; the class frequencies of the training labels by default (as scikit-learn's LDA).

    Attributes
    ----------
    classes_ : ndarray (n_classes,)
    priors_ : ndarray (n_classes,) float64
    n_features_in_ : int
        Number of leading inputs usable (predictions for 1..n_features_in_ of them): the inputs given, limited to
        ``n_trials - n_classes`` (the rank of the within-class scatter) and to the leading block whose covariance is
        positive definite.
    means_ : ndarray (n_classes, n_features_in_) float64
    chol_ : ndarray (n_features_in_, n_features_in_) float64
        Lower Cholesky factor of the pooled within-class covariance (divided by ``n_trials``, as scikit-learn's
        ``solver='svd'`` does since 1.5; the divisor only matters through the log-prior term).

    Notes
    -----
    The decision function for ``n`` inputs is the Bayes rule with a shared covariance,
    ``x' S_n^-1 mu_k - 1/2 mu_k' S_n^-1 mu_k + log pi_k`` with ``S_n`` the top-left ``n x n`` block (see the module
    docstring). It equals scikit-learn's ``LinearDiscriminantAnalysis()`` fitted on the first ``n`` columns, up to a
    class-independent offset.
    """

    def __init__(self, priors=None):
        self.priors = priors

    def fit(self, scores, labels):
        """Fit on training scores.

        Parameters
        ----------
        scores : array_like, shape (n_trials, n_pcs)
            PC scores (or any inputs whose nested prefixes are to be used).
        labels : array_like, shape (n_trials,)
            Class labels (any hashable dtype numpy can sort).

        Returns
        -------
        self

        Raises
        ------
        ValueError
            Fewer than two classes, or fewer trials than classes + 1.
        numpy.linalg.LinAlgError
            The first input has zero within-class variance.
        """
        z = np.asarray(scores, dtype=np.float64)
        y = np.asarray(labels)
        if z.ndim != 2 or y.shape != (z.shape[0],):
            raise ValueError(f"scores must be (n, d) and labels (n,), got {z.shape} and {y.shape}")
        self.classes_, yi = np.unique(y, return_inverse=True)
        k = len(self.classes_)
        n = z.shape[0]
        if k < 2 or n <= k:
            raise ValueError(f"need >= 2 classes and more trials than classes (got {k} classes, {n} trials)")
        counts = np.bincount(yi, minlength=k).astype(np.float64)
        self.priors_ = counts / n if self.priors is None else np.asarray(self.priors, dtype=np.float64)
        means = np.zeros((k, z.shape[1]))
        np.add.at(means, yi, z)
        means /= counts[:, None]
        self.means_ = means
        centred = z - means[yi]
        # the within-class scatter has rank <= n - k: only that many leading inputs can be used
        d = min(z.shape[1], n - k)
        cov = centred[:, :d].T @ centred[:, :d] / n
        chol, info = dpotrf(cov, lower=1, clean=1)
        if info > 0:  # leading minor `info` not positive definite: keep the (info - 1) inputs before it
            d = info - 1
            if d < 1:
                raise np.linalg.LinAlgError("the within-class covariance of the first input is zero")
            chol = chol[:d, :d]
        elif info < 0:  # pragma: no cover - LAPACK argument error
            raise np.linalg.LinAlgError(f"dpotrf failed (info={info})")
        self.chol_ = np.tril(chol)
        self.means_ = means[:, :d]
        # whitened class means: rows are L^-1 mu_k
        self._means_w = solve_triangular(self.chol_, self.means_.T, lower=True).T
        self._half_norm = 0.5 * np.cumsum(self._means_w**2, axis=1)  # (k, d)
        self._log_prior = np.log(self.priors_)
        self.n_features_in_ = d
        return self

    def decision_all(self, scores, n_max=None):
        """Discriminant values for every nested input count.

        Parameters
        ----------
        scores : array_like, shape (n_trials, >= n_max)
        n_max : int, optional
            Largest input count (default: all fitted inputs).

        Returns
        -------
        ndarray, shape (n_max, n_trials, n_classes) float64
            ``out[n - 1]`` is the decision function using the first ``n`` inputs.
        """
        n_max = self.n_features_in_ if n_max is None else min(int(n_max), self.n_features_in_)
        z = np.asarray(scores, dtype=np.float64)[:, : self.n_features_in_]
        zw = solve_triangular(self.chol_, z.T, lower=True).T  # (n, d) whitened
        mw = self._means_w[:, :n_max]
        # cumulative sum over the whitened coordinates: (n_max, n_trials, k)
        prod = zw[:, None, :n_max] * mw[None, :, :]
        out = np.cumsum(prod.transpose(2, 0, 1), axis=0)
        out -= self._half_norm[:, :n_max].T[:, None, :]
        out += self._log_prior[None, None, :]
        return out

    def predict_all(self, scores, n_max=None, *, chunk=4096):
        """Predicted class labels for every nested input count.

        Parameters
        ----------
        scores : array_like, shape (n_trials, >= n_max)
        n_max : int, optional
        chunk : int
            Trials per block (bounds the temporary ``(n_max, chunk, n_classes)`` array).

        Returns
        -------
        ndarray, shape (min(n_max, n_features_in_), n_trials), dtype of ``classes_``
        """
        n_max = self.n_features_in_ if n_max is None else min(int(n_max), self.n_features_in_)
        z = np.asarray(scores)
        idx = np.empty((n_max, z.shape[0]), dtype=np.intp)
        for s in range(0, z.shape[0], chunk):
            idx[:, s : s + chunk] = self.decision_all(z[s : s + chunk], n_max).argmax(axis=2)
        return self.classes_[idx]


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


class TextureClassifier:
    """PCA + LDA texture classifier on spiking features (a fitted pipeline for the GUI's real-time view).

    Parameters
    ----------
    n_pcs : int
        Number of PCs used by :meth:`predict` by default (the real-time experiment: 25). PCA keeps
        ``max(n_pcs, max_pcs)`` components so other counts can be asked for without refitting.
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

    Examples
    --------
    >>> clf = TextureClassifier(n_pcs=25).fit(train_x, train_y)       # doctest: +SKIP
    >>> clf.calibrate(calibration_x)   # mean-centering calibration    # doctest: +SKIP
    >>> clf.predict(live_x)                                           # doctest: +SKIP
    """

    def __init__(self, n_pcs=25, max_pcs=50, random_state=0):
        self.n_pcs = n_pcs
        self.max_pcs = max_pcs
        self.random_state = random_state

    def fit(self, features, labels, n_pcs=None):
        """Fit PCA (once, ``max(n_pcs, max_pcs)`` components) and the nested LDA.

        Parameters
        ----------
        features : array_like, shape (n_trials, n_features)
        labels : array_like, shape (n_trials,)
        n_pcs : int, optional
            Overrides the default PC count used by :meth:`predict`.

        Returns
        -------
        self

        Raises
        ------
        ValueError
            Mismatched shapes or fewer than two classes.
        """
        x = np.asarray(features)
        y = np.asarray(labels)
        if x.ndim != 2 or y.shape != (x.shape[0],):
            raise ValueError(f"features must be (n, d) and labels (n,), got {x.shape} and {y.shape}")
        if n_pcs is not None:
            self.n_pcs = int(n_pcs)
        self.pca_ = fit_pca(x, max(self.n_pcs, self.max_pcs), random_state=self.random_state)
        self.center_ = np.asarray(self.pca_.mean_, dtype=np.float64).copy()
        self.lda_ = NestedLDA().fit(self._project(x), y)
        self.classes_ = self.lda_.classes_
        self.n_features_in_ = x.shape[1]
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
        x = np.asarray(features, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_features_in_:
            raise ValueError(f"calibration features must be (n, {self.n_features_in_}), got {x.shape}")
        self.center_ = x.mean(axis=0)
        return self

    def reset_calibration(self):
        """Return to the training mean (undo :meth:`calibrate`)."""
        self.center_ = np.asarray(self.pca_.mean_, dtype=np.float64).copy()
        return self

    def transform(self, features, n_pcs=None):
        """PC scores, shape ``(n_trials, n_pcs)`` float64 (a 1-D vector is treated as one trial)."""
        n = self.n_pcs if n_pcs is None else int(n_pcs)
        return self._project(features)[:, :n]

    def predict(self, features, n_pcs=None):
        """Predicted texture labels, shape ``(n_trials,)``, using ``n_pcs`` PCs (default: ``self.n_pcs``).

        Raises
        ------
        ValueError
            If ``n_pcs`` exceeds the fitted number of components.
        """
        n = self.n_pcs if n_pcs is None else int(n_pcs)
        if not 1 <= n <= self.n_components_:
            raise ValueError(f"n_pcs must be in 1..{self.n_components_}, got {n}")
        return self.lda_.predict_all(self._project(features), n)[n - 1]

    def predict_all(self, features, n_max=None):
        """Predictions for PCs 1..n_max: shape ``(n_max, n_trials)``."""
        return self.lda_.predict_all(self._project(features), n_max)

    def decision_function(self, features, n_pcs=None):
        """LDA discriminants, shape ``(n_trials, n_classes)`` float64 (larger = more likely)."""
        n = self.n_pcs if n_pcs is None else int(n_pcs)
        return self.lda_.decision_all(self._project(features), n)[n - 1]

    def predict_proba(self, features, n_pcs=None):
        """Posterior class probabilities (softmax of the discriminants), shape ``(n_trials, n_classes)``."""
        d = self.decision_function(features, n_pcs)
        d = d - d.max(axis=1, keepdims=True)
        p = np.exp(d)
        return p / p.sum(axis=1, keepdims=True)

    def score(self, features, labels, n_pcs=None):
        """Accuracy (fraction correct, float)."""
        return float(np.mean(self.predict(features, n_pcs) == np.asarray(labels)))

    def save(self, path):
        """Pickle the fitted classifier to ``path`` (a tagged dict; only load files you trust)."""
        with open(Path(path), "wb") as fh:
            pickle.dump({"format": _MODEL_FORMAT, "model": self}, fh, protocol=pickle.HIGHEST_PROTOCOL)

    @classmethod
    def load(cls, path):
        """Load a classifier written by :meth:`save`.

        Raises
        ------
        ValueError
            If the file is not a saved ``TextureClassifier``.
        """
        with open(Path(path), "rb") as fh:
            obj = pickle.load(fh)
        if not isinstance(obj, dict) or obj.get("format") != _MODEL_FORMAT or not isinstance(obj.get("model"), cls):
            raise ValueError(f"{path} is not a saved rigctl TextureClassifier")
        return obj["model"]
