"""Table 1 without scikit-learn's import (issue 57 item 4): the stratified folds are scikit-learn's own, index for
index, and ``rigctl analyze --table1`` imports neither scikit-learn nor pandas nor scipy.stats (~2 CPU-s of every
start on this machine)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest


@pytest.mark.parametrize("seed", range(6))
def test_stratified_folds_are_scikit_learns(seed):
    from sklearn.model_selection import StratifiedKFold

    from rigctl.analysis.folds import stratified_kfold

    rng = np.random.default_rng(seed)
    n_classes = int(rng.integers(2, 17))
    labels = np.array([f"T{c}" for c in rng.integers(0, n_classes, int(rng.integers(40, 900)))])
    labels[:n_classes] = [f"T{c}" for c in range(n_classes)]  # every class at least once, out of order below
    labels = labels[rng.permutation(len(labels))]
    k = int(rng.integers(2, 6))
    state = int(rng.integers(2**31))
    few = np.unique(labels, return_counts=True)[1].min() < k
    with warnings.catch_warnings(record=True) as ours_warned:
        warnings.simplefilter("always")
        ours = stratified_kfold(labels, k, state)
        theirs = list(StratifiedKFold(k, shuffle=True, random_state=state).split(labels, labels))
    assert len(ours_warned) == 2 * few  # a class with fewer trials than folds: both warn
    assert len(ours) == len(theirs) == k
    for (tr, te), (tr_s, te_s) in zip(ours, theirs, strict=True):
        np.testing.assert_array_equal(tr, tr_s)
        np.testing.assert_array_equal(te, te_s)


def test_stratified_folds_refuse_more_folds_than_any_class_has():
    from rigctl.analysis.folds import stratified_kfold

    with pytest.raises(ValueError, match="n_splits=5"):
        stratified_kfold(np.array(["a", "a", "b", "b"]), 5, 0)


_ANALYZE = """
import sys
from rigctl.cli import main
sys.argv = ["rigctl", "analyze", sys.argv[1], "--table1", "--repeats", "2", "--pcs", "5", "--jobs", "1"]
try:
    main()
except SystemExit as exc:
    assert not exc.code, exc.code
print("IMPORTED", *(m for m in ("sklearn", "pandas", "scipy.stats", "scipy.sparse") if m in sys.modules))
"""


def test_table1_imports_no_scikit_learn_pandas_or_scipy_stats_or_sparse(tmp_path, write_schema1):
    """The whole ``rigctl analyze FILE --table1`` (read, both tasks' repetitions, the table with its Welch tests) in
    a fresh interpreter, on features with more trials than columns (the paper's covariance path)."""
    from rigctl.analysis.synthetic import synthetic_features

    fs = synthetic_features(8, n_textures=6, n_channels=2, seed=1)
    path = write_schema1(fs, tmp_path / "small.encoded.h5", 1)
    run = subprocess.run([sys.executable, "-c", _ANALYZE, str(path)], capture_output=True, timeout=300,
                         cwd=tmp_path)
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    out = run.stdout.decode()
    assert "Individual Textures" in out
    imported = out.rsplit("IMPORTED", 1)[1].split()
    assert imported == [], f"rigctl analyze --table1 imported {imported}"
