"""The paper's classification tasks (Fig. 3, Table 1, Fig. 4) on a :class:`~rigctl.analysis.data.FeatureSet`.

Methods, "Tactile Texture Dataset - Statistical Analysis":

* **Individual textures** (Fig. 3A) and **texture groups** (Fig. 3B): 500 trials drawn at random per texture (8000 of
  24,000), 4-fold cross-validation (6000 train / 2000 test per fold); the accuracy of one repetition is over all
  8000 tested trials. Both tasks use the same draws and folds, so one PCA per (repetition, fold, variant) serves
  both label sets (PCA is unsupervised).
* **Extrapolation** (Fig. 3C-F): train on speeds 40/60/80 mm/s x forces 250/500 g: per texture and trained cell,
  75 trials train and 25 test; 25 test trials per texture from every untrained cell. The test set is split into the
  four cells of Fig. 3C-F: untrained speed and force, untrained force, untrained speed, trained.
* Every task: 20 repetitions (new random draws), accuracy for PCs 1..50 (PCA fitted once per split, nested PCs,
  :mod:`rigctl.analysis.classify`), mean and sd per PC count, confusion matrices at the table's PC count,
  Original vs each scaled variant with Welch + Cohen's d and the two-proportion z-test + Cohen's h.

When a data set has fewer trials than the paper, the per-texture / per-cell counts are scaled down automatically
(a :class:`UserWarning` is emitted and the counts are stored in :attr:`TaskResults.counts`). Textures of unequal
counts are not cut to the smallest: every trial up to the per-texture draw is used, each texture weighted equally
(:func:`run_cv`), and the warning says so with the numbers.

Methods, "Real-time Texture Classification - Statistical Analysis" (Fig. 4): :func:`run_realtime` on ramp-profile
trials (velocity profiles slow / medium / fast / slow-to-fast / fast-to-slow): k = 4 cross-validation offline;
train on 75 % of the slow and medium trials and test on the rest (trained profiles) and on the untrained profiles;
and, given a second session, the mean-centering calibration (10 trials per texture from the new session) before
classifying it with the model trained on the first; LDA on 25 PCs is the headline PC count.
"""

from __future__ import annotations

import functools
import warnings
import weakref
from typing import Any

import numpy as np

from rigctl.analysis.cells import (  # noqa: F401  (the cells' helpers: splits.py and tests use them from here)
    EXTRAPOLATION_CELLS,
    _cell_text,
    _cells,
    _extrapolation_draw,
    _extrapolation_plan,
    _isin,
    _some,
    extrapolation_split,
)
from rigctl.analysis.data import FeatureSet, default_variants
from rigctl.analysis.nested_lda import NestedLDA, fit_pca
from rigctl.analysis.parallel import connected, map_repeats, map_threads, one_blas_thread
from rigctl.analysis.params import CVParams, Execution, ExtrapolationParams, RealtimeParams, Repetitions, resolve
from rigctl.analysis.results import TASK_TITLES, Curve, TaskResults, task_title
from rigctl.analysis.splitpca import ordered_columns, split_scores, zero_padding
from rigctl.core.progress import Stage

__all__ = [
    "TASK_TITLES",
    "realtime_draw",
    "realtime_rng",
    "task_title",
    "EXTRAPOLATION_CELLS",
    "Curve",
    "TaskResults",
    "cv_draw_counts",
    "cv_split",
    "extrapolation_split",
    "run_cv",
    "run_extrapolation",
    "run_realtime",
    "run_table1",
]

def _warn(res: TaskResults, msg: str):
    res.warnings.append(msg)
    warnings.warn(msg, UserWarning, stacklevel=3)


def _variants(fs: FeatureSet, variants, task="table1"):
    vs = default_variants(fs.variants, task) if variants is None else list(variants)
    missing = [v for v in vs if v not in fs.features]
    if missing:
        raise KeyError(f"variants not in the data: {missing} (have {fs.variants})")
    if not vs:
        raise ValueError("no feature variants to analyse")
    return vs


def _label_codes(labels, classes):
    """Labels and classes as integer codes that sort as they do (their places in the sorted union): the repetitions
    fit, predict and count on these (NestedLDA's ``np.unique``, its predictions and the comparisons with the truth
    were string operations, ~8 of a CV repetition's ~14 ms per fold and label set), with the same class order, so
    the same predictions, counts and confusion matrices (in ``classes``' order)."""
    labels, classes = np.asarray(labels), np.asarray(classes)
    universe = np.unique(np.concatenate([labels.ravel(), classes.ravel()]))
    return np.searchsorted(universe, labels), np.searchsorted(universe, classes)


def _accumulate(pred, truth, classes, confusion_pcs, weights=None):
    """pred (n_pcs, n_test) -> correct counts per PC (``weights`` (n_test,): weighted) and the confusion matrix at
    confusion_pcs (trials counted)."""
    hit = pred == truth[None, :]
    correct = hit.sum(axis=1) if weights is None else hit @ np.asarray(weights, dtype=np.float64)
    j = min(confusion_pcs, pred.shape[0]) - 1
    return correct, _confusion(truth, pred[j], classes)


