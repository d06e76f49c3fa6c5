"""The parameters of an encoding (:class:`EncodeParams`): the model's constants (paper eqs. 1-5, Methods), the
feature windows and the kernel's precision. Stored with every encoded file (``parameters`` attribute) and read back
with :meth:`EncodeParams.from_dict`; :func:`rigctl.encoding.pipeline.encode_session` and the estimators take them.
Re-exported by :mod:`rigctl.encoding.pipeline`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from rigctl.core.encoding_model import MODEL_RATE_HZ, RA_CUTOFF_HZ
from rigctl.encoding.features import N_WINDOWS_REALTIME, N_WINDOWS_SCALED
from rigctl.encoding.force import C_MAX, EPSILON, REFERENCE_FORCE_G
from rigctl.encoding.izhikevich import K_RA, K_SA
from rigctl.encoding.speed import REALTIME_REFERENCE_SPEED_MM_S, REFERENCE_SPEED_MM_S, WINDOW_S

__all__ = ["EncodeParams"]


@dataclass
class EncodeParams:
    """Parameters of an encoding run (stored as JSON in the output's ``parameters`` attribute).

    Attributes (units in the names; defaults: the paper's Methods)
    ----------------------------------------------------------------
    fs_hz : the model's step rate, Hz (1 kHz: 1 ms Izhikevich steps); readings at another rate are resampled to it.
    input_rate_hz : the session's sample rate, Hz (None: taken from the session's layout by :func:`encode_session`).
    k_sa, k_ra : eq. (3) input scales (100, 3). cutoff_hz : RA low-pass (20 Hz). rectify_ra : rectify the RA input.
    reference_speed_mm_s : eq. (2) reference (120 mm/s); realtime_reference_speed_mm_s : real-time one (100 mm/s).
    reference_force_g, epsilon, c_max : eq. (1) (500 g, 0.1 spikes/s, 5).
    window_s : feature window length, s (0.1 = 100 ms).
    n_windows_scaled : windows of the speed-scaled variants (20 = 2 s at the reference speed, the paper's); None =
        enough for the longest trial in scaled time (``duration x speed / reference``: whole trials).
    n_windows_unscaled : windows of the unscaled variants; None = enough for the longest trial of the file
        (:func:`windows_for`; 60 for the paper's dataset).
    n_windows_realtime : windows of the real-time variants (20).
    realtime_taxels : channels of the real-time variants; None = the sensor's first (top) layer (0-8 on the paper's
        sensor).
    izhikevich : eqs. (3)-(5) tonic-spiking constants.
    kernel_dtype : the fused kernel's state, "float32" (default: within the model's own rounding sensitivity,
        :mod:`rigctl.encoding.fused`) or "float64".
    crop_s : every trial cut to its first ``crop_s`` seconds before encoding (a common length: trial lengths that
        differ by texture are a label, :mod:`rigctl.encoding.lengths`); None = whole trials. A trial shorter than
        it is refused.
    """

    fs_hz: float = MODEL_RATE_HZ
    input_rate_hz: float | None = None
    k_sa: float = K_SA
    k_ra: float = K_RA
    cutoff_hz: float = RA_CUTOFF_HZ
    rectify_ra: bool = True
    reference_speed_mm_s: float = REFERENCE_SPEED_MM_S
    realtime_reference_speed_mm_s: float = REALTIME_REFERENCE_SPEED_MM_S
    reference_force_g: float = REFERENCE_FORCE_G
    epsilon: float = EPSILON
    c_max: float = C_MAX
    window_s: float = WINDOW_S
    n_windows_scaled: int | None = N_WINDOWS_SCALED
    n_windows_unscaled: int | None = None
    n_windows_realtime: int = N_WINDOWS_REALTIME
    realtime_taxels: list[Any] | None = None
    izhikevich: dict[str, Any] = field(default_factory=lambda: {"a": 0.02, "b": 0.2, "c": -65.0, "d": 6.0, "v_peak": 30.0})
    kernel_dtype: str = "float32"
    crop_s: float | None = None

    @classmethod
    def from_dict(cls, d) -> "EncodeParams":
        """The parameters an encoded file was made with (``open_encoded(path).parameters``); unknown keys are
        ignored, missing ones take the defaults. Use them to encode new trials the same way (:func:`encode_batch`:
        same windows, taxels and constants, so the features match the file's columns)."""
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in dict(d or {}).items() if k in known})

    def __post_init__(self) -> None:
        if self.kernel_dtype not in ("float32", "float64"):
            raise ValueError(f"kernel_dtype must be 'float32' or 'float64', got {self.kernel_dtype!r}")
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"window_s must be > 0 s, got {self.window_s!r}")
        for name in ("n_windows_scaled", "n_windows_realtime", "n_windows_unscaled"):
            if getattr(self, name) is not None and int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
