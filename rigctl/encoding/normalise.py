"""Per-taxel normalisation of sensor readings to 0-1 over the whole dataset (Methods, tactile texture dataset).

"The taxel readings were normalized between 0 and 1 on a per-taxel basis (i.e. minimum and maximum readings for
each taxel from the whole dataset was used)." :class:`TaxelRange` accumulates those minima and maxima chunk by
chunk (a first pass over a session), and hands the encoder an affine map (offset, scale) that the Izhikevich kernel
applies on the fly, so raw ``uint16`` ADC counts never need a float copy.
"""

from __future__ import annotations

# one type for the per-taxel range, shared with the calibration and the live encoder: rigctl.core.normalisation
from rigctl.core.normalisation import TaxelRange as TaxelRange

__all__ = ["TaxelRange"]
