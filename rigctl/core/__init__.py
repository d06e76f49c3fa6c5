"""rigctl.core: what every layer shares, importing nothing else of rigctl's.

- :mod:`rigctl.core.sensor` - :class:`SensorLayout` (taxel layers, pitch, rate, ADC bits); the paper's 3x3x2 @ 1 kHz,
  10-bit is :data:`PAPER_SENSOR`.
- :mod:`rigctl.core.textures` - :class:`TextureSet` (labels of any length, groups, geometry, stable codes); the
  paper's A-P set is :data:`PAPER_TEXTURES`.
- :mod:`rigctl.core.trial` - :class:`PlannedTrial` and :class:`TrialData` (the trial records).
- :mod:`rigctl.core.interfaces` - the device Protocols: :class:`DrumController`, :class:`TaxelSource`,
  :class:`PlateMounter`, :class:`MassPlacer`, :class:`RigBackend`.
"""

from rigctl.core.interfaces import DrumController, MassPlacer, PlateMounter, RigBackend, TaxelSource
from rigctl.core.sensor import PAPER_FINGER, PAPER_SENSOR, LayoutError, SensorLayout, TaxelLayer, parse_layout
from rigctl.core.textures import (
                                  PAPER_GROUPS,
                                  PAPER_TEXTURES,
                                  TextureSet,
                                  TextureSetError,
                                  TextureSpec,
                                  texture_set_from_labels,
)
from rigctl.core.trial import PlannedTrial, TrialData

__all__ = [
    "SensorLayout", "TaxelLayer", "PAPER_SENSOR", "PAPER_FINGER", "parse_layout", "LayoutError",
    "TextureSet", "TextureSpec", "TextureSetError", "PAPER_TEXTURES", "PAPER_GROUPS", "texture_set_from_labels",
    "PlannedTrial", "TrialData",
    "DrumController", "TaxelSource", "PlateMounter", "MassPlacer", "RigBackend",
]
