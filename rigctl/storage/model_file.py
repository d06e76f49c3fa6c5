"""Model files: a fitted scikit-learn pipeline (raw trials -> texture label, :mod:`rigctl.analysis.model`) written
with skops (``.skops``: a zip of JSON and arrays, loaded without running pickle code), with the library versions it
was made with.

Loading trusts only the types of rigctl, scikit-learn, numpy and scipy (anything else in the file is refused by
name) and checks the versions recorded: a file made with another scikit-learn or rigctl is refused with a clear
error unless ``check_versions=False`` (an estimator's internals can change between releases).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

from rigctl.storage.outputs import MODEL_META_NAME

__all__ = ["ModelFileError", "save_model", "load_model", "model_versions", "read_model_info"]

#: the format tag in the file's metadata
MODEL_FORMAT = "rigctl.model/1"
#: modules whose types a model file may hold
TRUSTED_PREFIXES = ("rigctl.", "sklearn.", "numpy.", "scipy.", "builtins.", "collections.")
_META = MODEL_META_NAME


class ModelFileError(ValueError):
    """Not a rigctl model file, a type it may not hold, or made with other library versions."""


def model_versions() -> dict[str, str]:
    """The versions a model file records: rigctl, scikit-learn, numpy, scipy, skops."""
    import numpy
    import scipy
    import sklearn
    import skops

    from rigctl.core.version import __version__

    return {"rigctl": __version__, "scikit-learn": sklearn.__version__, "numpy": numpy.__version__,
            "scipy": scipy.__version__, "skops": skops.__version__}


def save_model(model: Any, path: str | os.PathLike[str], *, info: dict[str, Any] | None = None,
               option: str = "--save-model") -> Path:
    """Write ``model`` (e.g. a fitted :class:`sklearn.pipeline.Pipeline`) to ``path`` with skops, plus a
    ``rigctl_model.json`` entry: format, library versions, ``info`` (JSON-able: variant, PCs, training file...).

    Written under the output policy (:func:`rigctl.storage.outputs.replacing`): refused (``OutputLocked``) while
    another writer holds ``path``, refused (``OutputError``) when ``path`` is anything but a rigctl model file,
    replaced in one rename (a failed write leaves the old file), the umask's mode."""
    import skops.io as sio

    from rigctl.storage.outputs import replacing

    path = Path(path)
    data = sio.dumps(model)
    meta = {"format": MODEL_FORMAT, "versions": model_versions(), "info": dict(info or {})}
    buf = io.BytesIO(data)
    with zipfile.ZipFile(buf, "a", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr(_META, json.dumps(meta, default=str))
    with replacing(path, kind="model", option=option) as tmp:
        tmp.write_bytes(buf.getvalue())
    return path


def read_model_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The metadata of a model file: ``{"format", "versions", "info"}``.

    Raises
    ------
    ModelFileError
        Not a rigctl model file.
    """
    try:
        with zipfile.ZipFile(path) as z:
            meta = json.loads(z.read(_META))
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as exc:
        raise ModelFileError(f"{path} is not a rigctl model file (rigctl analyze --save-model): {exc}") from None
    if meta.get("format") != MODEL_FORMAT:
        raise ModelFileError(f"{path}: model format {meta.get('format')!r}, this rigctl reads {MODEL_FORMAT}")
    return dict(meta)


def load_model(path: str | os.PathLike[str], *, check_versions: bool = True) -> Any:
    """Read a model written by :func:`save_model`.

    Raises
    ------
    FileNotFoundError
    ModelFileError
        Not a model file; a type outside rigctl / scikit-learn / numpy / scipy; or (``check_versions``) made with
        another rigctl or scikit-learn version than the running one (named, with both versions).
    """
    import skops.io as sio

    meta = read_model_info(path)
    if check_versions:
        here, there = model_versions(), meta.get("versions", {})
        differ = [f"{lib} {there.get(lib, '?')} (running {here[lib]})" for lib in ("rigctl", "scikit-learn")
                  if there.get(lib) != here[lib]]
        if differ:
            raise ModelFileError(f"{path} was made with {', '.join(differ)}: refit it with this version (rigctl "
                                 "analyze --save-model), or load with check_versions=False at your own risk")
    data = Path(path).read_bytes()
    untrusted = sio.get_untrusted_types(data=data)
    refused = [t for t in untrusted if not t.startswith(TRUSTED_PREFIXES)]
    if refused:
        raise ModelFileError(f"{path} holds types a rigctl model may not hold: {', '.join(refused)}")
    return sio.loads(data, trusted=untrusted)
