"""The paper's train/test splits as trial ids, for a network trained outside rigctl (``rigctl export ... --splits``).

The splits are drawn exactly as the analyses draw them (:func:`rigctl.analysis.tasks.cv_split`,
:func:`rigctl.analysis.tasks.extrapolation_split`'s plan and draw), one repetition each, from the trial labels alone,
so that a spiking network trained elsewhere is scored on the paper's hold-outs (Methods, "Tactile Texture Dataset -
Statistical Analysis"):

* ``cv``: individual textures, random k-fold cross-validation (the paper: 500 trials drawn per texture, 4 folds);
* ``untrained_speed``, ``untrained_force``, ``untrained_speed_force``: the extrapolation task (train on speeds
  40/60/80 mm/s x forces 250/500 g: per texture and trained cell 75 trials train and 25 test; 25 test trials per
  texture from every untrained cell), one split whose test trials are divided by the cell they come from;
  ``trained`` holds the held-out trials of the trained cells;
* a velocity-profile session (its trials carry profile names: ``realtime_profiles``, the handheld blocks): Fig. 4's
  tasks as ``rigctl analyze --task realtime`` draws them (``rt_offline``: k-fold CV over every trial;
  ``rt_trained`` / ``rt_untrained``: train on a fraction of the trained profiles' trials, test on the rest of them /
  on the untrained profiles' trials), and no speed or force extrapolation: a ramp's speed label is its mean, so its
  "speed cell" is not the paper's.

Each task is ``{"folds": [{"train": [trial ids], "test": [trial ids]}, ...]}`` (the extrapolation tasks: one fold,
the same training trials). The file format is :mod:`rigctl.storage.splits_file`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rigctl.analysis.params import RealtimeParams
from rigctl.analysis.tasks import (
    EXTRAPOLATION_CELLS,
    _extrapolation_draw,
    _extrapolation_plan,
    cv_draw_counts,
    cv_split,
    realtime_draw,
    realtime_rng,
)
from rigctl.core.trial import CONSTANT_PROFILES, has_profiles

__all__ = ["PAPER_TRAIN_SPEEDS_MM_S", "PAPER_TRAIN_FORCES_G", "CONSTANT_PROFILES", "paper_splits",
           "has_profiles"]


#: the extrapolation task's trained speeds (mm/s) and forces (g), Methods
PAPER_TRAIN_SPEEDS_MM_S = (40.0, 60.0, 80.0)
PAPER_TRAIN_FORCES_G = (250.0, 500.0)


@dataclass(frozen=True)
class _Labels:
    """The labels the extrapolation plan reads (a :class:`~rigctl.analysis.data.FeatureSet`'s, without features)."""

    texture: np.ndarray
    speed_mm_s: np.ndarray
    force_g: np.ndarray

    @property
    def n_trials(self) -> int:
        return int(self.texture.shape[0])


def _ids(trial_id: np.ndarray, rows: np.ndarray) -> list[int]:
    return sorted(int(x) for x in trial_id[np.asarray(rows, np.int64)])


def paper_splits(texture: Sequence[str] | np.ndarray, speed_mm_s: Sequence[float] | np.ndarray,
                 force_g: Sequence[float] | np.ndarray, trial_id: Sequence[int] | np.ndarray, *, seed: int = 0,
                 per_texture: int = 500, k: int = 4,
                 train_speeds_mm_s: Sequence[float] = PAPER_TRAIN_SPEEDS_MM_S,
                 train_forces_g: Sequence[float] = PAPER_TRAIN_FORCES_G, n_train: int = 75,
                 n_test: int = 25, profile: Sequence[str] | np.ndarray | None = None,
                 realtime: RealtimeParams | None = None) -> dict[str, object]:
    """The paper's tasks as lists of trial ids (one repetition, ``seed``; the analyses' repetition 0).

    Parameters
    ----------
    texture, speed_mm_s, force_g, trial_id : (n_trials,) arrays
        Labels (speed in mm/s, force in g; NaN when unknown) and the ids the splits are given in.
    seed : int
        The draws' seed (``rigctl analyze --seed``: the same seed gives the same split as the analysis' first
        repetition).
    per_texture, k : the CV draw (reduced to the smallest texture's count, as :func:`run_cv` does).
    train_speeds_mm_s, train_forces_g, n_train, n_test : the extrapolation task (the paper's by default).
    profile : (n_trials,) velocity-profile names, or None: with any profile (:func:`has_profiles`), Fig. 4's tasks
        ``rt_offline``, ``rt_trained``, ``rt_untrained`` (``realtime``: trained profiles, folds, train fraction;
        :class:`~rigctl.analysis.params.RealtimeParams`' defaults) in place of the extrapolation tasks.

    Returns
    -------
    dict
        ``{"seed", "tasks": {name: {"folds": [{"train": [...], "test": [...]}], ...}}, "counts", "notes"}``: every
        task the labels allow; a task they do not allow (no speeds, too few trials) is left out and named in
        ``notes`` with why.

    Raises
    ------
    ValueError
        Arrays of different lengths, a trial id listed twice.
    """
    tex = np.asarray(texture).astype(str)
    spd = np.asarray(speed_mm_s, np.float64)
    frc = np.asarray(force_g, np.float64)
    ids = np.asarray(trial_id, np.int64)
    if not (tex.shape == spd.shape == frc.shape == ids.shape) or tex.ndim != 1:
        raise ValueError(f"labels of unequal shapes: texture {tex.shape}, speed {spd.shape}, force {frc.shape}, "
                         f"trial_id {ids.shape}")
    if np.unique(ids).size != ids.size:
        raise ValueError("a trial id is listed twice")
    tasks: dict[str, object] = {}
    counts: dict[str, object] = {}
    notes: list[str] = []
    names, per = np.unique(tex, return_counts=True)
    drawn = cv_draw_counts(per, per_texture)
    n_draw = int(drawn.min()) if per.size else 0
    if n_draw >= k:  # as run_cv draws: every trial up to per_texture (unequal counts: weighted there, said here)
        idx, folds = cv_split(tex, n_draw if drawn.max() == n_draw else drawn, k, seed=seed, repeat=0)
        tasks["cv"] = {"folds": [{"train": _ids(ids, idx[tr]), "test": _ids(ids, idx[te])} for tr, te in folds],
                       "k": k}
        counts["cv"] = {"per_texture": n_draw, "k": k, "weighting": "none" if drawn.max() == n_draw else "balanced",
                        "drawn_per_texture": {str(t): int(d) for t, d in zip(names, drawn, strict=True)}}
    else:
        notes.append(f"cv: the smallest texture has {int(per.min()) if per.size else 0} trials, fewer than k={k}")
    if has_profiles(profile):
        _realtime_tasks(tex, np.asarray(profile).astype(str), ids, seed, realtime or RealtimeParams(), tasks, counts,
                        notes)
        return {"seed": int(seed), "tasks": tasks, "counts": counts, "notes": notes}
    try:
        cells, trained_cells, cat_of, (a_tr, a_te, u_te), info = _extrapolation_plan(
            _Labels(tex, spd, frc), train_speeds_mm_s, train_forces_g, None, None, n_train, n_test)
    except ValueError as exc:
        notes.append(f"extrapolation: {exc}")
    else:
        train_idx, test_idx, test_cat = _extrapolation_draw(cells, trained_cells, cat_of, a_tr, a_te, u_te,
                                                            np.random.default_rng([seed, 10_000]),
                                                            info["held_out_cells"])
        train = _ids(ids, train_idx)
        for cat in EXTRAPOLATION_CELLS.values():
            m = test_cat == cat
            if m.any():
                tasks[cat] = {"folds": [{"train": train, "test": _ids(ids, test_idx[m])}]}
            else:
                notes.append(f"{cat}: no test trials in these labels")
        counts["extrapolation"] = {"train_per_cell": a_tr, "test_per_trained_cell": a_te,
                                   "test_per_untrained_cell": u_te, "trained_speeds_mm_s": info["trained_speeds"],
                                   "trained_forces_g": info["trained_forces"],
                                   "held_out_cells_per_texture": info["held_out_cells"]}
    return {"seed": int(seed), "tasks": tasks, "counts": counts, "notes": notes}


def _realtime_tasks(tex: np.ndarray, profile: np.ndarray, ids: np.ndarray, seed: int, params: RealtimeParams,
                    tasks: dict[str, object], counts: dict[str, object], notes: list[str]) -> None:
    """Fig. 4's tasks of a velocity-profile session into ``tasks`` (:func:`realtime_draw`, repetition 0 of ``rigctl
    analyze --task realtime --seed``)."""
    if profile.shape != tex.shape:
        raise ValueError(f"labels of unequal shapes: texture {tex.shape}, profile {profile.shape}")
    present = set(profile.tolist())
    trained = [p for p in params.train_profiles if p in present]
    notes.append("a velocity-profile session: Fig. 4's tasks (rt_*, as analyze --task realtime draws them); no speed "
                 "or force extrapolation (a ramp's speed label is its mean speed, not a speed cell)")
    if not trained:
        notes.append(f"rt_trained, rt_untrained: none of the trained profiles {', '.join(params.train_profiles)} "
                     f"in the data (has {', '.join(sorted(present))})")
    in_tr = np.isin(profile, trained)
    _, per = np.unique(tex, return_counts=True)
    if per.size and per.min() < params.k:
        notes.append(f"rt_offline: the smallest texture has {int(per.min())} trials, fewer than k={params.k}")
        return
    folds, train, held, untrained = realtime_draw(tex, in_tr, params.k, params.train_fraction,
                                                  realtime_rng(seed, 0))
    tasks["rt_offline"] = {"folds": [{"train": _ids(ids, tr), "test": _ids(ids, te)} for tr, te in folds],
                           "k": params.k}
    if trained:
        for name, test in (("rt_trained", held), ("rt_untrained", untrained)):
            if test.size:
                tasks[name] = {"folds": [{"train": _ids(ids, train), "test": _ids(ids, test)}]}
            else:
                notes.append(f"{name}: no test trials in these labels")
    counts["realtime"] = {"trained_profiles": trained, "profiles": sorted(present), "k": params.k,
                          "train_fraction": params.train_fraction,
                          "trials_by_profile": {p: int(np.sum(profile == p)) for p in sorted(present)}}
