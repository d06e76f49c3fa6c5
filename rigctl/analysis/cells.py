"""The speed-force cells of the extrapolation task (Fig. 3C-F) and their draws: which cells are trained, how many
trials each gives to training and test, and, for a design of one trial per cell, the whole cells held out
(:func:`rigctl.analysis.tasks.run_extrapolation` runs the task; :mod:`rigctl.analysis.splits` exports the same draws).
NumPy only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rigctl.analysis.data import FeatureSet

__all__ = ["EXTRAPOLATION_CELLS", "extrapolation_split"]


#: extrapolation test cells: (speed trained?, force trained?) -> task key
EXTRAPOLATION_CELLS = {
    (False, False): "untrained_speed_force",
    (True, False): "untrained_force",
    (False, True): "untrained_speed",
    (True, True): "trained",
}


def _cells(fs: FeatureSet):
    return np.round(np.abs(fs.speed_mm_s), 6), np.round(fs.force_g, 6)


def _isin(values, wanted):
    """``np.isin`` where a NaN label (no speed or no force recorded, e.g. imported recordings) matches a NaN."""
    wanted = np.asarray(wanted, float)
    return np.isin(values, wanted) | (np.isnan(values) & bool(np.isnan(wanted).any()))


def _some(names, k: int = 3) -> str:
    """The first ``k`` names, and how many more."""
    names = list(names)
    return ", ".join(names[:k]) + (f" (+{len(names) - k} more)" if len(names) > k else "")


def _fmt_values(values) -> str:
    return ", ".join("none" if np.isnan(v) else f"{float(v):g}" for v in np.asarray(values, float)) or "none"


def _cell_text(cell: str) -> str:
    """``"Board10mm|100.0|120.0"`` -> ``"Board10mm at 100 mm/s, 120 g"``."""
    texture, speed, force = cell.rsplit("|", 2)
    return f"{texture} at {_fmt_values([float(speed)])} mm/s, {_fmt_values([float(force)])} g"


def _extrapolation_plan(fs, train_speeds, train_forces, test_speeds, test_forces, n_train, n_test):
    """Cells (texture|speed|force -> trial indices), trained cells, cell category, and the counts to draw."""
    spd, frc = _cells(fs)
    tr_s = np.unique(spd) if train_speeds is None else np.round(np.abs(np.asarray(train_speeds, float)), 6)
    tr_f = np.unique(frc) if train_forces is None else np.round(np.asarray(train_forces, float), 6)
    s_in = _isin(spd, tr_s)
    f_in = _isin(frc, tr_f)
    keep = np.ones(fs.n_trials, bool)
    if test_speeds is not None:
        keep &= _isin(spd, np.round(np.abs(np.asarray(test_speeds, float)), 6)) | s_in
    if test_forces is not None:
        keep &= _isin(frc, np.round(np.asarray(test_forces, float), 6)) | f_in
    trained = s_in & f_in
    if not trained.any():
        raise ValueError(f"no trials at the trained speeds {_fmt_values(tr_s)} mm/s and forces "
                         f"{_fmt_values(tr_f)} g (the file has speeds {_fmt_values(np.unique(spd))} mm/s, forces "
                         f"{_fmt_values(np.unique(frc))} g)")
    cell_key = np.char.add(np.char.add(fs.texture.astype(str), "|"),
                           np.char.add(spd.astype(str), np.char.add("|", frc.astype(str))))
    cells = {}
    for i in np.flatnonzero(keep):
        cells.setdefault(cell_key[i], []).append(i)
    cells = {c: np.asarray(ix) for c, ix in cells.items()}
    trained_cells = [c for c, ix in cells.items() if trained[ix[0]]]
    test_cells = [c for c, ix in cells.items() if not trained[ix[0]]]
    min_tr = min(len(cells[c]) for c in trained_cells)
    a_tr, a_te, hold = n_train, n_test, 0
    if min_tr < n_train + n_test:
        a_te = max(1, int(round(min_tr * n_test / (n_train + n_test))))
        a_tr = min_tr - a_te
        if a_tr < 1:  # a cell of one trial cannot be split: whole trained cells are held out instead
            hold = _held_out_cells(cells, trained_cells, min_tr, n_train, n_test)
            a_tr, a_te = min_tr, min_tr
    min_te = min((len(cells[c]) for c in test_cells), default=a_te)
    u_te = min(a_te, min_te)
    cat_of = {cell: EXTRAPOLATION_CELLS[(bool(s_in[ix[0]]), bool(f_in[ix[0]]))] for cell, ix in cells.items()}
    smallest_tr = sorted(_cell_text(c) for c in trained_cells if len(cells[c]) == min_tr)
    smallest_te = sorted(_cell_text(c) for c in test_cells if len(cells[c]) == min_te)
    info = {"min_trained": min_tr, "min_untrained": min_te, "trained_speeds": [float(x) for x in tr_s],
            "smallest_trained": smallest_tr, "smallest_untrained": smallest_te,
            "trained_forces": [float(x) for x in tr_f], "held_out_cells": hold,
            "trained_cells_per_texture": min(len(v) for v in _by_texture(trained_cells).values())}
    return cells, trained_cells, cat_of, (a_tr, a_te, u_te), info


def _by_texture(cell_names) -> dict[str, list[str]]:
    """Cell names (``texture|speed|force``) by texture, each list sorted."""
    out: dict[str, list[str]] = {}
    for c in sorted(cell_names):
        out.setdefault(c.rsplit("|", 2)[0], []).append(c)
    return out


def _held_out_cells(cells, trained_cells, min_tr, n_train, n_test) -> int:
    """How many whole trained cells per texture a repetition holds out for test when a trained cell holds too few
    trials to split (a design of one trial per cell): the paper's test share (``n_test / (n_train + n_test)``) of the
    fewest trained cells a texture has, at least one, leaving at least one to train on. ValueError when a texture has
    a single trained cell."""
    per_texture = _by_texture(trained_cells)
    fewest = min(len(v) for v in per_texture.values())
    if fewest < 2:
        texture = next(t for t, v in per_texture.items() if len(v) == fewest)
        short = sorted(c for c in trained_cells if len(cells[c]) == min_tr)
        raise ValueError(f"the trained cell {_cell_text(short[0])} has only {min_tr} trials"
                         f"{f' (and {len(short) - 1} more cells)' if len(short) > 1 else ''} and {texture} has one "
                         "trained cell: cannot split into train and test, by trials or by whole cells (leave its "
                         "texture out with --textures, or train other speeds/forces)")
    return int(min(fewest - 1, max(1, round(fewest * n_test / (n_train + n_test)))))


def _extrapolation_draw(cells, trained_cells, cat_of, n_train, n_test, n_untrained, rng, hold_cells=0):
    """Per cell: ``n_train`` + ``n_test`` from trained cells, ``n_untrained`` test trials from the others. With
    ``hold_cells`` (a design of one trial per cell, :func:`_held_out_cells`): per texture, that many whole trained
    cells drawn at random are test cells (``n_test`` of their trials), the others train (``n_train`` of theirs)."""
    held = set()
    if hold_cells:
        for names in _by_texture(trained_cells).values():
            held.update(names[i] for i in rng.permutation(len(names))[:hold_cells])
    trained_cells = set(trained_cells)
    train_idx, test_idx, test_cat = [], [], []
    for cell in sorted(cells):
        perm = rng.permutation(cells[cell])
        if cell in held:
            chosen = perm[:n_test]
        elif cell in trained_cells:
            train_idx.append(perm[:n_train])
            chosen = perm[n_train : n_train + n_test] if not hold_cells else perm[:0]
        else:
            chosen = perm[:n_untrained]
        test_idx.append(chosen)
        test_cat += [cat_of[cell]] * len(chosen)
    return np.concatenate(train_idx), np.concatenate(test_idx), np.asarray(test_cat)


def extrapolation_split(fs: FeatureSet, *, train_speeds=(40, 60, 80), train_forces=(250, 500), n_train=75,
                        n_test=25, seed=0, repeat=0):
    """One repetition's split of the extrapolation task, as :func:`run_extrapolation` draws it.

    Returns
    -------
    train_idx : ndarray int
    test_idx : ndarray int
    test_cell : ndarray str
        Per test trial: ``untrained_speed_force``, ``untrained_force``, ``untrained_speed`` or ``trained``.
    """
    cells, trained_cells, cat_of, (a_tr, a_te, u_te), info = _extrapolation_plan(
        fs, train_speeds, train_forces, None, None, n_train, n_test)
    return _extrapolation_draw(cells, trained_cells, cat_of, a_tr, a_te, u_te,
                               np.random.default_rng([seed, 10_000 + repeat]), info["held_out_cells"])
