"""A trial encoded on the taxel board (the handheld rig's ``--onboard-encoder``): its ``onboard`` group in the trial's
group (docs/session-format.md, "Trials encoded on the board"), written by the session writer, read by the reader and
recognised by the one validator (:mod:`rigctl.storage.validate`: such a trial has no raw taxels and is not damaged for
lacking them).

Layout of ``/trials/NNNNNN/onboard``:

- ``spike_sample`` (s,) int64: each spike's sample, counted from the first sample the board encoded;
- ``spike_taxel`` (s,) uint8: each spike's taxel (0-8, the top layer row-major);
- ``counts`` (9, 20) uint16: the board's counts frame (spikes per taxel and 100 ms scaled-time window);
- ``speeds_mm_s`` (w,) float64: the speed each real-time 100 ms window was scaled with on the board;
- ``held_windows`` (h,) int64: the windows the board scaled with the last speed (theirs came late);
- attributes ``samples`` (encoded), ``dropped_samples``, ``queue_max``, ``rate_hz``.

The trial's group has the attribute ``encoded_on_board = True`` and ``n_samples = 0`` (no taxel frames).
"""

from __future__ import annotations

from typing import Any

import h5py
import numpy as np

from rigctl.core.onboard import OnboardEncoding

__all__ = ["ONBOARD_ATTR", "ONBOARD_GROUP", "is_onboard", "onboard_samples", "read_onboard", "write_onboard"]

#: the trial group's attribute marking a trial encoded on the board (no raw taxels)
ONBOARD_ATTR = "encoded_on_board"
#: the trial group's subgroup holding the board's record
ONBOARD_GROUP = "onboard"
_ARRAYS = ("spike_sample", "spike_taxel", "counts", "speeds_mm_s", "held_windows")
_SCALARS = ("samples", "dropped_samples", "queue_max", "rate_hz")  # attributes of the group


def write_onboard(group: Any, enc: OnboardEncoding) -> None:
    """Write ``enc`` as ``group``'s ``onboard`` subgroup (``group``: an h5py group or group id of the trial)."""
    g = group.create_group(ONBOARD_GROUP) if isinstance(group, h5py.Group) else h5py.Group(group).create_group(
        ONBOARD_GROUP)
    for name in _ARRAYS:
        g.create_dataset(name, data=getattr(enc, name))
    for name in _SCALARS:
        g.attrs[name] = getattr(enc, name)


def is_onboard(attrs: Any) -> bool:
    """Whether a trial group's attributes mark it encoded on the board."""
    return bool(attrs.get(ONBOARD_ATTR, False))


def read_onboard(group: h5py.Group) -> OnboardEncoding | None:
    """The board's record of a trial group, None when it has none. Raises KeyError, OSError for a damaged one."""
    if ONBOARD_GROUP not in group:
        return None
    g = group[ONBOARD_GROUP]
    a = g.attrs
    return OnboardEncoding(spike_sample=g["spike_sample"][()], spike_taxel=g["spike_taxel"][()], counts=g["counts"][()],
                           speeds_mm_s=g["speeds_mm_s"][()], held_windows=g["held_windows"][()],
                           samples=int(a["samples"]), dropped_samples=int(a["dropped_samples"]),
                           queue_max=int(a["queue_max"]), rate_hz=float(a["rate_hz"]))


def onboard_samples(group: h5py.Group) -> tuple[int | None, str | None]:
    """For a trial group with no taxel frames: ``(samples the board encoded, None)`` when it is marked encoded on the
    board (:data:`ONBOARD_ATTR`) and its record is whole (``onboard`` with 2-D uint16 ``counts``, spike columns of
    one length, ``samples`` a count); ``(None, reason)`` when it is marked but its record is not; ``(None, None)``
    when it is not marked (the trial is judged as any other)."""
    if not is_onboard(group.attrs):
        return None, None
    try:
        g = group[ONBOARD_GROUP]
        counts, sample, taxel = g["counts"], g["spike_sample"], g["spike_taxel"]
        samples = g.attrs["samples"]
        whole = (counts.ndim == 2 and counts.dtype == np.uint16 and sample.ndim == 1 and sample.shape == taxel.shape
                 and np.ndim(samples) == 0 and float(samples) == int(samples) and int(samples) >= 0)
    except (KeyError, TypeError, ValueError, OSError) as exc:
        return None, f"it is marked encoded on the board but its onboard record is unreadable ({exc})"
    if not whole:
        return None, "it is marked encoded on the board but its onboard record is not the documented one"
    return int(samples), None
