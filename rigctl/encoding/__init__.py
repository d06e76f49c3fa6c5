"""rigctl.encoding: the paper's neuromorphic encoding (numpy/numba; no device code).

Modules, one job each (data flows top to bottom):

- :mod:`~rigctl.encoding.normalise` - per-taxel 0-1 normalisation over the whole dataset (``TaxelRange``).
- :mod:`~rigctl.encoding.filters` - the RA input: 20 Hz Butterworth low-pass + derivative (``ra_input``, ``RAFilter``).
- :mod:`~rigctl.encoding.izhikevich` - eqs. (3)-(5): ``encode_sa``, ``encode_ra``, ``encode_trials``,
  ``StreamingEncoder``, the float64 kernel (``run_izhikevich``).
- :mod:`~rigctl.encoding.fused` - the fused kernel: raw counts -> normalisation, SA and RA (filter included) ->
  spike times in one pass, float32 (``run_fused``); used by the pipeline, the streaming encoder and eq. (1).
- :mod:`~rigctl.encoding.fixed_sa` - the on-board encoder's integer SA kernel, integer for integer the firmware's
  (``FixedSAEncoder``; ``ScanEncoder(kernel="fixed")``).
- :mod:`~rigctl.encoding.spikes` - ``SpikeTrains``: NWB-style flat spike times + row-end index (stored by
  :mod:`rigctl.storage.encoded`).
- :mod:`~rigctl.encoding.force` - eq. (1): vectorised bisection of the force coefficients (``ForceCoefficients``).
- :mod:`~rigctl.encoding.speed` - eq. (2): ``scale_spike_times``, ``incremental_scale`` (100 ms batches).
- :mod:`~rigctl.encoding.features` - SR/SC in 100 ms windows (720 / 2160 features for 18 taxels; 180 real-time).
- :mod:`~rigctl.encoding.rate` - the explicit resampling of readings not at the model's 1 kHz (1 ms steps).
- :mod:`~rigctl.encoding.estimators` - the same steps as scikit-learn transformers on raw trials
  (``TaxelNormaliser``, ``ForceScaler``, ``SpikeEncoder``, ``FeatureExtractor``), passing a
  :class:`~rigctl.encoding.batch.TrialBatch` on.
- :mod:`~rigctl.encoding.pipeline` - ``encode_session``: a session file -> the encoded file (Dask optional), written
  and read through :mod:`rigctl.storage.encoded` (which also holds the variant registry).

Submodules are imported on use (numba compiles on first call; compiled kernels are cached on disk).
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "FeatureExtractor": "rigctl.encoding.estimators",
    "SpikeEncoder": "rigctl.encoding.estimators",
    "TaxelNormaliser": "rigctl.encoding.estimators",
    "spike_features": "rigctl.encoding.features",
    "ForceScaler": "rigctl.encoding.estimators",
    "fit_force_coefficients": "rigctl.encoding.force",
    "StreamingEncoder": "rigctl.encoding.izhikevich",
    "encode_ra": "rigctl.encoding.izhikevich",
    "encode_sa": "rigctl.encoding.izhikevich",
    "encode_trials": "rigctl.encoding.izhikevich",
    "TaxelRange": "rigctl.encoding.normalise",
    "EncodeParams": "rigctl.encoding.pipeline",
    "encode_session": "rigctl.encoding.pipeline",
    "incremental_scale": "rigctl.encoding.speed",
    "scale_spike_times": "rigctl.encoding.speed",
    "SpikeTrains": "rigctl.encoding.spikes",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.encoding.estimators import (
        FeatureExtractor as FeatureExtractor,
        ForceScaler as ForceScaler,
        SpikeEncoder as SpikeEncoder,
        TaxelNormaliser as TaxelNormaliser,
    )
    from rigctl.encoding.features import spike_features as spike_features
    from rigctl.encoding.force import fit_force_coefficients as fit_force_coefficients
    from rigctl.encoding.izhikevich import (
        StreamingEncoder as StreamingEncoder,
        encode_ra as encode_ra,
        encode_sa as encode_sa,
        encode_trials as encode_trials,
    )
    from rigctl.encoding.normalise import TaxelRange as TaxelRange
    from rigctl.encoding.pipeline import EncodeParams as EncodeParams, encode_session as encode_session
    from rigctl.encoding.speed import incremental_scale as incremental_scale, scale_spike_times as scale_spike_times
    from rigctl.encoding.spikes import SpikeTrains as SpikeTrains
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
