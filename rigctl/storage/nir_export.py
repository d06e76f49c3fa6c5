"""A trained readout as a NIR graph (the Neuromorphic Intermediate Representation, https://neuroir.org: a file that
Norse, snnTorch, Lava, SpiNNaker, Sinabs/Speck and others read): ``Input -> Affine -> Output``, where the input is
one trial's window features (the "count window": each SA train's spike rate and each RA train's spike count per
window, in the order of :class:`rigctl.encoding.estimators.FeatureExtractor`) and the output the class scores; the
predicted texture is the label (``metadata["classes"]``) of the largest score. The graph's metadata says how the
input is counted (window, windows per train, trains, time base, the variant) so another tool can build it from
spike times. The affine map is :func:`rigctl.analysis.readout.affine_readout`'s.

Written with the ``nir`` package (optional: ``pip install 'rigctl[nir]'``), under the output policy
(:func:`rigctl.storage.outputs.replacing`, kind ``"nir"``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["NirExportError", "write_readout_nir", "NIR_NODES"]

#: the graph's node names, in order: the window features in, the readout, the class scores out
NIR_NODES = ("input", "readout", "output")


class NirExportError(RuntimeError):
    """The ``nir`` package is missing, or the readout's arrays do not fit together."""


def write_readout_nir(path: str | os.PathLike[str], weight: np.ndarray, bias: np.ndarray, *,
                      metadata: dict[str, object], overwrite: bool = False) -> Path:
    """Write ``Input(n_features) -> Affine(weight, bias) -> Output(n_classes)`` to ``path`` (a ``.nir`` HDF5 file).

    Parameters
    ----------
    weight : (n_classes, n_features) float; bias : (n_classes,) float.
    metadata : JSON-like values (str, numbers, lists of str / numbers) stored as the graph's metadata; must hold
        ``classes`` (n_classes labels in the scores' order).
    overwrite : replace an existing NIR file rigctl wrote (never another kind of file).

    Raises
    ------
    NirExportError
        ``nir`` not installed; shapes that do not fit; no ``classes`` of the right length.
    FileExistsError, rigctl.storage.outputs.OutputError, rigctl.storage.outputs.OutputLocked
        The output policy.
    """
    try:
        import nir
    except ImportError:
        raise NirExportError("writing NIR needs the nir package: pip install 'rigctl[nir]'") from None
    from rigctl.storage.outputs import replacing

    w = np.asarray(weight, dtype=np.float64)
    b = np.asarray(bias, dtype=np.float64)
    classes = list(metadata.get("classes", []))  # type: ignore[call-overload]
    if w.ndim != 2 or b.shape != (w.shape[0],) or len(classes) != w.shape[0]:
        raise NirExportError(f"readout weight {w.shape}, bias {b.shape} and {len(classes)} classes do not fit")
    graph = nir.NIRGraph(
        nodes={"input": nir.Input(input_type=np.array([w.shape[1]])), "readout": nir.Affine(weight=w, bias=b),
               "output": nir.Output(output_type=np.array([w.shape[0]]))},
        edges=[("input", "readout"), ("readout", "output")],
        metadata={**metadata, "classes": [str(c) for c in classes]})
    with replacing(path, overwrite=overwrite, kind="nir") as tmp:
        nir.write(tmp, graph)
    return Path(path)
