"""The paper's analyses as an operator runs them, once for ``rigctl analyze`` and the GUI's analysis tab.

:class:`AnalysisPlan` says which analyses to run and with what (the parameter objects of
:mod:`rigctl.analysis.params`); :func:`run_analyses` runs them on a :class:`rigctl.analysis.data.FeatureSet`:
Table 1's tasks (textures, groups, extrapolation), the speed-only extrapolation and the real-time analyses, with or
without the per-trial baseline, and merges them into one :class:`rigctl.analysis.results.TaskResults`.
:func:`load_or_encode` reads an encoded file's features, encoding a session file first where asked;
:func:`train_model` fits the raw-trials-to-label pipeline on the session an encoded file came from and saves it;
:func:`force_leak_report` measures how much the paper's label-dependent force coefficients leak into its accuracy.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigctl.analysis.grouping import one_recording_per_texture
from rigctl.analysis.params import CVParams, Execution, ExtrapolationParams, RealtimeParams, Repetitions
from rigctl.core.progress import ProgressEvent

__all__ = ["AnalysisPlan", "ANALYSIS_TASKS", "BaselineError", "run_analyses", "load_or_encode", "encoded_path_for", "train_model",
           "TrainedModel", "force_leak_report"]

#: the analyses :func:`run_analyses` knows (``"all"``: the six rows of Table 1)
ANALYSIS_TASKS = ("textures", "groups", "extrapolation", "speed-extrapolation", "realtime")

Progress = Callable[[ProgressEvent], Any] | None


class BaselineError(ValueError):
    """The per-trial baseline cannot be removed from these features (the spike trains per trial do not fit)."""


@dataclass(frozen=True)
class AnalysisPlan:
    """Which analyses to run, and with what.

    Attributes
    ----------
    tasks : analyses of :data:`ANALYSIS_TASKS`, in order
    groups_optional : "groups" is skipped, with a warning, on data whose texture set defines no groups (a plan for
        "all" of Table 1); otherwise such data is an error
    reps : :class:`rigctl.analysis.params.Repetitions` (PCs, repetitions, seed, variants)
    cv, extrapolation, realtime : the tasks' own parameters; the speed-only extrapolation uses ``extrapolation``
        with every force trained unless given
    baseline : "keep" | "remove" | "both": the per-trial, per-spike-train level removed before PCA (tasks of the
        baseline-removed data are prefixed ``baseline_removed:``)
    channels : spike trains per trial for the baseline removal (None: from the file's sensor layout)
    new_session : a second session's features for the real-time analysis (mean-centering calibration)
    on_error : "raise" (a task the data cannot support is an error) or "skip" (it is skipped and the reason added
        to the results' warnings: the GUI)
    """

    tasks: tuple[str, ...] = ("textures", "groups", "extrapolation")
    groups_optional: bool = True
    reps: Repetitions = field(default_factory=Repetitions)
    cv: CVParams = field(default_factory=CVParams)
    extrapolation: ExtrapolationParams = field(default_factory=ExtrapolationParams)
    realtime: RealtimeParams = field(default_factory=RealtimeParams)
    baseline: str = "keep"
    channels: int | None = None
    new_session: Any = None
    on_error: str = "raise"

    def __post_init__(self) -> None:
        bad = [t for t in self.tasks if t not in ANALYSIS_TASKS]
        if bad:
            raise ValueError(f"unknown analysis {', '.join(bad)}; choose from {', '.join(ANALYSIS_TASKS)} or all")
        if self.baseline not in ("keep", "remove", "both"):
            raise ValueError(f"baseline must be keep, remove or both, not {self.baseline!r}")
        if self.on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be raise or skip, not {self.on_error!r}")

    @classmethod
    def for_task(cls, task: str, **kw: Any) -> "AnalysisPlan":
        """The plan of one ``rigctl analyze --task``: a name of :data:`ANALYSIS_TASKS`, or "all" (Table 1: textures,
        groups where the texture set defines them, extrapolation). ValueError for another name."""
        if task == "all":
            return cls(("textures", "groups", "extrapolation"), groups_optional=True, **kw)
        return cls((task,), groups_optional=False, **kw)


def run_analyses(fs: Any, plan: AnalysisPlan, *, progress: Progress = None,
                 execution: Execution | None = None) -> Any:
    """Run ``plan`` on the features ``fs`` (:class:`rigctl.analysis.data.FeatureSet`).

    Returns
    -------
    rigctl.analysis.results.TaskResults
        Every task's curves (keys prefixed ``baseline_removed:`` for the baseline-removed data), counts, settings
        and warnings (the library's warnings of the run are kept there, not shown).

    Raises
    ------
    ValueError / KeyError
        A task the data cannot support (``plan.on_error == "raise"``); :class:`BaselineError` (a ValueError): the
        baseline cannot be removed.
    """
    from rigctl.analysis import tasks

    runs = [("", fs)]
    if plan.baseline in ("remove", "both"):
        try:
            fs_b = fs.without_baseline(plan.channels)
        except ValueError as exc:
            raise BaselineError(str(exc)) from None
        runs = [("", fs), ("baseline_removed:", fs_b)] if plan.baseline == "both" else [("baseline_removed:", fs_b)]
    execution = execution or Execution()
    out = tasks.TaskResults()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # what matters is in the results' warnings
        for tag, data in runs:
            res = _run_tasks(data, plan, progress, execution)
            for t, by_v in res.curves.items():
                for c in by_v.values():
                    c.task = tag + t
                    out.add(c)
            out.counts.update({tag + k: v for k, v in res.counts.items()})
            out.warnings.extend(tag + w for w in res.warnings)
            out.settings.update(res.settings)
    return out


def _run_tasks(data: Any, plan: AnalysisPlan, progress: Progress, execution: Execution) -> Any:
    from rigctl.analysis import tasks

    res = tasks.TaskResults()
    cv_tasks = [t for t in plan.tasks if t in ("textures", "groups")]
    if "groups" in cv_tasks and plan.groups_optional and data.group is None:
        cv_tasks.remove("groups")
        name = data.textures.name
        res.warnings.append(f"groups task skipped: the texture set {name!r} defines no texture groups" if name
                            else "groups task skipped: the file's texture set defines no texture groups")
    steps: list[tuple[str, Callable[[], Any]]] = []
    if cv_tasks:
        steps.append(("/".join(cv_tasks), lambda: tasks.run_cv(data, tuple(cv_tasks), plan.cv, reps=plan.reps,
                                                               execution=execution, progress=progress)))
        if plan.cv.groups is None and one_recording_per_texture(data):
            spec = f"block:{max(plan.cv.k, 2)}"
            blocked = dataclasses.replace(plan.cv, groups=spec)
            res.warnings.append(
                f"every texture's trials come from one recording: random folds test how well a recording recognises "
                f"itself; the 'time blocks held out' rows keep each block of a recording on one side ({spec}; "
                "choose with --cv-groups block:N)")
            steps.append(("/".join(cv_tasks) + " " + spec, lambda: _renamed(tasks.run_cv(
                data, tuple(cv_tasks), blocked, reps=plan.reps, execution=execution, progress=progress))))
    if "extrapolation" in plan.tasks:
        steps.append(("extrapolation", lambda: tasks.run_extrapolation(
            data, plan.extrapolation, reps=plan.reps, execution=execution, progress=progress)))
    if "speed-extrapolation" in plan.tasks:
        speed = dataclasses.replace(plan.extrapolation, prefix="speed_")
        steps.append(("speed-extrapolation", lambda: tasks.run_extrapolation(
            data, speed, reps=plan.reps, execution=execution, progress=progress)))
    if "realtime" in plan.tasks:
        steps.append(("realtime", lambda: tasks.run_realtime(
            data, plan.realtime, new_session=plan.new_session, reps=plan.reps, progress=progress)))
    for name, step in steps:
        try:
            res.merge(step())
        except (ValueError, KeyError) as exc:
            if plan.on_error == "raise":
                raise
            res.warnings.append(f"{name} skipped: {exc}")
    res.warnings = list(dict.fromkeys(res.warnings))  # a blocked twin repeats its random run's warnings
    return res


#: appended to a task's name for its time-blocked twin (reported beside the random folds)
BLOCKED_SUFFIX = "_blocked"


def _renamed(res: Any) -> Any:
    """``res`` with every task renamed ``<task>_blocked`` (its curves and counts)."""
    from rigctl.analysis import tasks

    out = tasks.TaskResults()
    for t, by_v in res.curves.items():
        for c in by_v.values():
            c.task = t + BLOCKED_SUFFIX
            out.add(c)
    out.counts.update({k + BLOCKED_SUFFIX: v for k, v in res.counts.items()})
    out.warnings.extend(res.warnings)
    out.settings.update(res.settings)
    return out


def encoded_path_for(session_path: str | os.PathLike[str]) -> Path:
    """Where a session's encoded file goes beside it: ``<name>.encoded.h5``."""
    p = Path(session_path)
    return p.with_name(p.stem + ".encoded.h5")


def load_or_encode(path: str | os.PathLike[str], variants: Sequence[str] | None = None, *, task: str | None = "table1",
                   encode_to: str | os.PathLike[str] | None = None, progress: Progress = None,
                   overwrite: bool = False, keep_nonfinite: bool = False) -> tuple[Any, Path]:
    """The features of ``path`` (an encoded file): ``variants``, else ``task``'s default variants
    (:func:`rigctl.analysis.data.default_variants`; ``task=None``: every variant in the file). A session file is
    encoded first into ``encode_to`` (None: it is an error, :class:`rigctl.analysis.data.NotEncodedError`; an
    existing ``encode_to`` is replaced only with ``overwrite``, never while another writer holds it;
    ``keep_nonfinite``: see :func:`rigctl.encoding.pipeline.encode_session`).

    Returns ``(FeatureSet, the encoded file's path)``. Raises NotEncodedError, ValueError / KeyError (variants),
    OSError."""
    from rigctl.analysis.data import NotEncodedError, default_variants, list_variants, load_features
    from rigctl.encoding.pipeline import encode_session

    path = Path(path)
    try:
        have = list_variants(path)
        return load_features(path, variants or (default_variants(have, task) if have and task else None)), path
    except NotEncodedError:
        if encode_to is None:
            raise
    out = Path(encode_to)
    # the output policy: replaced only if asked
    encode_session(path, out, progress=progress, overwrite=overwrite, keep_nonfinite=keep_nonfinite)
    return load_features(out, variants or (default_variants(list_variants(out), task) if task else None)), out


@dataclass(frozen=True)
class TrainedModel:
    """What :func:`train_model` fitted: the fitted pipeline, its variant, the PCs it kept, the trials it saw."""

    model: Any
    variant: str
    n_pcs: int
    n_trials: int
    info: dict[str, Any]


def train_model(encoded_path: str | os.PathLike[str], variant: str = "speed_scaled", n_pcs: int = 25, *,
                max_pcs: int | None = None) -> TrainedModel:
    """Fit the raw-trials-to-label pipeline (:func:`rigctl.analysis.model.texture_pipeline`: normalise, [force,]
    encode, features, PCA + LDA) on every trial of the session the encoded file was made from, encoding as the file
    did (its parameters). Save it with :func:`rigctl.storage.model_file.save_model` (``model``, ``info=info``).

    Raises FileNotFoundError (the source session is gone), ValueError (unknown variant, too few trials)."""
    from rigctl.analysis.model import model_info, session_of, texture_pipeline, trials_of_session

    session, params = session_of(encoded_path)
    trials, texture = trials_of_session(session)
    model = texture_pipeline(variant, n_pcs, max_pcs=max_pcs, params=params).fit(trials, texture)
    return TrainedModel(model, variant, int(model[-1].n_pcs_), len(trials),
                        model_info(model, session=session, analysed=str(encoded_path)))


def force_leak_report(source: str | os.PathLike[str], variant: str, *, n_pcs: int, repeats: int,
                      seed: int = 0) -> dict[str, Any]:
    """A force-scaled ``variant``'s accuracy with its label-dependent force coefficients (eq. 1) fitted on all trials
    (the paper; test labels leak in) and within each CV fold, on the raw trials of ``source`` (a session file, or
    an encoded file whose session is found; encoded as that file was): :func:`rigctl.analysis.model.force_leak`'s
    dict (``fitted_on_all``, ``per_fold``, ``leak``: fractions; ``variant``, ``n_pcs``, ``folds``, ``repeats``).

    Raises FileNotFoundError (the encoded file's session is gone), ValueError/KeyError (not a force-scaled variant,
    too few trials)."""
    from rigctl.analysis.model import force_leak, session_of, trials_of_session

    session, params = session_of(source)
    trials, texture = trials_of_session(session)
    return dict(force_leak(trials, texture, variant=variant, n_pcs=n_pcs, repeats=repeats, seed=seed,
                           params=params))
