"""PCA of overlapping training splits from shared Gram blocks (the fast path of Table 1).

The paper's cross-validation (Methods, "Tactile Texture Dataset - Statistical Analysis") fits one PCA per fold on
three quarters of the same 8000 drawn trials. The training covariance of fold ``f`` is the sum of the Gram matrices
of the *other* folds' test blocks, so each block's Gram matrix ``X_b' X_b`` (float32, one BLAS ``syrk``) is computed
once and shared by every fold that trains on it: the four folds cost one pass over the 8000 trials instead of four
passes over 6000. The leading principal axes of each training covariance come from a randomized subspace iteration
on the ``(n_features, n_features)`` covariance (the same range finder as scikit-learn's randomized PCA, applied to
``X' X`` instead of ``X``: each iteration costs ``n_features^2`` per column instead of ``n_trials * n_features``).

Rows are centred on the mean of all blocks before their Gram matrices are formed (the per-split mean is then a small
correction, no cancellation in float32). :class:`SplitPCA` exposes the attributes of
:class:`sklearn.decomposition.PCA` that the analyses use (``mean_``, ``components_``, ``explained_variance_``,
``n_components_``, :meth:`~SplitPCA.transform`). ``tests/analysis/test_ana_splitpca.py`` checks the Table 1
accuracies against a scikit-learn ``PCA(n)`` + ``LinearDiscriminantAnalysis`` refit for every PC count.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import eigh

__all__ = ["GramBlocks", "SplitPCA", "split_scores"]


class SplitPCA:
    """A fitted PCA (the leading ``n_components_`` axes of one training split).

    Attributes
    ----------
    mean_ : ndarray (n_features,) float64
        Mean of the training rows.
    components_ : ndarray (n_components_, n_features) float32
        Principal axes, by decreasing variance (nested: PCs ``1..n`` are the first ``n`` rows).
    explained_variance_ : ndarray (n_components_,) float64
        Variance along each axis (divisor ``n_train - 1``, as scikit-learn).
    n_components_ : int
    """

    def __init__(self, mean, components, explained_variance, centre, offset):
        self.mean_ = mean
        self.components_ = components
        self.explained_variance_ = explained_variance
        self.n_components_ = components.shape[0]
        self._centre = centre  # the GramBlocks' centre; offset = (mean_ - centre) @ components_.T
        self._offset = offset

    def transform(self, x):
        """PC scores ``(x - mean_) @ components_.T``: shape ``(n_trials, n_components_)`` float64."""
        x = np.asarray(x)
        return self.transform_centred((x - self._centre).astype(np.float32, copy=False))

    def transform_centred(self, xc):
        """PC scores of rows already centred on the :class:`GramBlocks` centre (float32 ``(n, n_features)``)."""
        return (xc @ self.components_.T).astype(np.float64) - self._offset


class GramBlocks:
    """Gram matrices of row blocks of one feature matrix, for PCAs of any union of the blocks.

    Parameters
    ----------
    x : array_like, shape (n_rows, n_features)
        Feature matrix (float32 or float64; the Gram matrices are float32, as scikit-learn keeps float32 input).
    blocks : sequence of int index arrays
        Disjoint row blocks of ``x`` (e.g. the test sets of the k folds; one block = one training set).

    Attributes
    ----------
    centre : ndarray (n_features,) float64
        Mean of the rows in the blocks.
    xc : ndarray (n_rows, n_features) float32
        ``x - centre`` (rows outside every block are centred too, for :meth:`SplitPCA.transform_centred`).

    Raises
    ------
    ValueError
        ``x`` not 2-D, an empty block.
    """

    def __init__(self, x, blocks):
        x = np.asarray(x)
        if x.ndim != 2:
            raise ValueError(f"features must be 2-D (n_trials, n_features), got shape {x.shape}")
        self.blocks = [np.asarray(b) for b in blocks]
        if any(b.size == 0 for b in self.blocks):
            raise ValueError("empty row block")
        rows = np.concatenate(self.blocks)
        self.centre = (x if rows.size == x.shape[0] else x[rows]).mean(axis=0, dtype=np.float64)
        self.xc = x.astype(np.float32, copy=True)  # (no float64 temporary of the whole matrix)
        self.xc -= self.centre.astype(np.float32)
        self._grams = []
        self._sums = []
        for b in self.blocks:
            xb = self.xc[b]
            self._grams.append(xb.T @ xb)  # numpy calls BLAS syrk for a matrix times its own transpose
            self._sums.append(xb.sum(axis=0, dtype=np.float64))
        self.n_features = x.shape[1]

    def pca(self, use, n_components, *, random_state=0, n_iter=7, n_oversamples=10):
        """PCA of the rows of the blocks ``use``.

        Parameters
        ----------
        use : sequence of int
            Block numbers forming the training split.
        n_components : int
            PCs wanted; clipped to ``min(n_train - 1, n_features)``.
        random_state : int
            Seed of the random starting subspace.
        n_iter : int
            Subspace iterations (scikit-learn's randomized PCA: 7 for 50 PCs of 2160 features).
        n_oversamples : int
            Extra columns of the subspace (scikit-learn: 10).

        Returns
        -------
        SplitPCA

        Raises
        ------
        ValueError
            Fewer than two training rows.
        """
        use = list(use)
        n = int(sum(self.blocks[i].size for i in use))
        if n < 2:
            raise ValueError(f"need at least 2 training rows, got {n}")
        k = int(min(n_components, n - 1, self.n_features))
        if k < 1:
            raise ValueError("need at least one principal component")
        cov = self._grams[use[0]].copy()
        for i in use[1:]:
            cov += self._grams[i]
        s = np.sum([self._sums[i] for i in use], axis=0)
        shift = s / n  # training mean - centre (small: the centre is the mean of all blocks)
        cov -= np.outer(s.astype(np.float32), shift.astype(np.float32))
        cov *= np.float32(1.0 / (n - 1))
        vals, vecs = _top_eigen(cov, k, n_iter, n_oversamples, random_state)
        comps = np.ascontiguousarray(vecs.T, dtype=np.float32)
        offset = shift @ comps.T.astype(np.float64)
        return SplitPCA(self.centre + shift, comps, vals, self.centre, offset)


def _top_eigen(cov, k, n_iter, n_oversamples, random_state):
    """Leading ``k`` eigenpairs of a symmetric PSD matrix: exact for small matrices, else a randomized subspace
    iteration with a Rayleigh-Ritz step (Halko, Martinsson & Tropp 2011, Alg. 4.4 on ``cov``)."""
    d = cov.shape[0]
    p = min(d, k + n_oversamples)
    if d <= 4 * p:  # small: LAPACK's exact solver is as cheap
        vals, vecs = eigh(cov.astype(np.float64), subset_by_index=[d - k, d - 1])
        return vals[::-1], vecs[:, ::-1]
    q = np.random.default_rng(random_state).standard_normal((d, p)).astype(cov.dtype)
    for _ in range(n_iter + 1):
        q, _ = np.linalg.qr(cov @ q)  # (numpy's QR is 10x faster than scipy's on tall float32 blocks)
    small = (q.T @ (cov @ q)).astype(np.float64)
    vals, u = eigh((small + small.T) / 2)
    top = np.argsort(vals)[::-1][:k]
    return vals[top], q @ u[:, top].astype(q.dtype)


def split_scores(x, splits, n_components, *, random_states, kfold=False):
    """PC scores of each split's training and test rows, with the PCA fitted on its training rows.

    Parameters
    ----------
    x : array_like, shape (n_rows, n_features)
        The rows the splits index (float32 features).
    splits : sequence of (train, test) int index arrays into ``x``
    n_components : int
        PCs wanted (clipped to ``min(n_train - 1, n_features)``).
    random_states : sequence of int
        Seed per split (starting subspace of the iteration, or of scikit-learn's randomized PCA).
    kfold : bool
        The splits are k-fold cross-validation (the test sets partition the rows and each training set is the union
        of the other test sets): the test sets' Gram blocks are shared by the folds.

    Yields
    ------
    z_train : ndarray (n_train, n_pcs) float64
    z_test : ndarray (n_test, n_pcs) float64
        ``n_pcs`` = the PCs fitted, nested.

    Notes
    -----
    The covariance path is taken when the training split has at least as many rows as features (the paper's
    6000 x 2160 folds); a wider matrix (few trials, many windows) goes through :func:`~rigctl.analysis.classify.fit_pca`
    on the rows themselves, which is cheaper there and keeps memory at the data's size.
    """
    from rigctl.analysis.classify import fit_pca

    x = np.asarray(x)
    if x.shape[1] > min(len(tr) for tr, _ in splits):
        for (tr, te), rs in zip(splits, random_states):
            pca = fit_pca(x[tr], n_components, random_state=rs)
            yield pca.transform(x[tr]), pca.transform(x[te])
        return
    if kfold:
        gb = GramBlocks(x, [te for _, te in splits])
        for f, ((tr, te), rs) in enumerate(zip(splits, random_states)):
            pca = gb.pca([g for g in range(len(splits)) if g != f], n_components, random_state=rs)
            z = pca.transform_centred(gb.xc)  # every row once (no copies of the training rows)
            yield z[tr], z[te]
        return
    for (tr, te), rs in zip(splits, random_states):
        gb = GramBlocks(x, [tr])
        pca = gb.pca([0], n_components, random_state=rs)
        z = pca.transform_centred(gb.xc)
        yield z[tr], z[te]
