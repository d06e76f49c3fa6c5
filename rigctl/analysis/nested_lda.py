"""The nested-PC LDA (:class:`NestedLDA`) and the one-PCA-per-split fit (:func:`fit_pca`), without scikit-learn at
import: Table 1's repetitions (:mod:`rigctl.analysis.tasks`) use them, and scikit-learn's import (which pulls in
``scipy.stats`` and pandas: ~2 CPU-s of a ``rigctl analyze`` start on this machine) is only paid by what needs it
(:func:`fit_pca`'s PCA, :class:`rigctl.analysis.classify.TextureClassifier`). The method: the module docstring of
:mod:`rigctl.analysis.classify`, which re-exports both names.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dpotrf

__all__ = ["COMPILED_MIN", "fit_pca", "NestedLDA"]

#: NestedLDA.predict_all's size (trials x inputs x classes) from which it loads numba for its compiled pass (a Table 1
#: split: 2000 x 50 x 16 = 1.6e6; NumPy takes ~10 ms for 1e6)
COMPILED_MIN = 1_000_000


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
    from sklearn.decomposition import PCA

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
        # the class sums as one product with the indicator matrix (np.add.at took ~60 % of a fit)
        means = (yi[None, :] == np.arange(k)[:, None]).astype(np.float64) @ z
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
            Trials per block (bounds the whitened block).

        Returns
        -------
        ndarray, shape (min(n_max, n_features_in_), n_trials), dtype of ``classes_``

        Notes
        -----
        :meth:`decision_all`'s sums in the same order, so the same predictions (ties to the first class, as
        ``argmax``), without its ``(n_max, n_trials, n_classes)`` array: in one compiled pass
        (:func:`rigctl.analysis.lda_kernel.nested_argmax`, ~7x faster on a Table 1 split) when the call is large
        (``n_trials * n_max * n_classes`` >= :data:`COMPILED_MIN`) or numba is loaded already; else by NumPy
        (:func:`~rigctl.analysis.lda_kernel.nested_argmax_numpy`), so that a small analysis does not pay numba's
        first-use cost (~1-2 CPU-s).
        """
        import sys

        from rigctl.analysis import lda_kernel

        n_max = self.n_features_in_ if n_max is None else min(int(n_max), self.n_features_in_)
        z = np.asarray(scores, dtype=np.float64)[:, : self.n_features_in_]
        idx = np.empty((n_max, z.shape[0]), dtype=np.intp)
        compiled = "numba" in sys.modules or z.shape[0] * n_max * len(self.classes_) >= COMPILED_MIN
        argmax = lda_kernel.nested_argmax if compiled else lda_kernel.nested_argmax_numpy
        for s in range(0, z.shape[0], chunk):
            zw = solve_triangular(self.chol_, z[s : s + chunk].T, lower=True).T  # (trials, inputs) whitened
            idx[:, s : s + chunk] = argmax(zw[:, :n_max], self._means_w, self._half_norm, self._log_prior)
        return self.classes_[idx]
