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

__all__ = ["GramBase", "GramBlocks", "SplitPCA", "WARM_ITER", "ordered_columns", "split_scores", "zero_padding"]

#: subspace iterations of a warm-started PCA (:meth:`GramBlocks.pca`, ``warm_start``); from a random start: 7
WARM_ITER = 4


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

    def __init__(self, mean, components, explained_variance, centre, offset, subspace=None):
        self.mean_ = mean
        self.components_ = components
        self.explained_variance_ = explained_variance
        self.n_components_ = components.shape[0]
        self._centre = centre  # the GramBlocks' centre; offset = (mean_ - centre) @ components_.T
        self._offset = offset
        # (n_features, p) float32, the features' own order: the iteration's whole Ritz basis (components_ and the
        # oversampling columns), the start of a warm-started iteration on a nearby covariance (None: exact solver)
        self._subspace = subspace

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
    ordered : ndarray (n_rows of x, n_features) float32, optional
        ``x[:, order]`` (``padding``'s column order), made once for many objects (:func:`ordered_columns`): the
        groups are then gathered as rows' leading columns (contiguous) instead of by rows and columns of ``x``
        (~4x faster on the paper's features). The same values.

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

    def __init__(self, x, blocks, *, padding=None, rows=None, base=None, ordered=None):
        x = np.asarray(x)
        if x.ndim != 2:
            raise ValueError(f"features must be 2-D (n_trials, n_features), got shape {x.shape}")
        self.blocks = [np.asarray(b) for b in blocks]
        if any(b.size == 0 for b in self.blocks):
            raise ValueError("empty row block")
        if not self.blocks and base is None:
            raise ValueError("no row blocks")
        self._x = x
        self._rows = None if rows is None else np.asarray(rows)
        n_rows = x.shape[0] if rows is None else self._rows.size
        self._xc = None
        self.n_features = d = x.shape[1]
        if padding is None:
            padding = zero_padding(self._covered()) if base is None else (base.order,
                                                                          _extents(self._covered(), base.order))
        self._order, extent = padding
        if base is not None and (base.n_features != d or not np.array_equal(base.order, self._order)):
            raise ValueError("the base's Gram matrix is of other columns, or of another column order (padding)")
        self._base = base
        groups = _groups(np.asarray(extent))
        self._inverse = np.argsort(self._order)
        # per group: its rows, its leading columns k, its mean over them (float64) and its rows centred on it (f32)
        self._groups = []
        group_of = np.empty(n_rows, np.intp)
        slot_of = np.empty(n_rows, np.intp)
        if ordered is None and _is_identity(self._order):
            ordered = x
        if ordered is not None and ordered.shape != x.shape:
            raise ValueError(f"ordered is {ordered.shape}, not the features' {x.shape}")
        for g, (rows_g, k) in enumerate(groups):
            src = rows_g if rows is None else self._rows[rows_g]  # (gathered from x itself: no copy of x[rows])
            if ordered is None:
                xg = x[np.ix_(src, self._order[:k])]
            else:
                xg = ordered[src, :k]
            xg = xg.astype(np.float32, copy=False)
            m = xg.mean(axis=0, dtype=np.float64)
            xg -= m.astype(np.float32)
            self._groups.append((rows_g, k, m, xg))
            group_of[rows_g] = g
            slot_of[rows_g] = np.arange(rows_g.size)
        self._grams = []
        # per block: (rows per group in the block, their means, padded, in the columns' order: (d, groups) float64)
        self._stats = []
        for b in self.blocks:
            # the block's rows in one buffer, by decreasing extent (the widest group first), each centred on its
            # group's mean in the block over its leading columns; beyond a row's extent the buffer is never read
            gb = group_of[b]
            parts = [(g, slot_of[b[gb == g]]) for g in reversed(range(len(self._groups)))]
            parts = [(g, sel) for g, sel in parts if sel.size]
            buf = np.empty((b.size, d), np.float32)
            spans, means, r0 = [], [], 0
            for g, sel in parts:
                _, k, m, xg = self._groups[g]
                y = buf[r0:r0 + sel.size, :k]
                if k == d:
                    np.take(xg, sel, axis=0, out=y, mode="clip")  # (valid indices: no buffered copy)
                else:
                    y[...] = xg[sel]
                mu = y.mean(axis=0, dtype=np.float64)
                y -= mu.astype(np.float32)
                r0 += sel.size
                spans.append((r0, k))
                v = np.zeros(d)
                v[:k] = m + mu
                means.append((sel.size, v))
            self._stats.append((np.array([c for c, _ in means], np.float64), np.stack([v for _, v in means], axis=1)))
            self._grams.append(_panel_gram(buf, spans))
        # the centre: the mean of the blocks' rows (of the base's, when there is one)
        stats = self._stats if base is None else [(base.counts, base.means)]
        centre_p = sum(v @ n for n, v in stats) / sum(n.sum() for n, _ in stats)
        self.centre = centre_p[self._inverse]
        # the groups' means about the centre: added in pca (parallel axes), and the blocks' sums about it
        self._means = [(v - centre_p[:, None], n) for n, v in self._stats]
        self._sums = [v @ n for v, n in self._means]
        if base is not None:
            self._base_means = base.means - centre_p[:, None]
            self._base_sum = self._base_means @ base.counts
        self._total = None  # the sum of every block's Gram matrix, made when a PCA first uses most blocks
        self._work_buf = None

    def _work(self):
        """A ``(d, d)`` float32 buffer for the covariances of :meth:`pca` (one for every PCA of this object: each is
        consumed by its fit, and fresh pages of the paper's 2160 x 2160 matrices cost as much as filling them)."""
        if self._work_buf is None:
            self._work_buf = np.empty((self.n_features, self.n_features), np.float32)
        return self._work_buf

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
        return self.scores_of([pca])[0]

    def scores_of(self, pcas):
        """:meth:`scores` under each of ``pcas`` (e.g. the k folds' PCAs), with one product per group for all of them
        (one pass over the rows instead of one per PCA): a list of ``(n_rows, n_components_)`` float64 arrays."""
        wps = [p.components_[:, self._order] for p in pcas]  # (n_pcs, d) each, permuted
        wp = np.concatenate(wps)
        ends = np.cumsum([w.shape[0] for w in wps])
        c_p = self.centre[self._order]
        n_rows = self._x.shape[0] if self._rows is None else self._rows.size
        zs = [np.empty((n_rows, w.shape[0]), np.float64) for w in wps]
        wp64 = wp.T.astype(np.float64)
        for rows_g, k, m, xg in self._groups:
            v = -c_p.copy()
            v[:k] += m
            prod = xg @ wp[:, :k].T
            const = v @ wp64
            for z, p, end, w in zip(zs, pcas, ends, wps, strict=True):
                cols = slice(end - w.shape[0], end)
                z[rows_g] = prod[:, cols].astype(np.float64) + (const[cols] - p._offset)
        return zs

    def pca(self, use, n_components, *, random_state=0, n_iter=None, n_oversamples=10, warm_start=None):
        """PCA of the rows of the blocks ``use``.

        Parameters
        ----------
        use : sequence of int
            Block numbers forming the training split.
        n_components : int
            PCs wanted; clipped to ``min(n_train - 1, n_features)``.
        random_state : int
            Seed of the random starting subspace.
        n_iter : int, optional
            Subspace iterations: default 7 from a random start (scikit-learn's randomized PCA for 50 PCs of 2160
            features), :data:`WARM_ITER` from ``warm_start``.
        n_oversamples : int
            Extra columns of the subspace (scikit-learn: 10).
        warm_start : SplitPCA, optional
            A PCA of a nearby covariance (e.g. the first fold's, with which a fold shares two thirds of its rows):
            the iteration starts from its subspace instead of a random one (ignored when it has none: the exact
            solver, or fewer columns).

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
        # (in the columns' order of the groups, zero_padding; the result in the features' own order)
        rest = [i for i in range(len(self.blocks)) if i not in set(use)]
        if len(use) > 1 and len(rest) < len(use) - 1:  # (k-fold: the total less the held-out blocks)
            if self._total is None:
                self._total = self._grams[0].copy()
                for g in self._grams[1:]:
                    self._total += g
            cov = self._work()
            if rest:
                np.subtract(self._total, self._grams[rest[0]], out=cov)
            else:
                np.copyto(cov, self._total)
            for i in rest[1:]:
                cov -= self._grams[i]
        else:
            cov = self._work()
            np.copyto(cov, self._grams[use[0]])
            for i in use[1:]:
                cov += self._grams[i]
        s = np.sum([self._sums[i] for i in use], axis=0)
        v = [self._means[i][0] for i in use]
        w = [self._means[i][1] for i in use]
        return self._fit(cov, v, w, s, n, n_components, random_state, n_iter, n_oversamples, warm_start)

    def pca_base_less(self, held_out, n_components, *, random_state=0, n_iter=None, n_oversamples=10,
                      warm_start=None):
        """PCA of the base's rows less those of the blocks ``held_out`` (each block's rows among the base's).

        The training covariance is the base's Gram matrix less the held-out blocks' (:class:`GramBase`): where the
        training split is most of a fixed set of rows (the extrapolation task trains on 75 of each trained cell's
        100 trials), a repetition forms the Gram matrix of the quarter it leaves out instead of the three quarters
        it trains on. Parameters (``warm_start``: e.g. the base's own PCA, :attr:`GramBase.pca`), returns and errors
        as :meth:`pca`; ValueError also when this object has no base.
        """
        base = self._base
        if base is None:
            raise ValueError("no base Gram matrix (GramBlocks(..., base=GramBase(...)))")
        held_out = list(held_out)
        n = int(base.counts.sum() - sum(self.blocks[i].size for i in held_out))
        if n < 2:
            raise ValueError(f"need at least 2 training rows, got {n}")
        cov = base.gram.copy()
        for i in held_out:
            cov -= self._grams[i]
        s = self._base_sum - np.sum([self._sums[i] for i in held_out] + [np.zeros(self.n_features)], axis=0)
        v = [self._base_means] + [self._means[i][0] for i in held_out]
        w = [base.counts] + [-self._means[i][1] for i in held_out]
        return self._fit(cov, v, w, s, n, n_components, random_state, n_iter, n_oversamples, warm_start)

    def _fit(self, cov, v, w, s, n, n_components, random_state, n_iter, n_oversamples, warm_start):
        """The PCA from the training rows' Gram matrix ``cov`` (float32, about their groups' means, modified in
        place), those means about the centre (``v``: (d, groups) arrays, ``w``: their row counts, negative for rows
        taken out), the rows' sum ``s`` about the centre and their number ``n``."""
        k = int(min(n_components, n - 1, self.n_features))
        if k < 1:
            raise ValueError("need at least one principal component")
        shift = s / n  # training mean - centre (small: the centre is the mean of all blocks)
        # the groups' means about the centre, less the training mean's shift: one low-rank update
        # sum_g n_g v_g v_g' - s s' / n
        v = np.concatenate(v + [s[:, None]], axis=1)
        w = np.concatenate(w + [[-1.0 / n]])
        # (the scatter matrix, not divided by n - 1: the iteration's subspace does not depend on the scale, the
        # values are divided instead; the low-rank sgemm then skips its pass scaling the (d, d) matrix)
        _add_low_rank(cov, (v * w).astype(np.float32), v.astype(np.float32), 1.0)
        start = None
        sub = None if warm_start is None else warm_start._subspace
        if sub is not None and sub.shape == (self.n_features, min(self.n_features, k + n_oversamples)):
            start = sub[self._order]
        if n_iter is None:
            n_iter = 7 if start is None else WARM_ITER
        vals, vecs, basis = _top_eigen(cov, k, n_iter, n_oversamples, random_state, self._order, start=start)
        vals = vals / (n - 1)
        comps = np.ascontiguousarray(vecs.T[:, self._inverse], dtype=np.float32)
        shift = shift[self._inverse]
        offset = shift @ comps.T.astype(np.float64)
        return SplitPCA(self.centre + shift, comps, vals, self.centre, offset,
                        None if basis is None else basis[self._inverse])


class GramBase:
    """The Gram matrix of a fixed set of rows, formed once, from which training splits that are most of those rows
    take theirs by subtraction (:meth:`GramBlocks.pca_base_less`), and its PCA, their iterations' warm start.

    The extrapolation task (Fig. 3C-F) trains every repetition on 75 of the 100 trials of each trained
    speed-force cell: the Gram matrix of all of the trained cells' trials is formed once per variant and each
    repetition forms only its 25 held-out trials' (a third of the work). Pass it to :class:`GramBlocks` (``base=``),
    with the same column order (``padding``).

    Parameters
    ----------
    x : array_like, shape (n_rows, n_features)
    rows : int index array
        Rows of ``x`` (distinct).
    padding : (order, extent), optional
        :func:`zero_padding` of ``x[rows]`` (or the order of a matrix they are a subset of and these rows' extents).
    n_components : int, optional
        Fit the base's own PCA too (:attr:`pca`), the start of the splits' iterations.
    random_state : int
        Seed of that PCA's random start.
    ordered : ndarray, optional
        ``x[:, order]``, as :class:`GramBlocks`.

    Attributes
    ----------
    rows : ndarray (n,) intp
    order : ndarray (n_features,) intp
        The columns' order of :attr:`gram`.
    n_features : int
    gram : ndarray (n_features, n_features) float32
        Sum over the rows' padding groups of each group's Gram matrix about its own mean, columns in ``order``.
    counts : ndarray (n_groups,) float64
        Rows per group.
    means : ndarray (n_features, n_groups) float64
        The groups' means (zero beyond their columns), in ``order``.
    pca : SplitPCA or None
    """

    def __init__(self, x, rows, *, padding=None, n_components=None, random_state=0, ordered=None):
        rows = np.asarray(rows)
        gb = GramBlocks(x, [np.arange(rows.size)], padding=padding, rows=rows, ordered=ordered)
        self.rows = rows
        self.order = gb._order
        self.n_features = gb.n_features
        self.gram = gb._grams[0]
        self.counts, self.means = gb._stats[0]
        self.pca = None if n_components is None else gb.pca([0], n_components, random_state=random_state)


def _panel_gram(buf, spans, width=256):
    """``sum_g Y_g' Y_g`` over the row groups of ``buf`` (n, d) float32: ``spans`` = [(end row, extent k), ...] by
    decreasing ``k``, the rows before ``end`` being the groups of extent >= ``k`` (each row read only up to its
    extent). One BLAS product per column panel of ``width`` columns (upper part and diagonal block, from the rows
    that reach it), written in place into the result (``np.matmul`` with ``out=`` a view: no zeroed temporary, no
    per-group triangle copy, no add pass), the panel's lower part then copied from its transpose. The same sums as
    the groups' ``syrk`` up to float32 rounding (other blocking; ~0.85x their time with their gathers, one thread).
    Returns ``(d, d)`` float32, symmetric; zero beyond the widest extent."""
    d = buf.shape[1]
    gram = np.empty((d, d), np.float32)
    k0 = spans[0][1]
    if k0 < d:
        gram[k0:] = 0
        gram[:k0, k0:] = 0
    tiles = []
    for i, (end, k) in enumerate(spans):
        lo = spans[i + 1][1] if i + 1 < len(spans) else 0
        rows = buf[:end]
        for c0 in range(lo, k, width):
            c1 = min(c0 + width, k)
            np.matmul(rows[:, :c1].T, rows[:, c0:c1], out=gram[:c1, c0:c1])
            tiles.append((c0, c1))
    for c0, c1 in tiles:  # the lower part, the transpose of the upper (exactly symmetric, as syrk's)
        gram[c1:k0, c0:c1] = gram[c0:c1, c1:k0].T
        below = np.tril_indices(c1 - c0, -1)
        tile = gram[c0:c1, c0:c1]
        tile[below] = tile.T[below]
    return gram


def _add_low_rank(cov, a, b, scale):
    """``cov = scale * (cov + a @ b.T)`` in place, by one BLAS ``sgemm`` into ``cov`` (C-contiguous float32, symmetric,
    as is ``a @ b.T``: its Fortran-ordered view, the transpose, is updated), not a ``(d, d)`` temporary and two more
    passes over it (fresh pages of the paper's 2160 x 2160 covariance cost as much as the passes themselves)."""
    from scipy.linalg.blas import sgemm

    scale = np.float32(scale)
    if cov.dtype == np.float32 and cov.flags.c_contiguous:
        out = sgemm(scale, a, b, beta=scale, c=cov.T, trans_b=True, overwrite_c=True)
        if np.shares_memory(out, cov):
            return
    cov += a @ b.T
    cov *= scale


def _top_eigen(cov, k, n_iter, n_oversamples, random_state, order=None, start=None):
    """Leading ``k`` eigenpairs of a symmetric PSD matrix: exact for small matrices, else a randomized subspace
    iteration (Halko, Martinsson & Tropp 2011, Alg. 4.4 on ``cov``) whose last product gives the eigenpairs by the
    Nystrom approximation ``Y (Q' Y)^-1 Y'`` of ``cov`` (``Y = cov Q``; Tropp, Yurtsever, Udell & Cevher 2017, Alg. 3,
    with their stabilising shift): as accurate as a Rayleigh-Ritz step on the span of ``Y`` (measured on the paper's
    features: docs/results.md 5o) without the Rayleigh-Ritz step's own product ``cov Q`` (``n_iter + 1`` products in
    all; Rayleigh-Ritz, one more, if the Nystrom core is not positive definite). ``order``: ``cov``'s rows and columns
    are the features in this order (the random start is drawn in the features' own order and permuted with them, so
    the iteration does not depend on the order). ``start``: (d, k + n_oversamples), the starting subspace instead of
    a random one (warm start). Returns the values, the vectors and the whole basis ``(d, k + n_oversamples)`` by
    decreasing value (None from the exact solver)."""
    d = cov.shape[0]
    p = min(d, k + n_oversamples)
    if d <= 4 * p:  # small: LAPACK's exact solver is as cheap
        vals, vecs = eigh(cov.astype(np.float64), subset_by_index=[d - k, d - 1])
        return vals[::-1], vecs[:, ::-1], None
    if start is not None:
        q = _orthonormal(np.asarray(start, cov.dtype))
    else:
        q = np.random.default_rng(random_state).standard_normal((d, p)).astype(cov.dtype)
        if order is not None:
            q = q[order]
        q = _orthonormal(q)
    for i in range(n_iter):  # (one Cholesky QR pass before the last: the span is the same, the last restores
        q = _orthonormal(_times(cov, q), passes=2 if i == n_iter - 1 else 1)  # the orthogonality to float32)
    y = _times(cov, q)
    got = _nystrom(q, y)
    if got is None:  # (Rayleigh-Ritz on the span of y)
        q = _orthonormal(y)
        small = (q.T @ _times(cov, q)).astype(np.float64)
        vals, u = eigh((small + small.T) / 2)
        top = np.argsort(vals)[::-1]
        vals, basis = vals[top], q @ u[:, top].astype(q.dtype)
    else:
        vals, basis = got
        basis = basis.astype(q.dtype)
    return vals[:k], basis[:, :k], basis


def _times(cov, q):
    """``cov @ q`` for a symmetric ``cov`` (d, d) and a thin ``q`` (d, p), as ``(q' cov)'`` (a (d, p) Fortran-ordered
    view): OpenBLAS's ``sgemm`` takes ~15 % less time with the thin factor on the left (one thread, 2160 x 2160 by 60:
    7.7 against 9.0 ms); the same product up to float32 rounding."""
    return (q.T @ cov).T


def _nystrom(q, y):
    """Eigenpairs (values decreasing, float64; vectors ``(d, p)``) of the Nystrom approximation ``Y (Q' Y)^-1 Y'`` of
    a PSD matrix ``A`` from an orthonormal ``Q`` (d, p) and ``Y = A Q``, with the shift ``nu`` of float32's
    precision (``A + nu I`` approximated, ``nu`` taken off the values); None if the core ``Q' Y`` is not positive
    definite."""
    q64 = q.astype(np.float64)
    y64 = y.astype(np.float64)
    nu = float(np.finfo(np.float32).eps * np.linalg.norm(y64))
    y64 += nu * q64
    core = q64.T @ y64
    c, info = dpotrf((core + core.T) / 2, lower=0, clean=1)
    if info != 0:
        return None
    f = solve_triangular(c, y64.T, trans="T", lower=False, check_finite=False).T  # Y C^-1
    u, sv, _ = np.linalg.svd(f, full_matrices=False)
    return np.maximum(sv**2 - nu, 0.0), u


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
        return order, _extents(x, order, steps=steps, chunk=chunk)
    step = max(1, -(-d // steps))
    return order, np.clip(-(-extent // step) * step, 1, d)


def _extents(x, order, *, steps=32, chunk=4096):
    """Each row's extent in the column order ``order``: one past its last non-zero column, rounded up as
    :func:`zero_padding` rounds."""
    n, d = x.shape
    rank = np.empty(d, np.int32)
    rank[order] = np.arange(1, d + 1)
    extent = np.empty(n, np.intp)
    for s in range(0, n, chunk):
        extent[s:s + chunk] = ((x[s:s + chunk] != 0) * rank).max(axis=1, initial=0)
    step = max(1, -(-d // steps))
    return np.clip(-(-extent // step) * step, 1, d)


def ordered_columns(x, order):
    """``x[:, order]`` as a new C-contiguous float32 matrix, or None when ``order`` is the columns' own (nothing to
    reorder: :class:`GramBlocks` then reads ``x`` itself). Made once per feature matrix and passed to every
    :class:`GramBlocks` of its rows (``ordered=``): gathering a group's rows and leading columns from it is one
    contiguous copy per row, where ``x[np.ix_(rows, order[:k])]`` gathered element by element (the paper's
    2160-column variants: ~0.1 CPU-s per repetition each). Memory: one more copy of ``x``."""
    x = np.asarray(x)
    if _is_identity(order):
        return None
    out = np.empty((x.shape[0], len(order)), np.float32)
    for s in range(0, x.shape[0], 256):  # (a cached block of rows at a time: ~0.1 s for 24,000 x 2160)
        np.take(x[s:s + 256].astype(np.float32, copy=False), order, axis=1, out=out[s:s + 256])
    return out


def _is_identity(order):
    order = np.asarray(order)
    return bool(order.ndim == 1 and np.array_equal(order, np.arange(order.size)))


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


def _orthonormal(y, passes=2):
    """An orthonormal basis of the columns of ``y`` (d, p) float32, as float32: Cholesky QR in float64 (``y' y =
    R' R``, ``Q = y R^-1``: two small products, where LAPACK's Householder QR of the tall block took ~40 % of an
    iteration); the float64 Gram keeps it exact to float32 for condition numbers up to ~1e7, and a second pass
    restores the orthogonality lost beyond (``passes``: 1 inside a subspace iteration, whose next product only needs
    the span). Householder QR if the Gram is not positive definite (rank-deficient)."""
    y64 = y.astype(np.float64)
    for _ in range(passes):
        r, info = dpotrf(y64.T @ y64, lower=0, clean=1)
        if info != 0:
            return np.linalg.qr(y)[0]
        y64 = y64 @ solve_triangular(r, np.eye(r.shape[0]), lower=False, check_finite=False)
    return y64.astype(np.float32)


def split_scores(x, splits, n_components, *, random_states, kfold=False, padding=None, rows=None, base=None,
                 warm_start=True, ordered=None):
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
    base : GramBase, optional
        The Gram matrix of a set of rows of ``x`` (indices into ``x`` itself) that holds a split's training rows:
        its covariance is then the base's less the base's other rows (:meth:`GramBlocks.pca_base_less`), when they
        are fewer than the training rows and all among ``rows``; else formed from the training rows. Its padding
        order is the one used (``padding``'s order must be the same).
    warm_start : bool
        k-fold: the later folds' iterations start from the first fold's subspace (the folds share two thirds of
        their rows), with a base from the base's PCA: :data:`WARM_ITER` iterations instead of 7 from a random start
        (as good a subspace, measured on the paper's features: docs/results.md 5i). False: every split from a random
        start.
    ordered : ndarray, optional
        ``x[:, order]`` for ``padding``'s order (:func:`ordered_columns`), as :class:`GramBlocks`.

    Yields
    ------
    z_train : ndarray (n_train, n_pcs) float64
    z_test : ndarray (n_test, n_pcs) float64
        ``n_pcs`` = the PCs fitted, nested.

    Notes
    -----
    The covariance path is taken when the training split has at least as many rows as features (the paper's
    6000 x 2160 folds); a wider matrix (few trials, many windows) goes through :func:`~rigctl.analysis.nested_lda.fit_pca`
    on the rows themselves, which is cheaper there and keeps memory at the data's size.
    """
    from rigctl.analysis.nested_lda import fit_pca

    x = np.asarray(x)
    if x.shape[1] > min(len(tr) for tr, _ in splits):
        x = x if rows is None else x[rows]
        for (tr, te), rs in zip(splits, random_states):
            pca = fit_pca(x[tr], n_components, random_state=rs)
            yield pca.transform(x[tr]), pca.transform(x[te])
        return
    if kfold:
        gb = GramBlocks(x, [te for _, te in splits], padding=padding, rows=rows, ordered=ordered)
        pcas: list[SplitPCA] = []
        for f, rs in enumerate(random_states[:len(splits)]):
            pcas.append(gb.pca([g for g in range(len(splits)) if g != f], n_components, random_state=rs,
                               warm_start=pcas[0] if pcas and warm_start else None))
        for (tr, te), z in zip(splits, gb.scores_of(pcas), strict=True):  # every row once, for every fold at once
            yield z[tr], z[te]
        return
    covered = np.arange(x.shape[0]) if rows is None else np.asarray(rows)
    for (tr, te), rs in zip(splits, random_states):
        held = None if base is None else _held_out(base, covered, np.asarray(tr), x.shape[0])
        if held is not None:
            gb = GramBlocks(x, [held] if held.size else [], padding=padding, rows=rows, base=base, ordered=ordered)
            pca = gb.pca_base_less([0] if held.size else [], n_components, random_state=rs,
                                   warm_start=base.pca if warm_start else None)
        else:
            gb = GramBlocks(x, [tr], padding=padding, rows=rows, ordered=ordered)
            pca = gb.pca([0], n_components, random_state=rs)
        z = gb.scores(pca)
        yield z[tr], z[te]



def _held_out(base, covered, tr, n_x):
    """Positions in ``covered`` of the base's rows that the split does not train on, or None when the base does not
    serve (a training row outside it, one of its other rows outside ``covered``, or as many of them as training
    rows: forming the training rows' Gram matrix is then as cheap)."""
    in_base = np.zeros(n_x, bool)
    in_base[base.rows] = True
    rows_tr = covered[tr]
    if not in_base[rows_tr].all():
        return None
    trained = np.zeros(n_x, bool)
    trained[rows_tr] = True
    held = np.flatnonzero(in_base[covered] & ~trained[covered])
    if held.size != base.rows.size - np.unique(rows_tr).size or held.size >= rows_tr.size:
        return None
    return held
