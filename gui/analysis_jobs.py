"""What the analysis tab runs in its worker process (:class:`rigctl_gui.workers.ProcessJob`): plain calls into
:mod:`rigctl.encoding.pipeline` and :mod:`rigctl.analysis`, in the order ``rigctl encode`` / ``rigctl analyze``
use them. No Qt here (the child process never imports it)."""

from __future__ import annotations

import warnings
from pathlib import Path


def encode(session_path: str, out_path: str, progress=None) -> str:
    """Encode a session file into an encoded file (:func:`rigctl.encoding.pipeline.encode_session`); ``progress``
    receives its :class:`rigctl.core.progress.ProgressEvent` s."""
    from rigctl.encoding.pipeline import encode_session

    return str(encode_session(session_path, out_path, progress=progress))


def encoded_path_for(session_path: str) -> str:
    """Where the tab writes the encoded file of a session: ``<name>.encoded.h5`` beside it."""
    p = Path(session_path)
    return str(p.with_name(p.stem + ".encoded.h5"))


def analyse(path: str, *, cv: bool = True, extrapolation: bool = True, repeats: int = 5, n_pcs: int = 50,
            per_texture: int = 500, seed: int = 0, variants=None, progress=None):
    """The paper's analyses on an encoded file (a session file is encoded first, beside it).

    ``progress`` receives the :class:`rigctl.core.progress.ProgressEvent` s of the encoding and the analyses.
    Returns ``(TaskResults, encoded_path)``. Tasks the data cannot support (e.g. extrapolation without the
    trained speeds/forces) are skipped and the reason is added to ``TaskResults.warnings``.
    """
    from rigctl.analysis import tasks
    from rigctl.analysis.data import NotEncodedError, load_features

    try:
        fs = load_features(path, variants)
    except NotEncodedError:
        path = encode(path, encoded_path_for(path), progress)
        fs = load_features(path, variants)
    res = tasks.TaskResults()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # they are kept in res.warnings
        if cv:
            wanted = ("textures", "groups") if fs.group is not None else ("textures",)
            if fs.group is None:
                res.warnings.append(f"groups skipped: the texture set {fs.textures.name or ''!r} defines no texture "
                                    "groups")
            try:
                res.merge(tasks.run_cv(fs, wanted, variants=variants, n_pcs=n_pcs, repeats=repeats,
                                       per_texture=per_texture, seed=seed, progress=progress))
            except (ValueError, KeyError) as exc:
                res.warnings.append(f"textures/groups skipped: {exc}")
        if extrapolation:
            try:
                res.merge(tasks.run_extrapolation(fs, variants=variants, n_pcs=n_pcs, repeats=repeats, seed=seed,
                                                  progress=progress))
            except (ValueError, KeyError) as exc:
                res.warnings.append(f"extrapolation skipped: {exc}")
    return res, str(path)


def model_path_for(encoded_path: str, variant: str) -> str:
    """Where the tab saves the model it trains: ``<name>.<variant>.skops`` beside the encoded file."""
    p = Path(encoded_path)
    return str(p.with_name(f"{p.name.removesuffix('.h5').removesuffix('.encoded')}.{variant}.skops"))


def train_classifier(path: str, variant: str = "speed_scaled", n_pcs: int = 25, out_path: str | None = None) -> str:
    """Fit the raw-trials-to-label pipeline (:func:`rigctl.analysis.model.texture_pipeline`: normalise, encode,
    features, PCA + LDA) on every trial of the session an encoded file was made from, encoding as the file did
    (its parameters), and save it as a model file (:func:`rigctl.storage.model_file.save_model`, the format of
    ``rigctl analyze --save-model``). Returns the model file's path (default :func:`model_path_for`)."""
    from rigctl.analysis.model import model_info, session_of, texture_pipeline, trials_of_session
    from rigctl.storage.model_file import save_model

    session, params = session_of(path)
    trials, texture = trials_of_session(session)
    model = texture_pipeline(variant, n_pcs, params=params).fit(trials, texture)
    out = out_path or model_path_for(path, variant)
    save_model(model, out, info=model_info(model, session=session, analysed=path))
    return out
