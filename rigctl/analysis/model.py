"""The raw-trials-to-label model: one scikit-learn :class:`~sklearn.pipeline.Pipeline` of the encoding steps
(:mod:`rigctl.encoding.estimators`) and the PCA + LDA classifier (:class:`rigctl.analysis.classify.TextureClassifier`).

``rigctl analyze --save-model`` fits it on a session's trials and writes it (:mod:`rigctl.storage.model_file`); the
GUI's real-time view loads the file and calls ``predict`` on each new trial: the file alone classifies, with the
normalisation, encoding parameters and classifier it was trained with.

:func:`force_leak` measures what fitting the per-texture force coefficients on all trials (as the paper did: they
use the very label the classifier predicts) adds to the accuracy, against fitting them within each CV fold.
"""

from __future__ import annotations

import numpy as np
from sklearn.model_selection import StratifiedKFold
from sklearn.pipeline import Pipeline

from rigctl.analysis.classify import TextureClassifier
from rigctl.encoding.estimators import FeatureExtractor, ForceScaler, SpikeEncoder, TaxelNormaliser

__all__ = ["texture_pipeline", "model_info", "trials_of_session", "session_of", "force_leak"]


def texture_pipeline(variant: str = "speed_scaled", n_pcs: int = 25, *, max_pcs: int | None = None, params=None,
                     random_state: int = 0) -> Pipeline:
    """``normalise -> [force] -> encode -> features -> classify`` for one feature variant.

    Parameters
    ----------
    variant : a name of :data:`rigctl.storage.encoded.VARIANTS`; force-scaled variants get a
        :class:`~rigctl.encoding.estimators.ForceScaler` step (label-free for the ``*_label_free`` ones, per texture
        otherwise: that one uses the labels the trials carry at predict time too, as the paper did).
    n_pcs, max_pcs, random_state : :class:`TextureClassifier`'s (``max_pcs`` default ``n_pcs``).
    params : dict or EncodeParams (e.g. an encoded file's ``parameters``): windows and model constants.

    Raises
    ------
    ValueError
        Unknown variant.
    """
    from rigctl.storage.encoded import ALL_VARIANTS, VARIANTS

    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose from {', '.join(ALL_VARIANTS)}")
    info = VARIANTS[variant]
    steps = [("normalise", TaxelNormaliser())]
    if info.force_scaled:
        steps.append(("force", ForceScaler(label_free=bool(info.label_free))))
    steps += [("encode", SpikeEncoder(params)), ("features", FeatureExtractor(variant, params)),
              ("classify", TextureClassifier(variant, n_pcs=n_pcs, max_pcs=max_pcs or n_pcs,
                                             random_state=random_state))]
    return Pipeline(steps)


def model_info(model: Pipeline, *, session, analysed) -> dict:
    """What a model file records about a fitted :func:`texture_pipeline` (JSON-able): variant, PCs used, textures,
    the session it was fitted on (absolute path) and the file analysed."""
    from pathlib import Path

    clf = model[-1]
    return {"variant": clf.variant, "n_pcs": int(clf.n_pcs_), "textures": [str(c) for c in clf.classes_],
            "session": str(Path(session).resolve()), "analysed": str(analysed)}


def session_of(path):
    """The session whose raw trials a model starts from, and the encoding parameters to use: ``(session_path,
    parameters dict)`` for an encoded file (its ``source_session``, else a file of that name beside it), ``(path,
    None)`` for a session file.

    Raises
    ------
    FileNotFoundError
        The encoded file's session is not found.
    """
    from pathlib import Path

    from rigctl.storage.encoded import NotEncodedError, open_encoded

    try:
        with open_encoded(path) as f:
            session, params = f.attrs.get("source_session"), dict(f.parameters)
    except NotEncodedError:
        return Path(path), None
    candidates = [Path(session), Path(path).parent / Path(session).name] if session else []
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise FileNotFoundError(f"{path} was encoded from {session or 'an unknown session'}, which is not found: "
                                "a model starts from the raw trials; give the session file")
    return found, params


