"""Trial lengths by label: a label hidden in the trial length.

When one texture's trials are shorter than another's (6 s against 8 s), features sized to the longest trial give the
short ones empty last windows, and a classifier reads the texture off the padding (100 % on that texture, whatever
the encoding). :func:`length_imbalance` names it; ``rigctl encode --crop-s S`` cuts every trial to its first S seconds
(:func:`rigctl.encoding.pipeline.encode_session` with ``EncodeParams.crop_s``), a common length, so the length says nothing.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LENGTH_TOLERANCE", "length_imbalance", "crop_samples"]

#: textures whose median trial durations differ by more than this fraction of the longest are named
LENGTH_TOLERANCE = 0.05


def length_imbalance(texture: np.ndarray, duration_s: np.ndarray, *, tolerance: float = LENGTH_TOLERANCE
                     ) -> str | None:
    """One line naming the textures whose median trial duration (s) differs from the others' by more than
    ``tolerance`` of the longest, with the crop that removes it (``--crop-s``: the shortest trial), or None.

    texture : (n_trials,) labels; duration_s : (n_trials,) s (NaN entries ignored)."""
    tex = np.asarray(texture).astype(str)
    dur = np.asarray(duration_s, np.float64)
    ok = np.isfinite(dur) & (dur > 0)
    if ok.sum() < 2:
        return None
    labels = np.unique(tex[ok])
    med = {str(t): float(np.median(dur[ok & (tex == t)])) for t in labels}
    lo, hi = min(med.values()), max(med.values())
    if len(med) < 2 or hi - lo <= tolerance * hi:
        return None
    order = sorted(med, key=lambda t: med[t])
    shown = ", ".join(f"{t} {med[t]:.2f} s" for t in (order[:3] + ["..."] + order[-2:] if len(order) > 5 else order)
                      if t != "...") + (" ..." if len(order) > 5 else "")
    crop = math.floor(float(dur[ok].min()) * 100) / 100
    return (f"trial durations differ by texture (median: {shown}): features sized to the longest trial leave the "
            "shorter ones' last windows empty, a label a classifier can read off the padding; crop every trial to a "
            f"common length: rigctl encode --crop-s {crop:g}")


def crop_samples(crop_s: float | None, rate_hz: float) -> int | None:
    """Samples of ``crop_s`` seconds at ``rate_hz`` (None: no crop)."""
    if crop_s is None:
        return None
    return max(1, int(round(float(crop_s) * float(rate_hz))))
