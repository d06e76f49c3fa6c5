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


def train_classifier(path: str, variant: str = "speed_scaled", n_pcs: int = 25):
    """Fit a :class:`rigctl.analysis.classify.TextureClassifier` on every trial of an encoded file.

    Returns ``(classifier, taxel_min, taxel_max)``: the normalisation the file was encoded with, needed to encode
    new trials the same way for the real-time view. The classifier also carries ``encode_params`` (the file's
    encoding parameters: windows, taxels, constants) and ``layout`` (the file's sensor).
    """
    from rigctl.analysis.classify import TextureClassifier
    from rigctl.analysis.data import load_features
    from rigctl.storage.encoded import open_encoded

    fs = load_features(path, [variant])
    clf = TextureClassifier(n_pcs=n_pcs, max_pcs=max(n_pcs, 1)).fit(fs.features[variant], fs.texture)
    clf.n_pcs = min(clf.n_pcs, clf.n_components_)  # a small data set has fewer PCs than asked for
    clf.variant = variant
    with open_encoded(path) as ef:
        norm = ef.normalisation
        # encode live trials exactly as the file was (same windows, taxels, constants -> same feature columns)
        clf.encode_params = dict(ef.parameters)
        clf.layout = ef.layout
    return clf, norm["taxel_min"], norm["taxel_max"]  # float64 ADC counts