def trials_of_session(path, trial_ids=None):
    """The complete trials of a session file as pipeline input: ``(trials, texture)``, a list of
    :class:`rigctl.core.trial.TrialData` (attrs with speed, force and texture) and ``(n,)`` str labels."""
    from rigctl.storage.session import open_session
    from rigctl.storage.validate import usable_trials

    with open_session(path) as s:
        report = usable_trials(s)  # the one trial validator: damaged trials excluded as everywhere else
        ids = report.ids if trial_ids is None else [int(t) for t in trial_ids if int(t) not in report.excluded]
        trials = [s.trial(t) for t in ids]
    return trials, np.array([str(t.attrs["texture"]) for t in trials])


def force_leak(trials, texture, *, variant: str = "speed_force_scaled", n_pcs: int = 10, k: int = 4,
               repeats: int = 1, seed: int = 0, params=None) -> dict:
    """Accuracy of a force-scaled variant with the force coefficients fitted on all trials (the paper's way: the
    test trials' labels shape their own coefficients) and fitted on each training fold only (no leak).

    Both use the same folds and, per fold, the same normalisation (fitted on the training fold), encoder and
    classifier (fitted on the training fold): the difference is the leak of the label-dependent step alone.
    Per-texture coefficients are applied with the labels the test trials carry in both cases (the variant's
    definition); per fold, they were found without the test trials.

    Parameters
    ----------
    trials, texture : raw trials (list of TrialData) and their labels (:func:`trials_of_session`).
    variant : a force-scaled variant. n_pcs : PCs of the classifier. k : folds. repeats : new folds per repeat.
    params : dict or EncodeParams (windows, constants).

    Returns
    -------
    dict: ``variant``, ``n_pcs``, ``folds``, ``repeats``, ``fitted_on_all`` and ``per_fold`` (mean accuracy,
    fraction correct), ``leak`` (their difference), ``per_repeat`` (list of [all, per fold] pairs).

    Raises
    ------
    ValueError
        A variant without a force step; a fold without 500 g reference trials for some (texture, speed).
    """
    from sklearn.base import clone

    from rigctl.encoding.batch import as_trial_batch

    texture = np.asarray(texture).astype(str)
    batch = as_trial_batch(trials)
    pipe = texture_pipeline(variant, n_pcs, params=params)
    if "force" not in pipe.named_steps:
        raise ValueError(f"{variant} has no force-scaling step: nothing label-dependent to compare")
    pairs = []
    for r in range(repeats):
        folds = StratifiedKFold(k, shuffle=True, random_state=seed + r).split(np.zeros(len(texture)), texture)
        correct = np.zeros(2)
        for tr, te in folds:
            train, test = _subset(batch, tr), _subset(batch, te)
            norm = TaxelNormaliser().fit(train)
            fitted_on = ((norm.transform(batch), texture), (norm.transform(train), texture[tr]))  # all, fold
            for j, (x_fit, y_fit) in enumerate(fitted_on):
                force = clone(pipe.named_steps["force"]).fit(x_fit, y_fit)
                rest = Pipeline([(name, clone(step)) for name, step in pipe.steps[2:]])
                rest.fit(force.transform(norm.transform(train)), texture[tr])
                correct[j] += np.sum(rest.predict(force.transform(norm.transform(test))) == texture[te])
        pairs.append([float(c) for c in correct / len(texture)])
    acc = np.mean(pairs, axis=0)
    return {"variant": variant, "n_pcs": n_pcs, "folds": k, "repeats": repeats, "fitted_on_all": float(acc[0]),
            "per_fold": float(acc[1]), "leak": float(acc[0] - acc[1]), "per_repeat": pairs}


def _subset(batch, idx):
    """The trials ``idx`` of a TrialBatch."""
    import dataclasses

    from rigctl.encoding.izhikevich import as_ragged

    idx = np.asarray(idx)
    return dataclasses.replace(batch, readings=as_ragged([batch.readings.trial(int(i)) for i in idx]),
                               speed_mm_s=batch.speed_mm_s[idx], force_g=batch.force_g[idx],
                               texture=None if batch.texture is None else batch.texture[idx])
