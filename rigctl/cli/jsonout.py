"""JSON the commands print (``--json``): strict JSON, so any parser reads it (``NaN`` and infinities are not JSON:
they become ``null``), numpy scalars and arrays as plain values, paths as text."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

__all__ = ["json_text", "strict"]


def strict(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, numpy scalars/arrays and paths made plain."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    tolist = getattr(value, "tolist", None)  # numpy scalars and arrays
    if callable(tolist):
        return strict(tolist())
    return value


def json_text(value: Any, *, indent: int | None = None) -> str:
    """``value`` as strict JSON text (:func:`strict`, then ``json.dumps(allow_nan=False)``)."""
    import json

    return json.dumps(strict(value), indent=indent, allow_nan=False, default=str)
