"""The fast Table 1 path (shared Gram blocks, subspace iteration, repetitions in parallel) gives the accuracies of the
straightforward scikit-learn PCA(n) + LinearDiscriminantAnalysis refit for every PC count, wherever it runs."""

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from rigctl.analysis.synthetic import synthetic_features

N_PCS = 8
#: test trials whose prediction may differ (on the decision boundary: float32 Gram + 7 subspace iterations vs a
#: float64 SVD, as scikit-learn's own randomized PCA differs from its exact one)
FLIPS = 2


def _straightforward(x, y, tr, te, n_pcs=N_PCS):
    """Correct test predictions per PC count 1..n_pcs: a PCA and an LDA fitted for every count."""
    from sklearn.decomposition import PCA
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    out = []
    for n in range(1, n_pcs + 1):
        pca = PCA(n, svd_solver="full").fit(x[tr])
        lda = LinearDiscriminantAnalysis().fit(pca.transform(x[tr]), y[tr])
        out.append(int(np.sum(lda.predict(pca.transform(x[te])) == y[te])))
    return np.array(out)


def _padded_features(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` trials' features of 3 spike trains x 20 windows (float32, n x 60), each trial filling 20, 10 or 5
    windows (zero beyond: a speed's padding), and the windows each fills."""
    x = rng.gamma(2.0, 5.0, (n, 3, 20))
    filled = rng.choice([20, 10, 5], n)
    for i, w in enumerate(filled):
        x[i, :, w:] = 0
    return x.reshape(n, -1).astype(np.float32), filled


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Tiny matrices: a threaded BLAS only waits for its other threads on a busy machine (10x slower)."""
    with threadpool_limits(1):
        yield


@pytest.fixture(scope="module")
def fs():
    # 8 textures x 15 conditions x 8 trials; 2 spike trains: 120 features unscaled, 40 speed scaled (fewer features
    # than training trials: the covariance path, with the subspace iteration for 120 and the exact solver for 40)
    return synthetic_features(8, n_textures=8, n_channels=2, noise=1.5, seed=3)


def test_cv_accuracies_equal_sklearn_refit_per_pc(fs):
    from rigctl.analysis.tasks import cv_split, run_cv

    res = run_cv(fs, ("textures",), n_pcs=N_PCS, repeats=1, per_texture=60, n_jobs=1)
    for v in ("original", "speed_scaled"):
        acc = res.curves["textures"][v].acc
        for r in range(1):
            idx, folds = cv_split(fs.texture, 60, 4, seed=0, repeat=r)
            x, y = fs.features[v][idx], fs.texture[idx]
            want = sum(_straightforward(x, y, tr, te) for tr, te in folds) / len(idx)
            assert np.abs(acc[r] - want).max() <= FLIPS / len(idx) + 1e-12, (v, r, acc[r], want)
            assert acc[r, -1] > 2 / 8  # the planted textures are found (chance 1/8)


def test_extrapolation_accuracies_equal_sklearn_refit_per_pc(fs):
    from rigctl.analysis.tasks import extrapolation_split, run_extrapolation

    res = run_extrapolation(fs, n_pcs=N_PCS, repeats=1, n_train=6, n_test=2, n_jobs=1)
    tr, te, cell = extrapolation_split(fs, n_train=6, n_test=2, seed=0, repeat=0)
    rows = np.concatenate([tr, te])
    for v in ("original", "speed_scaled"):
        x, y = fs.features[v][rows], fs.texture[rows]
        assert len(tr) >= x.shape[1]  # the covariance path
        for c in np.unique(cell):
            m = np.flatnonzero(cell == c) + len(tr)
            want = _straightforward(x, y, np.arange(len(tr)), m) / len(m)
            assert np.abs(res.curves[c][v].acc[0] - want).max() <= FLIPS / len(m) + 1e-12, (v, c)


def test_gram_block_pca_matches_sklearn():
    from sklearn.decomposition import PCA

    from rigctl.analysis.splitpca import GramBlocks

    rng = np.random.default_rng(0)
    scale = np.concatenate([np.geomspace(20, 2, 12), np.full(138, 0.5)])  # 12 distinct leading axes
    x = (rng.standard_normal((600, 150)) * scale + 5).astype(np.float32)
    blocks = np.array_split(rng.permutation(600), 3)
    gb = GramBlocks(x, blocks)
    rows = np.concatenate(blocks[1:])
    for use, want_rows in (([1, 2], rows), ([0], blocks[0])):
        p = gb.pca(use, 12)
        ref = PCA(12, svd_solver="full").fit(x[want_rows])
        np.testing.assert_allclose(p.mean_, ref.mean_, rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(p.explained_variance_, ref.explained_variance_, rtol=1e-3)
        cos = np.abs(np.sum(p.components_ * ref.components_, axis=1))  # same axes up to sign
        assert cos.min() > 0.999
        np.testing.assert_allclose(np.abs(p.transform(x[:5])), np.abs(ref.transform(x[:5])), rtol=1e-3, atol=1e-3)


@pytest.mark.filterwarnings("ignore:extrapolation. smallest trained cell")
def test_repetitions_in_threads_and_on_dask_give_the_same_table(fs):
    from rigctl.analysis.tasks import run_table1

    distributed = pytest.importorskip("dask.distributed")
    kw = {"variants": ["original"], "n_pcs": N_PCS, "repeats": 2, "per_texture": 40}

    def run(**where):
        res = run_table1(fs, **{**kw, **where})
        return {t: c["original"].acc for t, c in res.curves.items()}, res

    one, res = run(n_jobs=1)
    assert set(one) == {"textures", "groups", "untrained_speed_force", "untrained_force", "untrained_speed",
                        "trained"}
    assert all(a.shape == (2, N_PCS) for a in one.values())
    threads, _ = run(n_jobs=2)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        on_dask, _ = run(scheduler=cluster.scheduler_address)
    for t in one:
        np.testing.assert_array_equal(threads[t], one[t])
        np.testing.assert_array_equal(on_dask[t], one[t])


def test_zero_padded_rows_give_the_dense_pca_and_scores():
    """The unscaled variants' trials are zero-padded to the longest (a 2 s trial fills 20 of 60 windows): the Gram
    blocks are formed per padding group on its leading columns only, and the PCA and the scores are the dense ones."""
    from sklearn.decomposition import PCA

    from rigctl.analysis.splitpca import GramBlocks, zero_padding

    rng = np.random.default_rng(1)
    n, trains, windows = 900, 4, 30
    x = rng.gamma(2.0, 5.0, (n, trains, windows)) * np.linspace(3, 1, windows)
    filled = rng.choice([30, 20, 15, 10], n)  # windows each trial fills (speeds)
    for i, w in enumerate(filled):
        x[i, :, w:] = 0
    x[rng.random(x.shape) < 0.03] = 0  # silent windows inside a trial too
    x = x.reshape(n, -1).astype(np.float32)
    order, extent = zero_padding(x)
    assert len(np.unique(extent)) >= 4  # the four trial lengths are found
    assert np.all(np.flatnonzero(x[np.argmin(extent)] != 0) < x.shape[1])
    for i in range(n):  # every row is zero beyond its extent, in the order
        assert not x[i, order[extent[i]:]].any()
    order, extent = zero_padding(x, filled)  # by the trials' lengths (their speeds): one extent each
    assert sorted(np.unique(extent)) == [40, 60, 80, 120]  # (4 trains x 10, 15, 20, 30 windows)
    for i in range(n):
        assert not x[i, order[extent[i]:]].any()
    blocks = np.array_split(rng.permutation(n), 3)
    gb = GramBlocks(x, blocks)
    assert len(gb._groups) >= 4  # (the grouped path: not one dense group)
    dense = GramBlocks(x, blocks, padding=(np.arange(x.shape[1]), np.full(n, x.shape[1])))  # one group: every column
    assert len(dense._groups) == 1
    for use in ([1, 2], [0]):
        p, q = gb.pca(use, 10), dense.pca(use, 10)  # the same random start: equal up to float32 rounding
        np.testing.assert_allclose(p.mean_, q.mean_, rtol=1e-6, atol=1e-4)
        np.testing.assert_allclose(p.explained_variance_, q.explained_variance_, rtol=1e-4)
        assert np.abs(np.sum(p.components_ * q.components_, axis=1)).min() > 0.9999
        z, want = gb.scores(p), q.transform_centred(dense.xc)
        assert (np.abs(np.abs(z) - np.abs(want)).max(axis=0) < 2e-3 * want.std(axis=0)).all()
    rows = np.concatenate(blocks[1:])
    ref = PCA(3, svd_solver="full").fit(x[rows])  # the leading axes, well separated: as scikit-learn's exact PCA
    p = gb.pca([1, 2], 3)
    np.testing.assert_allclose(p.explained_variance_[:2], ref.explained_variance_[:2], rtol=1e-3)
    assert np.abs(np.sum(p.components_[:2] * ref.components_[:2], axis=1)).min() > 0.999


def test_the_groups_gathered_from_the_ordered_copy_are_the_same_numbers():
    """GramBlocks / GramBase / split_scores given the features in the padding's column order (ordered_columns, made
    once per matrix: the groups are then contiguous row copies) form the same Gram matrices, PCAs and scores, bit
    for bit; a copy of another shape is refused; an order that is the columns' own needs no copy."""
    from rigctl.analysis.splitpca import GramBase, GramBlocks, ordered_columns, split_scores, zero_padding

    rng = np.random.default_rng(4)
    n = 600
    x, filled = _padded_features(rng, n)
    order, extent = zero_padding(x, filled)
    xo = ordered_columns(x, order)
    np.testing.assert_array_equal(xo, x[:, order])
    assert ordered_columns(x, np.arange(x.shape[1])) is None
    rows = rng.permutation(n)[:450]
    blocks = np.array_split(np.arange(rows.size), 3)
    a = GramBlocks(x, blocks, padding=(order, extent[rows]), rows=rows)
    b = GramBlocks(x, blocks, padding=(order, extent[rows]), rows=rows, ordered=xo)
    for ga, gb_ in zip(a._grams, b._grams, strict=True):
        np.testing.assert_array_equal(ga, gb_)
    pa, pb = a.pca([0, 1], 8), b.pca([0, 1], 8)
    np.testing.assert_array_equal(pa.components_, pb.components_)
    np.testing.assert_array_equal(a.scores(pa), b.scores(pb))
    base_rows = rows[:300]
    ba = GramBase(x, base_rows, padding=(order, extent[base_rows]))
    bb = GramBase(x, base_rows, padding=(order, extent[base_rows]), ordered=xo)
    np.testing.assert_array_equal(ba.gram, bb.gram)
    folds = [(np.concatenate([blocks[j] for j in range(3) if j != f]), blocks[f]) for f in range(3)]
    za = list(split_scores(x, folds, 8, random_states=[0, 1, 2], kfold=True, padding=(order, extent[rows]), rows=rows))
    zb = list(split_scores(x, folds, 8, random_states=[0, 1, 2], kfold=True, padding=(order, extent[rows]), rows=rows,
                           ordered=xo))
    for (ta, ea), (tb, eb) in zip(za, zb, strict=True):
        np.testing.assert_array_equal(ta, tb)
        np.testing.assert_array_equal(ea, eb)
    with pytest.raises(ValueError, match="ordered"):
        GramBlocks(x, blocks, padding=(order, extent[rows]), rows=rows, ordered=xo[:10])


def test_the_confusion_matrix_is_scikit_learns():
    from sklearn.metrics import confusion_matrix

    from rigctl.analysis.tasks import _confusion

    rng = np.random.default_rng(2)
    classes = ["P", "B", "A", "Board10mm", "C"]  # not sorted: the matrix is in this order
    truth = rng.choice(classes + ["Z"], 500)  # a label outside the classes is left out, as scikit-learn does
    pred = rng.choice(classes, 500)
    np.testing.assert_array_equal(_confusion(truth, pred, classes), confusion_matrix(truth, pred, labels=classes))
    ints = rng.integers(0, 7, 300)
    np.testing.assert_array_equal(_confusion(ints, ints[::-1], [3, 1, 0, 2]),
                                  confusion_matrix(ints, ints[::-1], labels=[3, 1, 0, 2]))


def test_the_base_less_the_held_out_rows_is_the_training_rows_pca():
    """The extrapolation's fast path (issue 57): the Gram matrix of a fixed set of zero-padded rows formed once
    (GramBase), a split's covariance as it less the rows it does not train on; the same PCA and scores as the
    training rows' own, warm-started from the base's PCA as close to scikit-learn's exact axes."""
    from sklearn.decomposition import PCA

    from rigctl.analysis.splitpca import GramBase, GramBlocks, split_scores, zero_padding

    rng = np.random.default_rng(4)
    n, trains, windows = 1500, 4, 30
    scale = np.concatenate([np.geomspace(12, 2, 8), np.full(windows - 8, 0.7)])
    x = rng.gamma(2.0, 1.0, (n, trains, windows)) * scale + 3
    filled = rng.choice([30, 20, 15, 10], n)
    for i, w in enumerate(filled):
        x[i, :, w:] = 0
    x = x.reshape(n, -1).astype(np.float32)
    order, extent = zero_padding(x, filled)
    base_rows = np.sort(rng.choice(n, 1000, replace=False))
    base = GramBase(x, base_rows, padding=(order, extent[base_rows]), n_components=10)
    train = np.sort(rng.choice(base_rows, 750, replace=False))
    held = np.setdiff1d(base_rows, train)
    rows = np.concatenate([train, held, np.setdiff1d(np.arange(n), base_rows)])  # train, held-out, others
    pos_held = np.arange(len(train), len(train) + len(held))
    gb = GramBlocks(x, [pos_held], padding=(order, extent[rows]), rows=rows, base=base)
    direct = GramBlocks(x, [np.arange(len(train))], padding=(order, extent[rows]), rows=rows)
    p, q = gb.pca_base_less([0], 10), direct.pca([0], 10)  # (cold, the same random start)
    np.testing.assert_allclose(p.mean_, x[train].mean(axis=0, dtype=np.float64), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(p.explained_variance_, q.explained_variance_, rtol=1e-4)
    assert np.abs(np.sum(p.components_ * q.components_, axis=1)).min() > 0.9999
    z, want = gb.scores(p), direct.scores(q)
    assert (np.abs(np.abs(z) - np.abs(want)).max(axis=0) < 1e-3 * want.std(axis=0)).all()
    ref = PCA(10, svd_solver="full").fit(x[train])
    warm = gb.pca_base_less([0], 10, warm_start=base.pca)
    for pca in (p, warm):
        np.testing.assert_allclose(pca.explained_variance_[:8], ref.explained_variance_[:8], rtol=1e-3)
        assert np.abs(np.sum(pca.components_[:8] * ref.components_[:8], axis=1)).min() > 0.999
    # split_scores takes the base where it saves work: the held-out rows are covered and fewer than the trained
    (z_tr, z_te), = split_scores(x, [(np.arange(len(train)), pos_held)], 10, random_states=[0], rows=rows,
                                 padding=(order, extent[rows]), base=base)
    np.testing.assert_allclose(np.abs(z_tr), np.abs(warm.transform(x[train])), rtol=1e-3, atol=1e-3)


@pytest.mark.filterwarnings("ignore:extrapolation. smallest trained cell")
def test_extrapolation_from_the_trained_cells_base_equals_sklearn_refit_per_pc(fs, monkeypatch):
    """With enough repetitions the extrapolation's PCAs come from the trained cells' Gram matrix less each
    repetition's held-out trials, warm-started: every repetition's accuracies are the straightforward refit's."""
    from rigctl.analysis import splitpca
    from rigctl.analysis.tasks import extrapolation_split, run_extrapolation

    used = []
    real = splitpca.GramBlocks.pca_base_less
    monkeypatch.setattr(splitpca.GramBlocks, "pca_base_less", lambda self, *a, **kw: used.append(1) or
                        real(self, *a, **kw))
    repeats = 3
    res = run_extrapolation(fs, n_pcs=N_PCS, repeats=repeats, n_train=6, n_test=2, n_jobs=1,
                            variants=["original"])
    assert len(used) == repeats  # (the base path was taken)
    for r in range(repeats):
        tr, te, cell = extrapolation_split(fs, n_train=6, n_test=2, seed=0, repeat=r)
        rows = np.concatenate([tr, te])
        x, y = fs.features["original"][rows], fs.texture[rows]
        for c in np.unique(cell):
            m = np.flatnonzero(cell == c) + len(tr)
            want = _straightforward(x, y, np.arange(len(tr)), m) / len(m)
            assert np.abs(res.curves[c]["original"].acc[r] - want).max() <= FLIPS / len(m) + 1e-12, (r, c)


def test_map_threads_keeps_the_order_and_gives_each_thread_one_blas_thread():
    """Table 1's once-per-run steps (each variant's padding and trained cells' Gram matrix) run side by side:
    results in the items' order, BLAS at one thread inside the workers and as configured again after; one job runs
    them in the caller's thread, BLAS untouched."""
    import threading

    from threadpoolctl import threadpool_info

    from rigctl.analysis.parallel import map_threads

    def blas_threads():
        return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    seen = []

    def work(i):
        seen.append((threading.get_ident(), blas_threads()))
        return i * i

    with threadpool_limits(2):
        assert map_threads(work, range(7), n_jobs=2) == [i * i for i in range(7)]
        assert {n for _, n in seen} == {1}
        assert threading.get_ident() not in {t for t, _ in seen}
        assert blas_threads() == 2
        seen.clear()
        assert map_threads(work, [3, 1], n_jobs=1) == [9, 1]
        assert seen == [(threading.get_ident(), 2), (threading.get_ident(), 2)]


def test_the_subspace_iteration_takes_its_eigenpairs_from_its_last_product():
    """The randomized eigensolver of the Gram path makes n_iter + 1 products with the covariance (the Nystrom
    approximation from the last one, no Rayleigh-Ritz product after it: one product of 6-9 fewer per PCA,
    docs/results.md 5o) and still gives the leading eigenpairs: subspace and values against LAPACK's, from a random
    start and from a warm one."""
    from scipy.linalg import eigh, subspace_angles

    from rigctl.analysis.splitpca import _top_eigen

    class Counted(np.ndarray):
        products = 0

        def __matmul__(self, other):
            Counted.products += 1
            return np.asarray(self) @ np.asarray(other)

        def __rmatmul__(self, other):  # (q' cov: the thin factor on the left, splitpca._times)
            Counted.products += 1
            return np.asarray(other) @ np.asarray(self)

    rng = np.random.default_rng(6)
    d, k = 400, 20
    basis = np.linalg.qr(rng.standard_normal((d, d)))[0]
    spectrum = np.concatenate([100.0 * 0.8 ** np.arange(k), 0.5 * 0.99 ** np.arange(d - k)])
    cov = ((basis * spectrum) @ basis.T).astype(np.float32)
    vals_x, vecs_x = eigh(cov.astype(np.float64))
    vals_x, vecs_x = vals_x[::-1][:k], vecs_x[:, ::-1][:, :k]
    c = cov.view(Counted)
    warm = None
    for n_iter, start in ((7, None), (4, "warm")):
        Counted.products = 0
        vals, vecs, sub = _top_eigen(c, k, n_iter, 10, 0, start=warm if start else None)
        assert Counted.products == n_iter + 1
        assert np.sin(subspace_angles(vecs.astype(np.float64), vecs_x).max()) < 1e-3
        np.testing.assert_allclose(vals, vals_x, rtol=1e-4)
        warm = sub + np.float32(0.01) * rng.standard_normal(sub.shape).astype(np.float32)


def test_the_panel_gram_is_the_sum_of_the_groups_gram_matrices():
    """The Gram blocks' one-buffer form (splitpca._panel_gram: rows by decreasing extent, one BLAS product per column
    panel written in place, the lower part copied from the upper) gives the groups' sum of Y_g' Y_g on their leading
    columns (a float64 reference, to float32 rounding), exactly symmetric, zero beyond the widest extent, and never
    reads a row beyond its extent (NaN there)."""
    from rigctl.analysis.splitpca import GramBlocks, _panel_gram, zero_padding

    rng = np.random.default_rng(9)
    d = 700
    for ks, width in (([700, 500, 333, 100], 256), ([600, 599, 64], 64), ([300], 1000)):
        ns = rng.integers(20, 90, len(ks))
        buf = np.full((ns.sum(), d), np.nan, np.float32)
        ref = np.zeros((d, d))
        start = 0
        for n, k in zip(ns, ks, strict=True):
            y = rng.standard_normal((n, k)).astype(np.float32)
            buf[start:start + n, :k] = y
            ref[:k, :k] += y.T.astype(np.float64) @ y
            start += n
        gram = _panel_gram(buf, list(zip(np.cumsum(ns), ks, strict=True)), width)
        assert gram.dtype == np.float32 and np.isfinite(gram).all()
        np.testing.assert_array_equal(gram, gram.T)
        np.testing.assert_allclose(gram, ref, rtol=1e-4, atol=1e-3 * np.sqrt(ns.sum()))
        assert not gram[ks[0]:].any() and not gram[:, ks[0]:].any()
    # and GramBlocks' matrices are the blocks' rows' groups' Gram matrices about their means in the block
    n = 500
    x, filled = _padded_features(rng, n)
    order, extent = zero_padding(x, filled)
    blocks = np.array_split(rng.permutation(n), 3)
    gb = GramBlocks(x, blocks, padding=(order, extent))
    for b, gram in zip(blocks, gb._grams, strict=True):
        want = np.zeros((x.shape[1],) * 2)
        for k in np.unique(extent[b]):
            y = x[np.ix_(b[extent[b] == k], order[:k])].astype(np.float64)
            y -= y.mean(axis=0)
            want[:k, :k] += y.T @ y
        np.testing.assert_allclose(gram, want, rtol=1e-4, atol=1e-3 * np.abs(want).max())
