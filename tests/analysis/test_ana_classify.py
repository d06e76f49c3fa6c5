"""Nested-PC PCA + LDA (rigctl.analysis.classify) against scikit-learn fits, one per PC count.

scikit-learn (and rigctl.analysis.classify, built on it) is imported by the tests, not at the module's top: every
pytest-xdist worker collects every module, and ~2 CPU-s of scikit-learn + scipy.stats + pandas is then paid only by
the workers that run these tests."""

import numpy as np
import pytest

from rigctl.storage.model_file import ModelFileError, load_model, save_model


def _data(n=900, d=60, k=6, seed=0, sep=0.4):
    rng = np.random.default_rng(seed)
    y = rng.integers(0, k, n)
    centres = rng.standard_normal((k, d)) * sep
    x = centres[y] + rng.standard_normal((n, d)) * np.linspace(3, 0.5, d)
    return x.astype(np.float32), np.array(list("ABCDEFGH"))[y]


def test_nested_lda_equals_sklearn_per_pc():
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    from rigctl.analysis.classify import NestedLDA, fit_pca

    x, y = _data()
    xtr, ytr, xte = x[:600], y[:600], x[600:]
    pca = fit_pca(xtr, 25)
    ztr = pca.transform(xtr).astype(np.float64)
    zte = pca.transform(xte).astype(np.float64)
    lda = NestedLDA().fit(ztr, ytr)
    dec = lda.decision_all(zte)
    pred = lda.predict_all(zte)
    assert pred.shape == (25, 300)
    for n in range(1, 26):
        ref = LinearDiscriminantAnalysis().fit(ztr[:, :n], ytr)
        np.testing.assert_array_equal(pred[n - 1], ref.predict(zte[:, :n]))
        diff = ref.decision_function(zte[:, :n]) - dec[n - 1]
        # equal up to a class-independent offset per trial
        np.testing.assert_allclose(diff - diff.mean(axis=1, keepdims=True), 0, atol=1e-8)


def test_nested_lda_with_unequal_priors_matches_sklearn():
    from sklearn.decomposition import PCA
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    from rigctl.analysis.classify import NestedLDA

    x, y = _data(seed=3)
    keep = (y != "A") | (np.arange(len(y)) % 4 == 0)  # class A rarer
    x, y = x[keep], y[keep]
    z = PCA(10, svd_solver="full").fit_transform(x).astype(np.float64)
    pred = NestedLDA().fit(z[:500], y[:500]).predict_all(z[500:])
    for n in (1, 4, 10):
        np.testing.assert_array_equal(pred[n - 1],
                                      LinearDiscriminantAnalysis().fit(z[:500, :n], y[:500]).predict(z[500:, :n]))


def test_pca_components_are_nested():
    from sklearn.decomposition import PCA

    from rigctl.analysis.classify import fit_pca

    x, _ = _data(n=400, d=40)
    big = PCA(20, svd_solver="full").fit(x)
    small = PCA(5, svd_solver="full").fit(x)
    # the first 5 axes of the 20-component PCA are the 5-component PCA (up to sign)
    dots = np.abs(np.sum(big.components_[:5] * small.components_, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-4)
    # the randomized solver used by fit_pca finds the same leading axes
    fast = fit_pca(x, 20)
    dots = np.abs(np.sum(big.components_[:5] * fast.components_[:5], axis=1))
    assert dots.min() > 0.99


def test_nested_pc_predictions_accuracy_rises_with_pcs():
    from rigctl.analysis.classify import nested_pc_predictions

    x, y = _data(sep=0.6)
    pred, pca = nested_pc_predictions(x[:600], y[:600], x[600:], 30)
    acc = (pred == y[600:]).mean(axis=1)
    assert pca.n_components_ == 30
    assert acc[-1] > acc[0] + 0.2  # more PCs carry the class signal
    assert acc[-1] > 0.6


def test_texture_classifier_roundtrip_and_calibration(tmp_path):
    from rigctl.analysis.classify import TextureClassifier

    x, y = _data(sep=0.8)
    clf = TextureClassifier(n_pcs=20).fit(x[:600], y[:600])
    base = clf.score(x[600:], y[600:])
    assert base > 0.8
    path = tmp_path / "model.skops"
    save_model(clf, path)
    back = load_model(path)
    np.testing.assert_array_equal(back.predict(x[600:]), clf.predict(x[600:]))
    # a session offset (sensor drift) breaks the classifier; mean-centering calibration restores it
    shift = np.linspace(-12, 12, x.shape[1]).astype(np.float32)
    drifted = x[600:] + shift
    assert back.score(drifted, y[600:]) < base - 0.2
    back.calibrate(drifted[:60])
    assert back.score(drifted, y[600:]) > base - 0.1
    back.reset_calibration()
    assert back.score(x[600:], y[600:]) == pytest.approx(base)
    proba = clf.predict_proba(x[600:610])
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_array_equal(clf.classes_[proba.argmax(axis=1)], clf.predict(x[600:610]))


def test_texture_classifier_errors(tmp_path):
    from rigctl.analysis.classify import NestedLDA, TextureClassifier

    x, y = _data(n=200, d=20)
    clf = TextureClassifier(n_pcs=5, max_pcs=10).fit(x, y)
    with pytest.raises(ValueError):
        clf.predict(x, n_pcs=11)
    with pytest.raises(ValueError):
        clf.calibrate(x[:, :5])
    bad = tmp_path / "bad.skops"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="not a rigctl model file"):
        load_model(bad)
    with pytest.raises(ValueError):
        NestedLDA().fit(np.zeros((5, 2)), np.zeros(5))  # one class


@pytest.mark.parametrize("k", [2, 4, 16])
def test_predict_all_is_the_argmax_of_decision_all(k):
    """NestedLDA.predict_all (rigctl.analysis.lda_kernel: compiled, or NumPy for small calls) gives exactly the class
    of the largest discriminant of decision_all for every PC count, ties to the first class."""
    from rigctl.analysis.classify import NestedLDA

    rng = np.random.default_rng(k)
    y = rng.integers(0, k, 3000)
    z = rng.standard_normal((k, 30))[y] * 0.3 + rng.standard_normal((3000, 30)) * np.linspace(3, 0.5, 30)
    lda = NestedLDA().fit(z[:2000], np.array(list("PONMLKJIHGFEDCBA"))[y[:2000]])
    np.testing.assert_array_equal(lda.predict_all(z[2000:]), lda.classes_[lda.decision_all(z[2000:]).argmax(axis=2)])
    from scipy.linalg import solve_triangular

    from rigctl.analysis.lda_kernel import nested_argmax, nested_argmax_numpy

    zw = solve_triangular(lda.chol_, z[2000:].T, lower=True).T
    want = lda.decision_all(z[2000:]).argmax(axis=2)
    for argmax in (nested_argmax, nested_argmax_numpy):  # (predict_all takes either by the call's size)
        np.testing.assert_array_equal(argmax(zw, lda._means_w, lda._half_norm, lda._log_prior), want)
    np.testing.assert_array_equal(lda.predict_all(z[2000:], 7, chunk=300),
                                  lda.classes_[lda.decision_all(z[2000:], 7).argmax(axis=2)])
    tie = np.zeros((5, 30))  # equal discriminants (equal priors, means symmetric about 0): the first class
    lda = NestedLDA().fit(np.vstack([np.eye(30), -np.eye(30)] * 3), np.repeat([0, 1], 30)[None].repeat(3, 0).ravel())
    assert (lda.predict_all(tie) == lda.classes_[lda.decision_all(tie).argmax(axis=2)]).all()