def _weighted_priors(y, w) -> np.ndarray:
    """The classes' (``np.unique(y)``) shares of the weights ``w``: with each texture's trials weighted by the inverse
    of its count, every texture has an equal share (a group the share of its textures)."""
    classes, inverse = np.unique(y, return_inverse=True)
    mass = np.bincount(inverse, weights=np.asarray(w, dtype=np.float64), minlength=classes.size)
    out: np.ndarray = mass / mass.sum()
    return out


def _confusion(truth, pred, classes):
    """``sklearn.metrics.confusion_matrix(truth, pred, labels=classes)`` (rows: true class, columns: predicted; pairs
    with a label outside ``classes`` left out) by one ``bincount``: scikit-learn's input checks took ~30 ms a call,
    48 calls a Table 1 repetition."""
    lab = np.asarray(classes)
    k = lab.size
    sorter = np.argsort(lab, kind="stable")

    def codes(a):
        a = np.asarray(a)
        i = np.minimum(np.searchsorted(lab, a, sorter=sorter), k - 1)
        c = sorter[i]
        return c, lab[c] == a

    ct, ok_t = codes(truth)
    cp, ok_p = codes(pred)
    ok = ok_t & ok_p
    return np.bincount(ct[ok] * k + cp[ok], minlength=k * k).reshape(k, k)


def run_cv(
    fs: FeatureSet,
    tasks=("textures", "groups"),
    params: CVParams | None = None,
    *,
    reps: Repetitions | None = None,
    execution: Execution | None = None,
    progress=None,
    **overrides,
) -> TaskResults:
    """Individual-texture and texture-group classification with k-fold CV (Fig. 3A-B).

    Parameters
    ----------
    fs : FeatureSet
    tasks : sequence of {"textures", "groups"}
        Label sets to classify; they share draws, folds and PCA fits.
    params : :class:`rigctl.analysis.params.CVParams`
        ``per_texture`` trials drawn per texture (the paper: 500 of 1500): every trial of a texture holding fewer
        (:func:`cv_draw_counts`); when the textures then draw unequal counts, each texture is weighted equally (LDA
        priors their equal shares, the accuracy the mean of the textures' accuracies) and a warning says so with
        the numbers (``counts["cv"]``: ``weighting``, ``drawn_per_texture``); equal counts are the paper's
        balanced draw, unchanged (fewer than ``per_texture`` each: a warning). ``k`` folds (the paper: 4),
        ``groups`` (None: random folds; ``recording``, ``session``,
        ``block:N``: folds that never put one group on both sides, :mod:`rigctl.analysis.grouping`).
    reps : :class:`rigctl.analysis.params.Repetitions`
        ``n_pcs`` (the paper: 50), ``repeats`` (each a new random draw and new folds; the paper: 20), ``seed``,
        ``variants`` (default: all in ``fs``), ``confusion_pcs`` (default ``n_pcs``).
    execution : :class:`rigctl.analysis.params.Execution`
        Where the repetitions run (``n_jobs``, ``scheduler``, ``workers``); the results do not depend on it.
    progress : callable, optional
        Receives :class:`rigctl.core.progress.ProgressEvent` s (stage ``"textures/groups"``, per finished repetition).
    **overrides
        Fields of the three objects as keywords (e.g. ``repeats=5``).

    Returns
    -------
    TaskResults

    Raises
    ------
    GroupsError (a ValueError)
        "groups" asked for on data whose texture set defines no groups (the paper's groups are never assumed).
    ValueError
        Unknown task, fewer than ``k`` trials per texture, or groups the data cannot give (a texture in one group).
    """
    params, reps, execution = resolve(overrides, params or CVParams(), reps or Repetitions(),
                                      execution or Execution())
    per_texture, k = params.per_texture, params.k
    groups, note = None, None
    if params.groups:
        from rigctl.analysis.grouping import checked_groups

        groups, note = checked_groups(fs, str(params.groups), k)  # note: a grouping not what was asked, said below
    variants, n_pcs, repeats, seed, confusion_pcs = (reps.variants, reps.n_pcs, reps.repeats, reps.seed,
                                                     reps.confusion_pcs)
    n_jobs, scheduler, workers = execution.n_jobs, execution.scheduler, execution.workers
    for t in tasks:
        if t not in ("textures", "groups"):
            raise ValueError(f"unknown CV task '{t}'")
    if "groups" in tasks:
        fs.require_groups()  # GroupsError: the file's texture set defines no groups
    vs = _variants(fs, variants)
    res = TaskResults()
    if groups is not None and note:
        _warn(res, note)
    textures, drawn, weights = _cv_draw(fs, res, per_texture, k)
    res.counts["cv"] = {"per_texture": int(drawn.min()), "n_textures": len(textures), "folds": k, "repeats": repeats,
                        "trials_per_repeat": int(drawn.sum()), "groups": params.groups,
                        "n_groups": None if groups is None else int(np.unique(groups).size),
                        "weighting": "none" if weights is None else "balanced",
                        "drawn_per_texture": {str(t): int(d) for t, d in zip(textures, drawn, strict=True)},
                        "trials_available": int(fs.n_trials)}
    n_draw = int(drawn.min())
    confusion_pcs = n_pcs if confusion_pcs is None else confusion_pcs
    classes = {t: (fs.texture_classes if t == "textures" else fs.group_classes) for t in tasks}
    padding = _paddings(fs, vs, None if scheduler is not None else n_jobs)
    codes = {t: _label_codes(fs.texture if t == "textures" else fs.group, classes[t]) for t in tasks}
    shared = {"features": {v: fs.features[v] for v in vs}, "padding": padding,
              "texture": _label_codes(fs.texture, textures)[0],  # (the same draws and folds: the same order)
              "labels": {t: c for t, (c, _) in codes.items()}, "classes": {t: c for t, (_, c) in codes.items()},
              "n_draw": n_draw if weights is None else drawn, "k": k, "n_pcs": n_pcs, "seed": seed,
              "confusion_pcs": confusion_pcs, "groups": groups, "weights": weights}
    bar = Stage(progress, "textures/groups", repeats * k * len(vs), unit="fit")
    per_repeat = map_repeats(_cv_repeat, repeats, shared, n_jobs=n_jobs, scheduler=scheduler, workers=workers,
                       on_done=lambda: bar.advance(k * len(vs)))
    n_used = min(len(c) for rep in per_repeat for folds, _ in rep.values() for c in folds)
    n_drawn = int(drawn.sum())  # (weighted: each repetition's weights sum to it, so the accuracy is balanced)
    for t in tasks:
        for v in vs:
            a = np.vstack([np.sum([c[:n_used] for c in rep[(t, v)][0]], axis=0) / n_drawn for rep in per_repeat])
            cm = np.sum([rep[(t, v)][1] for rep in per_repeat], axis=0)
            res.add(Curve(t, v, a.astype(np.float64), n_drawn, classes[t], cm.astype(np.int64),
                          min(confusion_pcs, n_used)))
    res.settings.update({"n_pcs": n_used, "repeats": repeats, "seed": seed})
    return res


