"""rigctl.analysis: the paper's PCA + LDA analyses (Fig. 3, Table 1, Fig. 4) on encoded spiking features.

Modules: ``data`` (read an encoded file through :mod:`rigctl.storage.encoded`: ``FeatureSet`` with the file's
sensor layout and texture set, ``load_features``), ``classify`` (PCA fitted once per
split, nested-PC LDA, ``TextureClassifier`` for the GUI's real-time view), ``tasks`` (textures, groups,
extrapolation, speed extrapolation, real-time), ``stats`` (Welch + Cohen's d, two-proportion z + Cohen's h),
``report`` (Table 1 text, JSON/CSV, Fig. 3-like PNGs), ``model`` (the raw-trials-to-label scikit-learn pipeline,
the force-leak measurement), ``synthetic`` (feature sets with planted confounds).
No device, serial or simulation imports.
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "TextureClassifier": "rigctl.analysis.classify",
    "FeatureSet": "rigctl.analysis.data",
    "NotEncodedError": "rigctl.analysis.data",
    "load_features": "rigctl.analysis.data",
    "texture_pipeline": "rigctl.analysis.model",
    "CVParams": "rigctl.analysis.params",
    "Execution": "rigctl.analysis.params",
    "ExtrapolationParams": "rigctl.analysis.params",
    "RealtimeParams": "rigctl.analysis.params",
    "Repetitions": "rigctl.analysis.params",
    "TaskResults": "rigctl.analysis.results",
    "run_cv": "rigctl.analysis.tasks",
    "run_extrapolation": "rigctl.analysis.tasks",
    "run_realtime": "rigctl.analysis.tasks",
    "run_table1": "rigctl.analysis.tasks",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.analysis.classify import TextureClassifier as TextureClassifier
    from rigctl.analysis.data import (
        FeatureSet as FeatureSet,
        NotEncodedError as NotEncodedError,
        load_features as load_features,
    )
    from rigctl.analysis.model import texture_pipeline as texture_pipeline
    from rigctl.analysis.params import (
        CVParams as CVParams,
        Execution as Execution,
        ExtrapolationParams as ExtrapolationParams,
        RealtimeParams as RealtimeParams,
        Repetitions as Repetitions,
    )
    from rigctl.analysis.results import TaskResults as TaskResults
    from rigctl.analysis.tasks import (
        run_cv as run_cv,
        run_extrapolation as run_extrapolation,
        run_realtime as run_realtime,
        run_table1 as run_table1,
    )
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
