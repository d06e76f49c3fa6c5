"""What the analysis tab runs in its worker process (:class:`rigctl_gui.workers.ProcessJob`): calls into the
operator layer (:mod:`rigctl.operations`: the analyses as ``rigctl analyze`` runs them, the model it saves) and
:mod:`rigctl.encoding.pipeline`. No Qt here (the child process never imports it)."""

from __future__ import annotations

from pathlib import Path


def encode(session_path: str, out_path: str, progress=None) -> str:
    """Encode a session file into an encoded file (:func:`rigctl.encoding.pipeline.encode_session`); ``progress``
    receives its :class:`rigctl.core.progress.ProgressEvent` s. The tab's own ``<name>.encoded.h5`` is replaced
    (the Encode button asks for it), under the library's output policy: refused while another writer holds it, never
    the session itself, a full disk one line with nothing left behind."""
    from rigctl.encoding.pipeline import encode_session

    return str(encode_session(session_path, out_path, progress=progress, overwrite=True))


def encoded_path_for(session_path: str) -> str:
    """Where the tab writes the encoded file of a session: ``<name>.encoded.h5`` beside it
    (:func:`rigctl.operations.encoded_path_for`)."""
    from rigctl.operations import encoded_path_for as beside

    return str(beside(session_path))


def analyse(path: str, *, cv: bool = True, extrapolation: bool = True, repeats: int = 5, n_pcs: int = 50,
            per_texture: int = 500, seed: int = 0, variants=None, progress=None, cv_groups: str | None = None):
    """The paper's analyses on an encoded file (a session file is encoded first, beside it): the operator layer's
    :func:`rigctl.operations.run_analyses`, as ``rigctl analyze`` runs them, skipping what the data cannot support.

    ``cv_groups``: how the textures/groups folds split the trials (``rigctl analyze --cv-groups``: None for random
    trials, ``recording``, ``session``, ``block:N``; ValueError from :func:`rigctl.analysis.grouping.cv_groups` when
    the file does not carry what it groups by, skipped as below). ``progress`` receives the
    :class:`rigctl.core.progress.ProgressEvent` s of the encoding and the analyses.
    Returns ``(TaskResults, encoded_path)``. Tasks the data cannot support (e.g. extrapolation without the
    trained speeds/forces, groups of a texture set without groups) are skipped and the reason is added to
    ``TaskResults.warnings``.
    """
    from rigctl.analysis.params import CVParams, Repetitions
    from rigctl.operations import AnalysisPlan, load_or_encode, run_analyses

    fs, encoded = load_or_encode(path, variants, task=None, encode_to=encoded_path_for(path), progress=progress,
                                 overwrite=True)  # the tab's own <name>.encoded.h5, as its Encode button
    wanted = (("textures", "groups") if cv else ()) + (("extrapolation",) if extrapolation else ())
    plan = AnalysisPlan(wanted, groups_optional=True, on_error="skip", cv=CVParams(per_texture=per_texture, groups=cv_groups),
                        reps=Repetitions(n_pcs=n_pcs, repeats=repeats, seed=seed, variants=variants))
    return run_analyses(fs, plan, progress=progress), str(encoded)


def model_path_for(encoded_path: str, variant: str) -> str:
    """Where the tab saves the model it trains: ``<name>.<variant>.skops`` beside the encoded file."""
    p = Path(encoded_path)
    return str(p.with_name(f"{p.name.removesuffix('.h5').removesuffix('.encoded')}.{variant}.skops"))


def train_classifier(path: str, variant: str = "speed_scaled", n_pcs: int = 25, out_path: str | None = None) -> str:
    """Fit the raw-trials-to-label pipeline on every trial of the session an encoded file was made from
    (:func:`rigctl.operations.train_model`, as ``rigctl analyze --save-model``) and save it as a model file
    (:func:`rigctl.storage.model_file.save_model`). Returns the model file's path (default :func:`model_path_for`)."""
    from rigctl.operations import train_model
    from rigctl.storage.model_file import save_model

    trained = train_model(path, variant, n_pcs)
    out = out_path or model_path_for(path, variant)
    save_model(trained.model, out, info=trained.info)
    return out
