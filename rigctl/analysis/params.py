"""Parameter objects of the analyses (:mod:`rigctl.analysis.tasks`), as :class:`rigctl.encoding.pipeline.EncodeParams`
is the encoder's: what a task repeats (:class:`Repetitions`), where the repetitions run (:class:`Execution`), and each
task's own settings (:class:`CVParams`, :class:`ExtrapolationParams`, :class:`RealtimeParams`).

Every ``run_*`` function takes them, and still accepts their fields as keywords (``run_cv(fs, repeats=5)`` is
``run_cv(fs, reps=Repetitions(repeats=5))``): :func:`resolve` routes each keyword to the object that has the field and
refuses one that none has (TypeError, as a misspelt keyword argument).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

__all__ = ["Repetitions", "Execution", "CVParams", "ExtrapolationParams", "RealtimeParams", "resolve"]


@dataclass(frozen=True)
class Repetitions:
    """What every analysis repeats.

    Attributes
    ----------
    n_pcs : largest PC count (nested PCs 1..n_pcs; the paper: 50)
    repeats : repetitions, each a new random draw (the paper: 20; Fig. 4: 100)
    seed : repetition ``r`` uses ``numpy.random.default_rng([seed, r])``: the same draws for every variant
    variants : feature variants (None: the task's default, all in the file)
    confusion_pcs : PC count of the confusion matrices (None: ``n_pcs``)
    """

    n_pcs: int = 50
    repeats: int = 20
    seed: int = 0
    variants: Sequence[str] | None = None
    confusion_pcs: int | None = None


@dataclass(frozen=True)
class Execution:
    """Where the repetitions run (:func:`rigctl.analysis.parallel.map_repeats`; the results do not depend on it):
    ``n_jobs`` at a time in this process (None: one per core), or on the Dask cluster at ``scheduler`` (an address,
    ``"local"`` with ``workers`` processes, or a client)."""

    n_jobs: int | None = None
    scheduler: Any = None
    workers: int | None = None


@dataclass(frozen=True)
class CVParams:
    """Texture / group classification with k-fold CV (Fig. 3A-B): ``per_texture`` trials drawn per texture (the
    paper: 500 of 1500; fewer with a warning when the data has fewer), ``k`` folds (the paper: 4), ``groups``: None
    (random stratified folds, the paper) or what a fold must not cut (:mod:`rigctl.analysis.grouping`:
    ``recording``, ``session``, ``block:N``; scikit-learn's StratifiedGroupKFold)."""

    per_texture: int = 500
    k: int = 4
    groups: str | None = None


@dataclass(frozen=True)
class ExtrapolationParams:
    """Extrapolation to untrained speed-force conditions (Fig. 3C-F).

    Attributes
    ----------
    train_speeds, train_forces : trained conditions, mm/s and g (the paper: 40, 60, 80 mm/s; 250, 500 g; None for
        forces: every force)
    test_speeds, test_forces : untrained conditions tested (None: all others)
    n_train, n_test : trials per texture and trained cell for training / testing (the paper: 75 + 25), and per
        untrained cell for testing (``n_test``)
    prefix : prepended to the task names (``"speed_"`` for the speed-only extrapolation)
    """

    train_speeds: Sequence[float] | None = (40, 60, 80)
    train_forces: Sequence[float] | None = (250, 500)
    test_speeds: Sequence[float] | None = None
    test_forces: Sequence[float] | None = None
    n_train: int = 75
    n_test: int = 25
    prefix: str = ""


@dataclass(frozen=True)
class RealtimeParams:
    """The real-time analyses of Fig. 4 (ramp-profile trials).

    Attributes
    ----------
    train_profiles : profiles trained in the extrapolation task (the paper: slow, medium)
    k : folds of the offline task (the paper: 4)
    train_fraction : fraction of the (trained-profile) trials drawn for training
    calibration_per_texture : trials per texture of a new session used for its mean-centering calibration
    headline_pcs : PC count of the confusion matrices (the paper's real-time classifier: 25)
    features : ``"windows"`` (the paper's: each train's windows) or ``"statistics"`` (each train's mean, spread and
        change over its windows: :func:`rigctl.encoding.alignment.window_statistics`, the live classifier's default)
    """

    train_profiles: Sequence[str] = ("slow", "medium")
    k: int = 4
    train_fraction: float = 0.75
    calibration_per_texture: int = 10
    headline_pcs: int = 25
    features: str = "windows"


T = TypeVar("T")


def resolve(overrides: dict[str, Any], *objects: Any) -> list[Any]:
    """``objects`` (parameter objects) with the fields in ``overrides`` replaced, each by the first object that has
    the field; returns them in order. Raises TypeError for a keyword no object has."""
    out = list(objects)
    left = dict(overrides)
    for i, obj in enumerate(out):
        names = {f.name for f in dataclasses.fields(obj)}
        mine = {k: left.pop(k) for k in list(left) if k in names}
        if mine:
            out[i] = dataclasses.replace(obj, **mine)
    if left:
        raise TypeError(f"unexpected keyword argument(s): {', '.join(sorted(left))}")
    return out
