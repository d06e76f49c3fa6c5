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
from scipy.linalg import eigh, solve_triangular
from scipy.linalg.lapack import dpotrf

__all__ = ["GramBlocks", "SplitPCA", "split_scores", "zero_padding"]


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

    The unscaled variants' trials are zero-padded to the longest trial's windows (a 2 s trial fills 20 of 60), so
    their rows are zero in whole runs of columns: the columns are ordered by how many rows use them, the rows grouped
    by the last column they use in that order (:func:`zero_padding`), and each group's Gram matrix is formed on its
    own leading columns only, centred on the group's mean (the zeros stay zeros), with the groups' means put back as a
    rank-``n_groups`` float64 term. The same sums as the dense ``X_b' X_b``; at the paper's size (speeds 40-120 mm/s:
    2-6 s trials) ~0.4 of its multiply-adds in the folds, ~0.6 in the extrapolation's training set. The PC scores
    (:meth:`scores`) use the groups too. A matrix without padding is one group of every column (the dense path).

    Parameters
    ----------
    x : array_like, shape (n_rows, n_features)
        Feature matrix (float32 or float64; the Gram matrices are float32, as scikit-learn keeps float32 input).
    blocks : sequence of int index arrays
        Disjoint row blocks of ``x`` (e.g. the test sets of the k folds; one block = one training set).
    padding : (order, extent), optional
        :func:`zero_padding` of the rows covered (or of a matrix they are a subset of: its order and these rows'
        extents).
    rows : int index array, optional
        The rows of ``x`` this object covers (default: all): ``blocks`` and :meth:`scores` index ``x[rows]``, which
        is never copied whole.

    Attributes
    ----------
    centre : ndarray (n_features,) float64
        Mean of the rows in the blocks.
    xc : ndarray (n_rows, n_features) float32
        ``x - centre`` (rows outside every block are centred too, for :meth:`SplitPCA.transform_centred`); made on
        first use (the fast path does not need it: :meth:`scores`).

    Raises
    ------
    ValueError
        ``x`` not 2-D, an empty block.
    """

    def __init__(self, x, blocks, *, padding=None, rows=None):
        x = np.asarray(x)
        if x.ndim != 2:
            raise ValueError(f"features must be 2-D (n_trials, n_features), got shape {x.shape}")
        self.blocks = [np.asarray(b) for b in blocks]
        if any(b.size == 0 for b in self.blocks):
            raise ValueError("empty row block")
        self._x = x
        self._rows = None if rows is None else np.asarray(rows)
        n_rows = x.shape[0] if rows is None else self._rows.size
        self._xc = None
        self.n_features = d = x.shape[1]
        self._order, extent = zero_padding(self._covered()) if padding is None else padding
        groups = _groups(np.asarray(extent))
        self._inverse = np.argsort(self._order)
        # per group: its rows, its leading columns k, its mean over them (float64) and its rows centred on it (f32)
        self._groups = []
        group_of = np.empty(n_rows, np.intp)
        slot_of = np.empty(n_rows, np.intp)
        for g, (rows_g, k) in enumerate(groups):
            src = rows_g if rows is None else self._rows[rows_g]  # (gathered from x itself: no copy of x[rows])
            xg = x[np.ix_(src, self._order[:k])].astype(np.float32, copy=False)
            m = xg.mean(axis=0, dtype=np.float64)
            xg -= m.astype(np.float32)
            self._groups.append((rows_g, k, m, xg))
            group_of[rows_g] = g
            slot_of[rows_g] = np.arange(rows_g.size)
        self._grams = []
        stats = []  # per block: (n rows, their mean, padded, permuted) per group in the block
        for b in self.blocks:
            gram = None
            means = []
            gb = group_of[b]
            for g in reversed(range(len(self._groups))):  # the widest first: it writes the whole matrix
                _, k, m, xg = self._groups[g]
                sel = slot_of[b[gb == g]]
                if sel.size == 0:
                    continue
                y = xg[sel]
                mu = y.mean(axis=0, dtype=np.float64)
                y -= mu.astype(np.float32)
                if gram is None and k == d:
                    gram = y.T @ y  # numpy calls BLAS syrk for a matrix times its own transpose
                else:
                    if gram is None:
                        gram = np.zeros((d, d), np.float32)
                    gram[:k, :k] += y.T @ y
                v = np.zeros(d)
                v[:k] = m + mu
                means.append((sel.size, v))
            stats.append((np.array([c for c, _ in means], np.float64), np.stack([v for _, v in means], axis=1)))
            self._grams.append(gram)
        # the centre: the mean of the blocks' rows
        centre_p = sum(v @ n for n, v in stats) / sum(n.sum() for n, _ in stats)
        self.centre = centre_p[self._inverse]
        # the groups' means about the centre: added in pca (parallel axes), and the blocks' sums about it
        self._means = [(v - centre_p[:, None], n) for n, v in stats]
        self._sums = [v @ n for v, n in self._means]
        self._total = None  # the sum of every block's Gram matrix, made when a PCA first uses most blocks

    def _covered(self):
        return self._x if self._rows is None else self._x[self._rows]

    @property
    def xc(self):
        """``x - centre`` as float32, ``(n_rows, n_features)`` (made on first use)."""
        if self._xc is None:
            self._xc = self._covered().astype(np.float32, copy=True)
            self._xc -= self.centre.astype(np.float32)
        return self._xc

    def scores(self, pca):
        """PC scores of every row of ``x`` under ``pca`` (one of :meth:`pca`'s), by groups: ``(n_rows,
        pca.n_components_)`` float64, equal to ``pca.transform_centred(self.xc)`` up to float32 rounding."""
        wp = pca.components_[:, self._order]  # (n_pcs, d) permuted
        c_p = self.centre[self._order]
        z = np.empty((self._x.shape[0], wp.shape[0]), np.float64)
        for rows_g, k, m, xg in self._groups:
            v = -c_p.copy()
            v[:k] += m
            z[rows_g] = (xg @ wp[:, :k].T).astype(np.float64) + (v @ wp.T.astype(np.float64) - pca._offset)
        return z

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
        # (in the columns' order of the groups, zero_padding; the result in the features' own order)
        rest = [i for i in range(len(self.blocks)) if i not in set(use)]
        if len(use) > 1 and len(rest) < len(use) - 1:  # (k-fold: the total less the held-out blocks)
            if self._total is None:
                self._total = self._grams[0].copy()
                for g in self._grams[1:]:
                    self._total += g
            cov = np.subtract(self._total, self._grams[rest[0]]) if rest else self._total.copy()
            for i in rest[1:]:
                cov -= self._grams[i]
        else:
            cov = self._grams[use[0]].copy()
            for i in use[1:]:
                cov += self._grams[i]
        s = np.sum([self._sums[i] for i in use], axis=0)
        shift = s / n  # training mean - centre (small: the centre is the mean of all blocks)
        # the groups' means about the centre, less the training mean's shift: one low-rank update
        # sum_g n_g v_g v_g' - s s' / n
        v = np.concatenate([self._means[i][0] for i in use] + [s[:, None]], axis=1)
        w = np.concatenate([self._means[i][1] for i in use] + [[-1.0 / n]])
        cov += ((v * w).astype(np.float32)) @ v.T.astype(np.float32)
        cov *= np.float32(1.0 / (n - 1))
        vals, vecs = _top_eigen(cov, k, n_iter, n_oversamples, random_state, self._order)
        comps = np.ascontiguousarray(vecs.T[:, self._inverse], dtype=np.float32)
        shift = shift[self._inverse]
        offset = shift @ comps.T.astype(np.float64)
        return SplitPCA(self.centre + shift, comps, vals, self.centre, offset)


def _top_eigen(cov, k, n_iter, n_oversamples, random_state, order=None):
    """Leading ``k`` eigenpairs of a symmetric PSD matrix: exact for small matrices, else a randomized subspace
    iteration with a Rayleigh-Ritz step (Halko, Martinsson & Tropp 2011, Alg. 4.4 on ``cov``). ``order``: ``cov``'s
    rows and columns are the features in this order (the random start is drawn in the features' own order and
    permuted with them, so the iteration does not depend on the order)."""
    d = cov.shape[0]
    p = min(d, k + n_oversamples)
    if d <= 4 * p:  # small: LAPACK's exact solver is as cheap
        vals, vecs = eigh(cov.astype(np.float64), subset_by_index=[d - k, d - 1])
        return vals[::-1], vecs[:, ::-1]
    q = np.random.default_rng(random_state).standard_normal((d, p)).astype(cov.dtype)
    if order is not None:
        q = q[order]
    for _ in range(n_iter + 1):
        q = _orthonormal(cov @ q)
    small = (q.T @ (cov @ q)).astype(np.float64)
    vals, u = eigh((small + small.T) / 2)
    top = np.argsort(vals)[::-1][:k]
    return vals[top], q @ u[:, top].astype(q.dtype)


def zero_padding(x, labels=None, *, steps=32, chunk=4096):
    """The zero padding of a feature matrix: a column order, and each row's extent in it.

    With ``labels`` (per row, e.g. the trial's speed: the trials of one speed are padded alike), the columns are
    ordered by how many labels use them (a label uses a column where any of its rows is non-zero; most first,
    stable) and a row's extent is one past the last column, in that order, that its label uses: the encoder's padding
    gives nested prefixes, one per speed (the paper's 40-120 mm/s fill 60/40/30/24/20 of 60 windows). Without labels
    the columns are ordered by how many rows use them and a row's extent is its own last non-zero column (a column
    that is silent in many trials then sorts late: measured on the paper's features, 0.58 of the dense Gram's work
    against 0.39 with the speeds). Extents are rounded up to a multiple of ``n_features / steps``; every row is zero
    beyond its extent (exactly). Computed once per feature matrix and passed to :class:`GramBlocks` for its subsets
    (``padding=(order, extent[rows])``).

    Returns
    -------
    order : ndarray (n_features,) intp
    extent : ndarray (n_rows,) intp
    """
    x = np.asarray(x)
    n, d = x.shape
    if labels is not None:
        keys, inverse = np.unique(np.asarray(labels), return_inverse=True)
        inverse = inverse.ravel()
        used = np.zeros((keys.size, d), bool)
        for s in range(0, n, chunk):
            nz = x[s:s + chunk] != 0
            for i in np.unique(inverse[s:s + chunk]):
                used[i] |= nz[inverse[s:s + chunk] == i].any(axis=0)
        count = used.sum(axis=0)
        if count.min() == keys.size:
            return np.arange(d), np.full(n, d, np.intp)
        order = np.argsort(-count, kind="stable")
        last = np.array([np.flatnonzero(u[order]).max() + 1 if u.any() else 1 for u in used])
        extent = last[inverse]
    else:
        count = np.zeros(d, np.int64)
        for s in range(0, n, chunk):
            count += np.count_nonzero(x[s:s + chunk], axis=0)
        if n == 0 or count.min() == n:
            return np.arange(d), np.full(n, d, np.intp)
        order = np.argsort(-count, kind="stable")
        rank = np.empty(d, np.int32)
        rank[order] = np.arange(1, d + 1)
        extent = np.empty(n, np.intp)
        for s in range(0, n, chunk):
            extent[s:s + chunk] = ((x[s:s + chunk] != 0) * rank).max(axis=1)
    step = max(1, -(-d // steps))
    return order, np.clip(-(-extent // step) * step, 1, d)


def _groups(extent, min_rows=64):
    """Rows of one extent as groups ``(rows, k)`` by increasing ``k``; a group of fewer than ``min_rows`` rows joins
    the next wider one."""
    levels = np.unique(extent)
    groups, pending = [], None
    for level in levels:
        rows = np.flatnonzero(extent == level)
        pending = rows if pending is None else np.concatenate([pending, rows])
        if pending.size >= min_rows or level == levels[-1]:
            groups.append((np.sort(pending), int(level)))
            pending = None
    return groups


def _orthonormal(y):
    """An orthonormal basis of the columns of ``y`` (d, p) float32, as float32: Cholesky QR in float64 (``y' y =
    R' R``, ``Q = y R^-1``: two small products, where LAPACK's Householder QR of the tall block took ~40 % of an
    iteration); the float64 Gram keeps it exact to float32 for condition numbers up to ~1e7, and a second pass
    restores the orthogonality lost beyond. Householder QR if the Gram is not positive definite (rank-deficient)."""
    y64 = y.astype(np.float64)
    for _ in range(2):
        r, info = dpotrf(y64.T @ y64, lower=0, clean=1)
        if info != 0:
            return np.linalg.qr(y)[0]
        y64 = y64 @ solve_triangular(r, np.eye(r.shape[0]), lower=False, check_finite=False)
    return y64.astype(np.float32)


def split_scores(x, splits, n_components, *, random_states, kfold=False, padding=None, rows=None):
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
    padding : (order, extent), optional
        :func:`zero_padding` of ``x`` (computed here when not given).
    rows : int index array, optional
        The splits index ``x[rows]`` (not copied whole: the groups are gathered from ``x``).

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
        x = x if rows is None else x[rows]
        for (tr, te), rs in zip(splits, random_states):
            pca = fit_pca(x[tr], n_components, random_state=rs)
            yield pca.transform(x[tr]), pca.transform(x[te])
        return
    if kfold:
        gb = GramBlocks(x, [te for _, te in splits], padding=padding, rows=rows)
        for f, ((tr, te), rs) in enumerate(zip(splits, random_states)):
            pca = gb.pca([g for g in range(len(splits)) if g != f], n_components, random_state=rs)
            z = gb.scores(pca)  # every row once (no copies of the training rows)
            yield z[tr], z[te]
        return
    for (tr, te), rs in zip(splits, random_states):
        gb = GramBlocks(x, [tr], padding=padding, rows=rows)
        pca = gb.pca([0], n_components, random_state=rs)
        z = gb.scores(pca)
        yield z[tr], z[te]