def _cv_draw(fs: FeatureSet, res: TaskResults, per_texture: int, k: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(textures, drawn per texture, per-trial weights or None)`` of :func:`run_cv`'s draw, its warning in ``res``:
    textures of unequal draws weight each texture equally (weights summing to the trials drawn); equal draws are the
    paper's (no weights). ValueError when a texture has fewer than ``k`` trials."""
    textures, counts = np.unique(fs.texture, return_counts=True)
    drawn = cv_draw_counts(counts, per_texture)
    n_draw = int(drawn.min())
    if n_draw < k:
        why = (f"per_texture is {per_texture}" if per_texture < k else f"the smallest texture has {counts.min()}")
        raise ValueError(f"need at least {k} trials per texture for {k}-fold CV ({why})")
    if drawn.max() > n_draw:  # textures of unequal counts: every trial, each texture weighted equally (said)
        _warn(res, _weighted_draw_warning(textures, counts, per_texture, drawn))
        return textures, drawn, (drawn.sum() / (len(textures) * drawn))[_label_codes(fs.texture, textures)[0]]
    if n_draw < per_texture:
        _warn(res, _short_draw_warning(textures, counts, per_texture, n_draw))
    return textures, drawn, None


def cv_draw_counts(counts, per_texture: int) -> np.ndarray:
    """Trials drawn per texture for the textures / groups tasks: every trial of each texture, up to ``per_texture``
    (the paper: 500 of its 1500); ``counts`` (n_textures,) the trials each texture holds. Equal counts are the
    paper's balanced draw; unequal ones are weighted (:func:`run_cv`: each texture counts equally)."""
    out: np.ndarray = np.minimum(np.asarray(counts, dtype=np.int64), int(per_texture))
    return out


def _weighted_draw_warning(textures: np.ndarray, counts: np.ndarray, per_texture: int, drawn: np.ndarray) -> str:
    """What an unequal draw does (issue 77 item 7: the smallest texture's count drawn from every texture used 120 of
    778 trials): every trial up to ``per_texture``, each texture weighted equally, and what the balanced draw would
    have used."""
    smallest = [f"{t} ({c})" for t, c in zip(textures, counts, strict=True) if c == counts.min()]
    return (f"textures/groups: the textures hold {counts.min()}-{counts.max()} trials (fewest: {_some(smallest)}); "
            f"using every trial up to --per-texture {per_texture} ({int(drawn.sum())} of {int(counts.sum())} trials "
            f"per repetition, {int(drawn.min())}-{int(drawn.max())} per texture), each texture weighted equally: the "
            "LDA's class priors are the textures' equal shares and the accuracy is the mean of the textures' "
            "accuracies (balanced accuracy); the confusion matrices count trials. A draw of the smallest count from "
            f"every texture would use {int(drawn.min()) * len(textures)}; "
            f"check the short texture's trials, or leave it out with --textures")


def _short_draw_warning(textures: np.ndarray, counts: np.ndarray, per_texture: int, n_draw: int) -> str:
    """The warning of a CV draw smaller than ``per_texture`` (``n_draw`` per texture, ``counts`` trials of each of
    ``textures``), with the advice that fits the data: a few textures short of the others set the size (check them or
    leave them out), or the session itself is smaller than the draw (say so with --per-texture)."""
    short = [f"{t} ({c})" for t, c in zip(textures, counts, strict=True) if c < per_texture]
    few = ", ".join(short[:6]) + (f" (+{len(short) - 6} more)" if len(short) > 6 else "")
    setters = [str(t) for t, c in zip(textures, counts, strict=True) if c == counts.min()]
    if counts.min() < np.median(counts):  # a few textures short of the others: they set the size
        advice = (f"the sample size is set by {_some(setters)} ({counts.min()} trials; median texture "
                  f"{int(np.median(counts))}): check its trials or leave it out with --textures")
    else:  # the session itself is smaller than the draw (a first recording, a small dataset): no texture to blame
        advice = (f"the session holds {counts.min()} trials for most textures: set --per-texture {n_draw} to say "
                  "so, or record more trials per texture")
    return (f"textures/groups: fewer than {per_texture} trials for {few}; drawing {n_draw} per texture instead of "
            f"{per_texture} ({n_draw * len(textures)} trials per repetition instead of {per_texture * len(textures)}): "
            f"{advice}")


#: zero_padding of the feature matrices in use, by id (with a weak reference that drops the entry with the matrix):
#: Table 1's two tasks share them
_PADDINGS: dict[int, tuple[weakref.ref, tuple]] = {}


def _forget_padding(key: int, _ref: weakref.ref) -> None:
    _PADDINGS.pop(key, None)


def _padding_labels(fs: FeatureSet) -> np.ndarray:
    """What pads a trial's unscaled windows alike: its speed (a trial covers a fixed travel) and its profile."""
    speed = np.char.mod("%.6g", np.round(np.abs(fs.speed_mm_s), 6))
    return speed if fs.profile is None else np.char.add(np.char.add(speed, "|"), fs.profile.astype(str))


def _paddings(fs: FeatureSet, vs, n_jobs=None) -> dict:
    """:func:`~rigctl.analysis.splitpca.zero_padding` of each variant's features and the features in its column
    order (:func:`~rigctl.analysis.splitpca.ordered_columns`, None where the order is the columns' own):
    ``{variant: (order, extent, ordered)}``, once for every repetition (and for both tasks of :func:`run_table1`);
    the variants not yet known side by side (``n_jobs`` threads, :func:`~rigctl.analysis.parallel.map_threads`)."""
    def known(v):
        hit = _PADDINGS.get(id(fs.features[v]))
        return hit is not None and hit[0]() is fs.features[v]

    def pad(v):
        x = fs.features[v]
        order, extent = zero_padding(x, labels)
        return order, extent, ordered_columns(x, order)

    missing = sorted((v for v in dict.fromkeys(vs) if not known(v)), key=lambda v: -fs.features[v].size)
    if missing:
        labels = _padding_labels(fs)
        for v, got in zip(missing, map_threads(pad, missing, n_jobs=n_jobs), strict=True):
            key = id(fs.features[v])
            _PADDINGS[key] = (weakref.ref(fs.features[v], functools.partial(_forget_padding, key)), got)
    return {v: _PADDINGS[id(fs.features[v])][1] for v in vs}


def _cv_repeat(r, *, features, texture, labels, classes, n_draw, k, n_pcs, seed, confusion_pcs, groups=None,
               padding=None, weights=None):
    """Repetition ``r`` of :func:`run_cv`: ``{(task, variant): ([correct per PC count, per fold], confusion)}``;
    with ``weights`` (per trial, :func:`run_cv`'s unequal draw) the correct counts are weighted and the LDA's priors
    are the classes' shares of the training weights."""
    idx, folds = cv_split(texture, n_draw, k, seed=seed, repeat=r, groups=groups)
    correct, cms = {}, {}
    for v, x in features.items():
        pad = None if padding is None else (padding[v][0], padding[v][1][idx])
        scores = split_scores(x, folds, n_pcs, random_states=[r * k + f for f in range(k)], kfold=True,
                              padding=pad, rows=idx, ordered=None if padding is None else padding[v][2])
        for (tr, te), (z_tr, z_te) in zip(folds, scores):
            for t, y_all in labels.items():
                y = y_all[idx]
                if weights is None:
                    pred = NestedLDA().fit(z_tr, y[tr]).predict_all(z_te)
                    c, cm = _accumulate(pred, y[te], classes[t], confusion_pcs)
                else:
                    w = weights[idx]
                    pred = NestedLDA(priors=_weighted_priors(y[tr], w[tr])).fit(z_tr, y[tr]).predict_all(z_te)
                    c, cm = _accumulate(pred, y[te], classes[t], confusion_pcs, w[te])
                correct.setdefault((t, v), []).append(c)
                cms[(t, v)] = cms.get((t, v), 0) + cm
    return {key: (correct[key], cms[key]) for key in correct}


def cv_split(texture, per_texture, k, *, seed=0, repeat=0, groups=None):
    """One repetition's draw and folds for the textures / groups tasks (Methods, Statistical Analysis).

    Parameters
    ----------
    texture : ndarray (n_trials,) str
    per_texture : int or ndarray (n_textures,) int
        Trials drawn at random (without replacement) per texture (the paper: 500), or per texture in
        ``np.unique(texture)``'s order (:func:`cv_draw_counts`).
    k : int
        Folds, stratified by texture (the paper: 4).
    seed, repeat : int
        ``numpy.random.default_rng([seed, repeat])``.
    groups : ndarray (n_trials,) str, optional
        What a fold must not cut (:func:`rigctl.analysis.grouping.cv_groups`): folds by
        ``sklearn.model_selection.StratifiedGroupKFold``, so train and test never share a group; without groups,
        ``StratifiedKFold(k, shuffle=True)``'s folds.

    Returns
    -------
    idx : ndarray (the per-texture draws' sum,) int
        Drawn trial indices.
    folds : list of (train, test) index arrays into ``idx``.
    """
    rng = np.random.default_rng([seed, repeat])
    uniq = np.unique(texture)
    each = np.broadcast_to(np.asarray(per_texture, dtype=np.int64), uniq.shape)
    idx = np.concatenate([rng.choice(np.flatnonzero(texture == t), int(n), replace=False)
                          for t, n in zip(uniq, each, strict=True)])
    state = int(rng.integers(2**31))
    if groups is not None:
        from sklearn.model_selection import StratifiedGroupKFold

        sgk = StratifiedGroupKFold(k, shuffle=True, random_state=state)
        return idx, list(sgk.split(idx, texture[idx], np.asarray(groups)[idx]))
    return idx, _stratified_folds(texture[idx], k, state)


def _stratified_folds(labels, k: int, state: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``StratifiedKFold(k, shuffle=True, random_state=state)``'s folds of ``labels`` (scikit-learn imported here)."""
    from sklearn.model_selection import StratifiedKFold

    return list(StratifiedKFold(k, shuffle=True, random_state=state).split(labels, labels))


def run_extrapolation(
    fs: FeatureSet,
    params: ExtrapolationParams | None = None,
    *,
    reps: Repetitions | None = None,
    execution: Execution | None = None,
    progress=None,
    **overrides,
) -> TaskResults:
    """Texture extrapolation to untrained speed-force conditions (Fig. 3C-F).

    Parameters
    ----------
    fs : FeatureSet
    params : :class:`rigctl.analysis.params.ExtrapolationParams`
        ``train_speeds`` (mm/s, matched on ``|speed|``: FabricSlide's signed directions count as one speed; None =
        every speed), ``train_forces`` (g; None = every force), ``test_speeds`` / ``test_forces`` (restrict the
        untrained test cells; default every condition in the data), ``n_train`` / ``n_test`` (per texture and
        trained cell: training and held-out test trials, the paper's 75 and 25; untrained cells contribute
        ``n_test`` test trials per texture; reduced proportionally, with a warning, when a cell has fewer than
        ``n_train + n_test`` trials), ``prefix`` (prepended to the task keys, e.g. ``"speed_"``).
    reps, execution, progress, **overrides
        As :func:`run_cv`.

    Returns
    -------
    TaskResults
        Tasks ``untrained_speed_force``, ``untrained_force``, ``untrained_speed``, ``trained`` (those with test trials).

    Raises
    ------
    ValueError
        No trials in the trained cells, or a trained cell too small to split.
    """
    params, reps, execution = resolve(overrides, params or ExtrapolationParams(), reps or Repetitions(),
                                      execution or Execution())
    train_speeds, train_forces, test_speeds, test_forces = (params.train_speeds, params.train_forces,
                                                            params.test_speeds, params.test_forces)
    n_train, n_test, prefix = params.n_train, params.n_test, params.prefix
    variants, n_pcs, repeats, seed, confusion_pcs = (reps.variants, reps.n_pcs, reps.repeats, reps.seed,
                                                     reps.confusion_pcs)
    n_jobs, scheduler, workers = execution.n_jobs, execution.scheduler, execution.workers
    vs = _variants(fs, variants)
    res = TaskResults()
    cells, trained_cells, cat_of, (a_tr, a_te, u_te), info = _extrapolation_plan(
        fs, train_speeds, train_forces, test_speeds, test_forces, n_train, n_test)
    hold = info["held_out_cells"]
    if hold:
        _warn(res, f"{prefix}extrapolation: a trained cell holds {info['min_trained']} trial(s) "
              f"({_some(info['smallest_trained'])}), too few to split into train and test: whole cells held out "
              f"instead: each repetition tests {hold} of each texture's {info['trained_cells_per_texture']} trained "
              f"cells (drawn at random; the '{task_title(prefix + 'trained')}' row: trained speeds and forces, cells "
              f"never trained on) and trains on the others; every untrained cell tests {u_te} trial(s)")
    elif (a_tr, a_te, u_te) != (n_train, n_test, n_test):
        _warn(res, f"{prefix}extrapolation: smallest trained cell has {info['min_trained']} trials "
              f"({_some(info['smallest_trained'])}) and smallest untrained cell {info['min_untrained']} "
              f"({_some(info['smallest_untrained']) or 'none'}); using {a_tr} train + {a_te} test per texture and trained "
              f"cell and {u_te} test per untrained cell (paper: {n_train} + {n_test}, {n_test})")
    res.counts[prefix + "extrapolation"] = {
        "train_per_cell": a_tr, "test_per_trained_cell": a_te, "test_per_untrained_cell": u_te,
        "trained_speeds": info["trained_speeds"], "trained_forces": info["trained_forces"],
        "n_trained_cells": len(trained_cells), "n_untrained_cells": len(cells) - len(trained_cells),
        "repeats": repeats, "split": "held-out cells" if hold else "trials within cells",
        "held_out_cells_per_texture": hold,
    }
    confusion_pcs = n_pcs if confusion_pcs is None else confusion_pcs
    classes = fs.texture_classes  # the texture set's order (stable codes)
    cats = [c for c in EXTRAPOLATION_CELLS.values() if c in set(cat_of.values())]
    padding = _paddings(fs, vs, None if scheduler is not None else n_jobs)
    texture_codes, class_codes = _label_codes(fs.texture, classes)
    shared = {"features": {v: fs.features[v] for v in vs}, "padding": padding, "texture": texture_codes,
              "classes": class_codes, "cells": cells, "trained_cells": trained_cells, "cat_of": cat_of, "counts": (a_tr, a_te, u_te),
              "cats": cats, "n_pcs": n_pcs, "seed": seed, "confusion_pcs": confusion_pcs, "hold_cells": hold,
              "bases": {} if hold else _trained_bases(fs, vs, padding, cells, trained_cells, a_tr, repeats, n_pcs,
                                                      seed, n_jobs=None if scheduler is not None else n_jobs)}
    bar = Stage(progress, prefix + "extrapolation", repeats * len(vs), unit="fit")
    per_repeat = map_repeats(_extrapolation_repeat, repeats, shared, n_jobs=n_jobs, scheduler=scheduler,
                       workers=workers, on_done=lambda: bar.advance(len(vs)))
    n_used = min(len(acc) for rep in per_repeat for acc, _, _ in rep.values())
    n_tested = {c: per_repeat[0][(c, vs[0])][2] for c in cats}
    for c in cats:
        for v in vs:
            a = np.vstack([rep[(c, v)][0][:n_used] for rep in per_repeat])
            cm = np.sum([rep[(c, v)][1] for rep in per_repeat], axis=0)
            res.add(Curve(prefix + c, v, a, n_tested[c], classes, cm.astype(np.int64), min(confusion_pcs, n_used)))
    res.counts[prefix + "extrapolation"]["tested_per_repeat"] = {prefix + c: n_tested[c] for c in cats}
    res.settings.update({"n_pcs": n_used, "repeats": repeats, "seed": seed})
    return res


def _trained_bases(fs, vs, padding, cells, trained_cells, n_train, repeats, n_pcs, seed, n_jobs=None):
    """Per variant, the Gram matrix of every trial of the trained cells and its PCA
    (:class:`~rigctl.analysis.splitpca.GramBase`), formed once: each repetition trains on ``n_train`` of each
    cell's trials and forms only the others' Gram matrix (the paper's 25 of 100). ``{}`` where that saves nothing
    (as many trials left out as trained on, or fewer trials than features: no covariance path)."""
    from rigctl.analysis.splitpca import GramBase

    rows = np.sort(np.concatenate([cells[c] for c in trained_cells]))
    n_tr = n_train * len(trained_cells)
    if repeats * (n_tr - (rows.size - n_tr)) <= rows.size:  # the base costs one pass over all of them
        return {}
    wanted = sorted((v for v in vs if fs.features[v].shape[1] <= n_tr), key=lambda v: -fs.features[v].shape[1])
    bases = map_threads(lambda v: GramBase(fs.features[v], rows, padding=(padding[v][0], padding[v][1][rows]),
                                           n_components=n_pcs, random_state=seed, ordered=padding[v][2]),
                        wanted, n_jobs=n_jobs)  # (the widest first: the threads finish together)
    return {v: bases[wanted.index(v)] for v in vs if v in wanted}


def _extrapolation_repeat(r, *, features, texture, classes, cells, trained_cells, cat_of, counts, cats, n_pcs, seed,
                          confusion_pcs, padding=None, bases=None, hold_cells=0):
    """Repetition ``r`` of :func:`run_extrapolation`: ``{(cell, variant): (accuracy per PC count, confusion,
    test trials)}``."""
    train_idx, test_idx, test_cat = _extrapolation_draw(cells, trained_cells, cat_of, *counts,
                                                        np.random.default_rng([seed, 10_000 + r]), hold_cells)
    y_tr, y_te = texture[train_idx], texture[test_idx]
    rows = np.concatenate([train_idx, test_idx])
    split = [(np.arange(len(train_idx)), np.arange(len(train_idx), len(rows)))]
    if bases:  # the trained cells' trials neither trained nor tested on: covered too (their Gram is subtracted)
        rows = np.concatenate([rows, np.setdiff1d(next(iter(bases.values())).rows, rows)])
    out = {}
    for v, x in features.items():
        pad = None if padding is None else (padding[v][0], padding[v][1][rows])
        (z_tr, z_te), = split_scores(x, split, n_pcs, random_states=[r], padding=pad, rows=rows,
                                     base=(bases or {}).get(v), ordered=None if padding is None else padding[v][2])
        pred = NestedLDA().fit(z_tr, y_tr).predict_all(z_te)
        for c in cats:
            m = test_cat == c
            correct, cm = _accumulate(pred[:, m], y_te[m], classes, confusion_pcs)
            out[(c, v)] = (correct / m.sum(), cm, int(m.sum()))
    return out


def run_table1(fs: FeatureSet, reps: Repetitions | None = None, *, execution: Execution | None = None,
               cv: CVParams | None = None, progress=None, **overrides) -> TaskResults:
    """All six rows of Table 1 (textures, groups and the four extrapolation cells), every variant.

    ``execution``: where the repetitions run, as :func:`run_cv`; one Dask client serves both tasks. ``overrides``:
    fields of ``reps``, ``execution`` and ``cv`` as keywords.
    """
    reps, execution, cv = resolve(overrides, reps or Repetitions(), execution or Execution(), cv or CVParams())
    with connected(execution.scheduler, execution.workers) as client:
        par = Execution(n_jobs=execution.n_jobs, scheduler=client)
        res = run_cv(fs, ("textures", "groups") if fs.group is not None else ("textures",), cv, reps=reps,
                     execution=par, progress=progress)
        return res.merge(run_extrapolation(fs, reps=reps, execution=par, progress=progress))


def _project(pca, x, centre):
    return (np.asarray(x, np.float64) - centre) @ np.asarray(pca.components_, np.float64).T


@one_blas_thread
def run_realtime(
    fs: FeatureSet,
    params: RealtimeParams | None = None,
    *,
    new_session: FeatureSet | None = None,
    reps: Repetitions | None = None,
    progress=None,
    **overrides,
) -> TaskResults:
    """The real-time analyses of Fig. 4 on ramp-profile trials (Methods, real-time Statistical Analysis).

    Parameters
    ----------
    fs : FeatureSet
        Training session: trials with a ``profile`` column (velocity-profile names), features of the real-time
        encoding (SA spike rates of 100 ms windows; variants ``original`` and ``speed_scaled``).
    new_session : FeatureSet, optional
        A second session: the model trained on ``train_fraction`` of ``fs`` is calibrated with the mean vector of
        ``calibration_per_texture`` trials per texture of it (spread over its profiles) and tested on the rest
        (task ``rt_new_session``, Fig. 4B green).
    params : :class:`rigctl.analysis.params.RealtimeParams`
        ``train_profiles`` (trained in the extrapolation task; the paper: slow, medium), ``k`` (folds of the offline
        task; 4), ``train_fraction`` (of the trained-profile trials drawn for training in the extrapolation /
        new-session tasks), ``calibration_per_texture``, ``headline_pcs`` (PC count of the confusion matrices; the
        paper's real-time classifier: 25).
    reps : :class:`rigctl.analysis.params.Repetitions`
        ``n_pcs`` (largest PC count, clipped to what the training split supports), ``repeats`` (default here: 100
        per data set, the paper's), ``seed``, ``variants`` (default: ``realtime_original`` /
        ``realtime_speed_scaled`` if present, else ``original`` / ``speed_scaled``).
    progress, **overrides
        As :func:`run_cv`.

    Returns
    -------
    TaskResults
        Tasks ``rt_offline``, ``rt_trained``, ``rt_untrained`` and, with ``new_session``, ``rt_new_session``.

    Raises
    ------
    ValueError
        No ``profile`` column, or none of ``train_profiles`` present.
    """
    params, reps = resolve(overrides, params or RealtimeParams(), reps or Repetitions(repeats=100))
    train_profiles, k, train_fraction = params.train_profiles, params.k, params.train_fraction
    calibration_per_texture, headline_pcs = params.calibration_per_texture, params.headline_pcs
    if params.features not in ("windows", "statistics"):
        raise ValueError(f"unknown real-time features {params.features!r}: windows or statistics")

    def view(x):  # the features the PCs see (params.features; one home: rigctl.encoding.alignment)
        if params.features == "windows":
            return x
        from rigctl.encoding.alignment import window_statistics
        from rigctl.encoding.features import N_WINDOWS_REALTIME

        return window_statistics(x, max(1, x.shape[1] // N_WINDOWS_REALTIME)).astype(np.float32)
    variants, n_pcs, repeats, seed = reps.variants, reps.n_pcs, reps.repeats, reps.seed
    if fs.profile is None:
        raise ValueError("the real-time analysis needs ramp-profile trials: /trials has no 'profile' column")
    vs = _variants(fs, variants, "realtime")
    res = TaskResults()
    classes = fs.texture_classes
    profiles = np.unique(fs.profile)
    trained_p = [p for p in train_profiles if p in set(profiles)]
    if not trained_p:
        raise ValueError(f"none of the training profiles {', '.join(map(str, train_profiles))} in the data (has "
                         f"{', '.join(map(str, profiles))})")
    in_tr = np.isin(fs.profile, trained_p)
    res.counts["realtime"] = {"trials": fs.n_trials, "profiles": list(map(str, profiles)),
                              "trained_profiles": trained_p, "repeats": repeats, "folds": k,
                              "trained_profile_trials": int(in_tr.sum()),
                              "untrained_profile_trials": int((~in_tr).sum())}
    store: dict[Any, Any] = {}
    n_used = [n_pcs]

    def add(task, v, pred, truth):
        n_used[0] = min(n_used[0], len(pred))
        correct, cm = _accumulate(pred, truth, classes, headline_pcs)
        a, c, n = store.get((task, v), ([], 0, 0))
        a.append(correct)
        store[(task, v)] = (a, c + cm, len(truth))

    bar = Stage(progress, "realtime", repeats * len(vs), unit="fit")
    for r in range(repeats):
        rng = realtime_rng(seed, r)
        folds, tr_idx, held, untr = realtime_draw(fs.texture, in_tr, k, train_fraction, rng)
        all_tr = _stratified_fraction(np.arange(fs.n_trials), fs.texture, train_fraction, rng)
        if new_session is not None:
            cal = _calibration_draw(new_session, calibration_per_texture, rng)
            rest = np.setdiff1d(np.arange(new_session.n_trials), cal)
        for v in vs:
            x = view(fs.features[v])
            preds, truths = [], []
            for f, (tr, te) in enumerate(folds):
                pca = fit_pca(x[tr], n_pcs, random_state=r * k + f)
                lda = NestedLDA().fit(pca.transform(x[tr]), fs.texture[tr])
                preds.append(lda.predict_all(pca.transform(x[te]), pca.n_components_))
                truths.append(fs.texture[te])
            n_min = min(len(p) for p in preds)
            add("rt_offline", v, np.hstack([p[:n_min] for p in preds]), np.concatenate(truths))
            pca = fit_pca(x[tr_idx], n_pcs, random_state=r)
            lda = NestedLDA().fit(pca.transform(x[tr_idx]), fs.texture[tr_idx])
            if len(held):
                add("rt_trained", v, lda.predict_all(pca.transform(x[held]), n_pcs), fs.texture[held])
            if len(untr):
                add("rt_untrained", v, lda.predict_all(pca.transform(x[untr]), n_pcs), fs.texture[untr])
            if new_session is not None and v in new_session.features:
                pca = fit_pca(x[all_tr], n_pcs, random_state=r)
                lda = NestedLDA().fit(pca.transform(x[all_tr]), fs.texture[all_tr])
                xn = view(new_session.features[v])
                centre = xn[cal].astype(np.float64).mean(axis=0)  # mean-centering calibration
                add("rt_new_session", v, lda.predict_all(_project(pca, xn[rest], centre), n_pcs),
                    new_session.texture[rest])
            bar.advance(1)
    for (task, v), (a, cm, n_te) in store.items():
        n = min(len(row) for row in a)  # PCs usable in this task (e.g. 30 training trials -> at most 25)
        acc = np.vstack([row[:n] for row in a]).astype(np.float64) / n_te
        res.add(Curve(task, v, acc, n_te, classes, np.asarray(cm, np.int64), min(headline_pcs, n)))
    res.settings.update({"n_pcs": n_used[0], "repeats": repeats, "seed": seed, "headline_pcs": headline_pcs})
    return res


def realtime_rng(seed: int, repeat: int) -> np.random.Generator:
    """The generator of :func:`run_realtime`'s repetition ``repeat`` (what :func:`realtime_draw` draws from)."""
    return np.random.default_rng([seed, 20_000 + repeat])


def realtime_draw(texture: np.ndarray, in_trained: np.ndarray, k: int, train_fraction: float,
                  rng: np.random.Generator) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray,
                                                     np.ndarray]:
    """One repetition's splits of Fig. 4's tasks (rows of ``texture``, (n,) labels; ``in_trained``, (n,) bool: the
    trial's profile is a trained one): ``(folds, train, held, untrained)``: the ``k`` stratified folds of the offline
    task (``rt_offline``), the trained-profile rows drawn for training (``train_fraction`` per texture), the
    trained-profile rows held out (``rt_trained``'s test) and the untrained-profile rows (``rt_untrained``'s test).
    :func:`run_realtime` and the exported splits (:func:`rigctl.analysis.splits.paper_splits`) draw with it."""
    folds = _stratified_folds(texture, k, int(rng.integers(2**31)))
    train = _stratified_fraction(np.flatnonzero(in_trained), texture, train_fraction, rng)
    held = np.setdiff1d(np.flatnonzero(in_trained), train)
    return folds, train, held, np.flatnonzero(~in_trained)


def _stratified_fraction(idx, labels, fraction, rng):
    """A random ``fraction`` of ``idx`` drawn within each label (at least one per label, at most all but one)."""
    out = []
    for lab in np.unique(labels[idx]):
        ix = idx[labels[idx] == lab]
        m = int(round(fraction * len(ix)))
        m = min(max(m, 1), max(len(ix) - 1, 1))
        out.append(rng.choice(ix, m, replace=False))
    return np.sort(np.concatenate(out))


def _calibration_draw(fs: FeatureSet, per_texture, rng):
    """Calibration trials of a new session: ``per_texture`` per texture spread evenly over its profiles."""
    out = []
    for tex in np.unique(fs.texture):
        ix = np.flatnonzero(fs.texture == tex)
        if fs.profile is not None:
            groups = [ix[fs.profile[ix] == p] for p in np.unique(fs.profile[ix])]
            per = max(1, per_texture // len(groups))
            chosen = np.concatenate([rng.permutation(g)[: min(per, len(g) - 1 if len(g) > 1 else 0)] for g in groups])
        else:
            chosen = rng.permutation(ix)[: min(per_texture, len(ix) - 1)]
        out.append(chosen.astype(np.int64))
    return np.sort(np.concatenate(out))
