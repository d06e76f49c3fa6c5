"""Per-taxel normalisation of sensor readings to 0-1 over the whole dataset (Methods, tactile texture dataset).

"The taxel readings were normalized between 0 and 1 on a per-taxel basis (i.e. minimum and maximum readings for
each taxel from the whole dataset was used)." :class:`TaxelRange` accumulates those minima and maxima chunk by
chunk (a first pass over a session), and hands the encoder an affine map (offset, scale) that the Izhikevich kernel
applies on the fly, so raw ``uint16`` ADC counts never need a float copy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["TaxelRange"]


@dataclass
class TaxelRange:
    """Running per-taxel minimum and maximum.

    Parameters
    ----------
    minimum, maximum : (n_taxels,) float64, in the readings' units (ADC counts for sessions). ``None`` until the
        first :meth:`update`.
    """

    minimum: np.ndarray | None = None
    maximum: np.ndarray | None = None
    n_samples: int = field(default=0)

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
        lo = x.min(axis=0).astype(np.float64)
        hi = x.max(axis=0).astype(np.float64)
        if self.minimum is None:
            self.minimum, self.maximum = lo, hi
        else:
            if lo.shape != self.minimum.shape:
                raise ValueError(f"{lo.size} taxels, expected {self.minimum.size}")
            self.minimum = np.minimum(self.minimum, lo)
            self.maximum = np.maximum(self.maximum, hi)  # type: ignore[arg-type]  # set by the first update
        self.n_samples += x.shape[0]
        return self

    @property
    def n_taxels(self) -> int:
        return 0 if self.minimum is None else self.minimum.size

    def offset_scale(self) -> tuple[np.ndarray, np.ndarray]:
        """``(offset, scale)`` (n_taxels,) float64 such that ``(x - offset) * scale`` is in [0, 1].

        A taxel that never changed (max == min) gets scale 0, i.e. a constant 0 input.

        Raises
        ------
        RuntimeError
            before any :meth:`update`.
        """
        if self.minimum is None:
            raise RuntimeError("TaxelRange has seen no data")
        span = self.maximum - self.minimum
        scale = np.divide(1.0, span, out=np.zeros_like(span), where=span > 0)
        return self.minimum.copy(), scale

    def normalise(self, readings: np.ndarray, dtype=np.float32) -> np.ndarray:
        """``(..., n_taxels)`` readings -> the same shape in [0, 1] (``dtype``, default float32)."""
        offset, scale = self.offset_scale()
        return ((np.asarray(readings, dtype=np.float64) - offset) * scale).astype(dtype)

    def to_dict(self) -> dict[str, Any]:
        return {"minimum": self.minimum.tolist(), "maximum": self.maximum.tolist(),  # type: ignore[union-attr]
                "n_samples": self.n_samples}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TaxelRange":
        return cls(np.asarray(d["minimum"], float), np.asarray(d["maximum"], float), int(d.get("n_samples", 0)))
