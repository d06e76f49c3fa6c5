"""rigctl.core: what every layer shares, importing nothing else of rigctl's.

- :mod:`rigctl.core.sensor` - :class:`SensorLayout` (taxel layers, pitch, rate, ADC bits); the paper's 3x3x2 @ 1 kHz,
  10-bit is :data:`PAPER_SENSOR`.
- :mod:`rigctl.core.textures` - :class:`TextureSet` (labels of any length, groups, geometry, stable codes); the
  paper's A-P set is :data:`PAPER_TEXTURES`.
- :mod:`rigctl.core.trial` - :class:`PlannedTrial` and :class:`TrialData` (the trial records).
- :mod:`rigctl.core.drum` - the drum controller in the rig's terms: :class:`DrumState`, :class:`Fault`,
  :class:`DrumStatus`, :class:`DrumLimits` (+ :class:`SetpointRange`, the rig's protocol range), the drum geometry,
  the state and fault words, the controller errors.
- :mod:`rigctl.core.normalisation` - :class:`TaxelRange`, the per-taxel 0-1 normalisation (one type everywhere).
- :mod:`rigctl.core.interfaces` - the device Protocols: :class:`DrumController`, :class:`TaxelSource`,
  :class:`PlateMounter`, :class:`MassPlacer`, :class:`RigBackend`.
- :mod:`rigctl.core.rig_plugins` - rig backends as plugins: the entry-point group ``rigctl.rigs``, a factory's
  :class:`~rigctl.core.rig_plugins.RigRequest` and what it returns (a RigBackend, a
  :class:`~rigctl.core.rig_plugins.SampleSource`, a ScanSource), the installed rigs found without importing them.
- :mod:`rigctl.core.progress` - :class:`ProgressEvent` (long work reports how far it is);
  :mod:`rigctl.core.lazy` - the lazy re-exports of the other packages' public names;
  :mod:`rigctl.core.version` - ``__version__`` (rigctl's modules import it from here, not from ``rigctl``).
- :mod:`rigctl.core.encoding_model` - the encoding model's fixed numbers (``MODEL_RATE_HZ``, ``RA_CUTOFF_HZ``);
  :mod:`rigctl.core.errors` - ``describe_error(exc)``, the one-line ``"TypeName: message"`` of an error.
"""

from rigctl.core.drum import (
    DRUM_CIRCUMFERENCE_MM,
    DRUM_DIAMETER_MM,
    MAX_FORCE_G,
    MAX_SPEED_MM_S,
    PROTOCOL_LIMITS,
    DrumError,
    DrumFault,
    DrumLimits,
    DrumState,
    DrumStatus,
    DrumTimeout,
    Fault,
    SetpointRange,
    SetpointRangeError,
    SettleBand,
    SpeedProfile,
)
from rigctl.core.interfaces import RIG_KINDS, DrumController, MassPlacer, PlateMounter, RigBackend, TaxelSource
from rigctl.core.normalisation import TaxelRange
from rigctl.core.progress import ProgressEvent
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
    "DrumController", "TaxelSource", "PlateMounter", "MassPlacer", "RigBackend", "RIG_KINDS",
    "DrumState", "Fault", "SpeedProfile", "DrumStatus", "DrumLimits", "SettleBand", "SetpointRange",
    "SetpointRangeError", "DrumError", "DrumTimeout", "DrumFault", "MAX_SPEED_MM_S", "MAX_FORCE_G", "PROTOCOL_LIMITS",
    "DRUM_DIAMETER_MM", "DRUM_CIRCUMFERENCE_MM",
    "TaxelRange", "ProgressEvent",
]
