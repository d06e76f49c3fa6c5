"""Stratified k-fold splits without importing scikit-learn.

:func:`stratified_kfold` gives the folds of ``sklearn.model_selection.StratifiedKFold(k, shuffle=True,
random_state=seed).split(x, labels)``, the same index arrays (``tests/analysis/test_ana_folds.py`` holds them equal
on many label sets and seeds): the same round-robin allocation of each class's trials to the folds and the same
shuffles of a ``numpy.random.RandomState(seed)``. Why not scikit-learn's own: importing it pulls in ``scipy.stats``
and pandas, ~2 CPU-s of every ``rigctl analyze`` start on this machine (issue 57 item 4), and Table 1's repetitions
need nothing else of it. The grouped folds (``StratifiedGroupKFold``) still come from scikit-learn.
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["stratified_kfold"]


def stratified_kfold(labels, k: int, random_state: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Shuffled stratified ``k``-fold splits of ``labels``.

    Parameters
    ----------
    labels : array_like (n,)
        Class labels (any dtype ``numpy.unique`` sorts).
    k : int
        Folds (>= 2).
    random_state : int
        Seed of the ``numpy.random.RandomState`` that shuffles each class's fold assignment.

    Returns
    -------
    list of ``k`` ``(train, test)`` pairs of int index arrays into ``labels`` (ascending), as scikit-learn's.

    Raises
    ------
    ValueError
        ``k < 2``, or more folds than trials in every class (scikit-learn's check; a class with fewer trials than
        folds only warns, a UserWarning, as there).
    """
    y = np.asarray(labels)
    if y.ndim != 1:
        raise ValueError(f"labels must be 1-D, got shape {y.shape}")
    if k < 2:
        raise ValueError(f"need at least 2 folds, got {k}")
    rng = np.random.RandomState(random_state)
    _, first, inverse = np.unique(y, return_index=True, return_inverse=True)
    # classes coded by order of first appearance, as scikit-learn's
    _, class_perm = np.unique(first, return_inverse=True)
    coded = class_perm[inverse.ravel()]
    n_classes = len(first)
    counts = np.bincount(coded)
    if np.all(k > counts):
        raise ValueError(f"n_splits={k} cannot be greater than the number of members in each class.")
    if k > counts.min():
        warnings.warn(f"The least populated class in y has only {counts.min()} members, which is less than "
                      f"n_splits={k}.", UserWarning, stacklevel=2)
    ordered = np.sort(coded)
    allocation = np.asarray([np.bincount(ordered[i::k], minlength=n_classes) for i in range(k)])
    test_folds = np.empty(len(y), dtype="i")
    for c in range(n_classes):
        folds_for_class = np.arange(k).repeat(allocation[:, c])
        rng.shuffle(folds_for_class)
        test_folds[coded == c] = folds_for_class
    indices = np.arange(len(y))
    return [(indices[test_folds != i], indices[test_folds == i]) for i in range(k)]
