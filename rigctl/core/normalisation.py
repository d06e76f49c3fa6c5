"""Per-taxel normalisation of sensor readings to 0-1: the one type, :class:`TaxelRange`.

Paper, Methods ("Tactile texture dataset"): "The taxel readings were normalized between 0 and 1 on a per-taxel basis
(i.e. minimum and maximum readings for each taxel from the whole dataset was used)"; for the real-time experiment
"an initial dataset of 10 trials per texture was collected to get the minimum and maximum values for each taxel".

The same object is the calibration's result (``rigctl.acquisition.calibration``: kept in the rig config and copied
into each session), the encoder's normaliser (``rigctl.encoding``: an affine map ``(x - offset) * scale`` the
Izhikevich kernel applies on the fly, so raw ``uint16`` ADC counts never need a float copy) and the live encoder's
(``rigctl.operations``), so nothing bridges one into another by hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["TaxelRange", "column_extremes"]


@dataclass
class TaxelRange:
    """Per-taxel minimum and maximum readings (ADC counts for sessions), accumulated chunk by chunk.

    Parameters
    ----------
    minimum, maximum : (n_taxels,) float64, in the readings' units; ``None`` until the first :meth:`update`.
    n_trials : trials (captures) the extremes were taken over (a calibration run; 0 when not counted).
    source : where they came from (a session file path, "captures", ...).
    calibrated_utc : when (ISO 8601, UTC; "" when not a calibration).
    n_samples : samples folded in by :meth:`update`.
    """

    minimum: np.ndarray | None = None
    maximum: np.ndarray | None = None
    n_trials: int = 0
    source: str = ""
    calibrated_utc: str = ""
    n_samples: int = 0

    def __post_init__(self) -> None:
        if self.minimum is not None:
            self.minimum = np.asarray(self.minimum, dtype=np.float64)
            self.maximum = np.asarray(self.maximum, dtype=np.float64)
            if self.minimum.shape != self.maximum.shape:
                raise ValueError(f"minimum {self.minimum.shape} and maximum {self.maximum.shape} differ in shape")

    # the rig config's names (its ``taxel_normalisation`` block)
    @property
    def taxel_min(self) -> np.ndarray:
        """The per-taxel minimum (:attr:`minimum`). RuntimeError before any data."""
        return self._require()[0]

    @property
    def taxel_max(self) -> np.ndarray:
        """The per-taxel maximum (:attr:`maximum`). RuntimeError before any data."""
        return self._require()[1]

    def _require(self) -> tuple[np.ndarray, np.ndarray]:
        if self.minimum is None or self.maximum is None:
            raise RuntimeError("TaxelRange has seen no data")
        return self.minimum, self.maximum

    @property
    def n_taxels(self) -> int:
        return 0 if self.minimum is None else int(self.minimum.size)

    def update(self, readings: np.ndarray) -> "TaxelRange":
        """Fold ``(n_samples, n_taxels)`` (or ``(..., n_taxels)``) readings into the range; returns self.

        Raises
        ------
        ValueError
            if the taxel count differs from earlier updates.
        """
        x = np.asarray(readings)
        if x.size == 0:
            return self
        x = x.reshape(-1, x.shape[-1])
        lo, hi = column_extremes(x)
        return self.fold(lo, hi, x.shape[0])

    def fold(self, minimum: np.ndarray, maximum: np.ndarray, n_samples: int) -> "TaxelRange":
        """Fold the per-taxel extremes of ``n_samples`` readings seen elsewhere (``(n_taxels,)`` each, in the
        readings' units; e.g. a trial's, from the session validator's read) into the range, as :meth:`update` of
        those readings would; returns self.

        Raises
        ------
        ValueError
            if the taxel count differs from earlier updates.
        """
        lo, hi = np.asarray(minimum, dtype=np.float64), np.asarray(maximum, dtype=np.float64)
        if self.minimum is None or self.maximum is None:
            self.minimum, self.maximum = lo, hi
        else:
            if lo.shape != self.minimum.shape:
                raise ValueError(f"{lo.size} taxels, expected {self.minimum.size}")
            self.minimum = np.minimum(self.minimum, lo)
            self.maximum = np.maximum(self.maximum, hi)
        self.n_samples += int(n_samples)
        return self

    def offset_scale(self) -> tuple[np.ndarray, np.ndarray]:
        """``(offset, scale)`` (n_taxels,) float64 such that ``(x - offset) * scale`` is in [0, 1] for readings
        inside the range. A taxel that never changed (max == min) gets scale 0, i.e. a constant 0 input.

        Raises RuntimeError before any :meth:`update`."""
        lo, hi = self._require()
        span = hi - lo
        scale = np.divide(1.0, span, out=np.zeros_like(span), where=span > 0)
        return lo.copy(), scale

    def normalise(self, readings: np.ndarray, dtype: Any = np.float32, *, clip: bool = False) -> np.ndarray:
        """``(..., n_taxels)`` readings -> the same shape, 0 at the minimum and 1 at the maximum (``dtype``); with
        ``clip``, readings outside the range are clipped to [0, 1]."""
        offset, scale = self.offset_scale()
        out = (np.asarray(readings, dtype=np.float64) - offset) * scale
        if clip:
            out = np.clip(out, 0.0, 1.0)
        result: np.ndarray = out.astype(dtype)
        return result

    def apply(self, taxels: np.ndarray) -> np.ndarray:
        """``(..., n_taxels)`` ADC counts -> float32 in [0, 1] (clipped); a taxel whose range is zero maps to 0."""
        return self.normalise(taxels, np.float32, clip=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (lists): the ``taxel_normalisation`` block of the rig config / session ``/calibration``
        (``taxel_min``, ``taxel_max``, ``n_trials``, ``source``, ``calibrated_utc``)."""
        lo, hi = self._require()
        return {"taxel_min": [float(v) for v in lo], "taxel_max": [float(v) for v in hi],
                "n_trials": int(self.n_trials), "source": self.source, "calibrated_utc": self.calibrated_utc}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TaxelRange":
        """From :meth:`to_dict`'s block (older blocks without the counts, or with ``minimum``/``maximum``, too).
        KeyError when the extremes are missing."""
        lo = d["taxel_min"] if "taxel_min" in d else d["minimum"]
        hi = d["taxel_max"] if "taxel_max" in d else d["maximum"]
        return cls(np.asarray(lo, float), np.asarray(hi, float), int(d.get("n_trials", 0)), str(d.get("source", "")),
                   str(d.get("calibrated_utc", "")), int(d.get("n_samples", 0)))


#: rows folded side by side in :func:`column_extremes` (numpy reduces wide rows far faster than 18-column ones)
_FOLD_ROWS = 64


def column_extremes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of each column of the 2-d ``(n_rows, n_columns)`` ``x`` (n_rows >= 1), each ``(n_columns,)``
    float64 in ``x``'s units: the rows reduced ``_FOLD_ROWS`` at a time side by side (the same extremes as
    ``x.min(axis=0)``, several times faster for few columns). IndexError for no rows."""
    n_ch = x.shape[1]
    n = x.shape[0] // _FOLD_ROWS * _FOLD_ROWS
    lo_parts, hi_parts = [], []
    if n and x.flags.c_contiguous:
        wide = x[:n].reshape(-1, _FOLD_ROWS * n_ch)
        lo_parts.append(wide.min(axis=0).reshape(_FOLD_ROWS, n_ch).min(axis=0))
        hi_parts.append(wide.max(axis=0).reshape(_FOLD_ROWS, n_ch).max(axis=0))
    else:
        n = 0
    if n < x.shape[0]:
        lo_parts.append(x[n:].min(axis=0))
        hi_parts.append(x[n:].max(axis=0))
    lo = np.minimum.reduce(lo_parts) if len(lo_parts) > 1 else lo_parts[0]
    hi = np.maximum.reduce(hi_parts) if len(hi_parts) > 1 else hi_parts[0]
    return np.asarray(lo).astype(np.float64), np.asarray(hi).astype(np.float64)

