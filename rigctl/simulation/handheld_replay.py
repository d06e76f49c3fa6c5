"""A recorded handheld session replayed as the handheld rig's scans (``rigctl acquire PROTOCOL --replay S.h5`` for a
handheld protocol, ``--motion replay:S.h5``).

:class:`SessionScans` is a :class:`rigctl.core.handheld.ScanSource` on a session file recorded on the handheld rig:
each cue (plate, profile) is answered with a recorded scan of that plate and profile, as it was recorded: its taxel
frames with their sequence numbers and receive times, each frame's time on the host clock from the trial's clock fit
(its clock attributes, :func:`rigctl.acquisition.clock.fitted_times`'s arithmetic), the tracker's position and
velocity samples, and the recorded boundaries (the ``scan_enter`` / ``scan_leave`` markers). The rig cuts it by
position again (:func:`rigctl.acquisition.handheld.cut_scan`) and the run engine, the live encoder and the classifier
take it as they took the live scan, so a replay gives the live run's end-of-scan predictions exactly (the same
frames, the same velocity samples at the same times; ``tests/acquisition/test_handheld_replay.py``).

Which recorded scan answers a cue: the one with the cue's trial id when it is of the cue's plate and profile (the
same protocol replayed), else the first not yet replayed of that plate and profile, in plan order. Only the scans the
one trial validator passes are replayed (:func:`rigctl.storage.validate.usable_trials`: an excluded one, an edit after
the seal, is warned of (``TrialsExcluded``) and never replayed).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.handheld import RawScan, ScanError
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import PlannedTrial, TrialData
from rigctl.storage.session import open_session
from rigctl.storage.validate import TrialsExcluded, usable_trials

__all__ = ["SessionScans"]

#: the clock attributes a replayed trial keeps as recorded (:func:`rigctl.acquisition.clock.trial_clock_attrs`)
CLOCK_ATTRS = ("trial_time_origin_s", "host_time_origin_s", "device_count_origin", "fitted_time_origin_s", "clock_period_s",
               "clock_drift_ppm", "clock_residual_s", "clock_blocks", "clock_rejected", "clock_span_s",
               "clock_segment")


def _frame_times(data: TrialData) -> np.ndarray:
    """Each frame's fitted host time on the trial's time axis, s (the recorded clock fit: relative to the trial's time
    0, ``trial_time_origin_s``, or in a trial recorded before it, the first frame's receive time; the receive times
    when the trial has no fit)."""
    a = data.attrs
    if "fitted_time_origin_s" not in a or "clock_period_s" not in a:
        return np.asarray(data.host_time_s, np.float64)
    seq = np.asarray(data.seq, np.int64)
    steps = np.concatenate((np.zeros(1, np.int64), np.bitwise_and(np.diff(seq), 0xFFFF)))
    fitted = float(a["fitted_time_origin_s"]) + np.cumsum(steps) * float(a["clock_period_s"])
    return fitted - float(a.get("trial_time_origin_s", a.get("host_time_origin_s", fitted[0])))


class SessionScans:
    """The scans of a recorded handheld session (module docstring).

    Parameters
    ----------
    path : the session file (recorded on the handheld rig: its trials carry ``boundary = "position"``).

    Raises
    ------
    ScanError
        The file holds no handheld scan (no complete trial with a position trace).
    OSError, rigctl.storage.session.SessionError
        The file cannot be read.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._session = open_session(self.path)
        s = self._session
        self.layout: SensorLayout = s.layout
        self.textures: TextureSet = s.textures
        rows = {int(r["trial_id"]): r for r in s.plan}
        report = usable_trials(s)  # the one trial validator: a damaged scan is never replayed
        if report.excluded:
            warnings.warn(f"{self.path}: {report.summary()}", TrialsExcluded, stacklevel=2)
        self._scans = [(tid, str(rows[tid]["texture"]), str(rows[tid]["profile"])) for tid in report.ids
                       if s.trial_attrs(tid).get("boundary") == "position"]
        if not self._scans:
            s.close()
            raise ScanError(f"{self.path} holds no handheld scan (no complete trial cut by position): record one "
                            "with a handheld protocol first")
        self._used: set[int] = set()
        self.scans = 0

    def _pick(self, planned: PlannedTrial) -> int:
        want = (str(planned.texture), str(planned.profile))
        for tid, tex, prof in self._scans:
            if tid == planned.trial_id and (tex, prof) == want and tid not in self._used:
                return tid
        for tid, tex, prof in self._scans:
            if (tex, prof) == want and tid not in self._used:
                return tid
        raise ScanError(f"{self.path.name} has no scan left of plate {want[0]} with profile {want[1]} to replay "
                        f"(it holds {len(self._scans)} scans, {len(self._used)} replayed)")

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """The recorded scan answering the cue ``planned`` (module docstring); None when ``stop()``. Raises
        ScanError when the recording has none left of that plate and profile."""
        if stop is not None and stop():
            return None
        tid = self._pick(planned)
        data = self._session.trial(tid)
        self._used.add(tid)
        self.scans += 1
        a = data.attrs
        keep = {k: a[k] for k in CLOCK_ATTRS if k in a}
        for k in ("tracker_rate_hz", "tracker_dropouts"):  # the live tracker's, not the replayed trace's
            if k in a:
                keep[k] = a[k]
        keep.update(replayed_from=str(self.path), replayed_trial=tid)
        seq = np.asarray(data.seq if data.seq is not None else np.arange(data.n_samples) % 65536, np.uint16)
        return RawScan(taxels=data.taxels, seq=seq, host_time_s=np.asarray(data.host_time_s, np.float64),
                       tracker_time_s=np.asarray(data.position_time_s, np.float64), along_mm=data.position_mm,
                       velocity_mm_s=np.asarray(data.speed_mm_s, np.float64), attrs=keep,
                       frame_time_s=_frame_times(data),
                       time_origin_s=float(a.get("trial_time_origin_s", a.get("host_time_origin_s", 0.0))))

    def describe(self) -> dict[str, Any]:
        """JSON-able: kind, the file, its scans."""
        return {"kind": "session_replay", "path": str(self.path), "scans": len(self._scans),
                "sensor_layout": self.layout.to_dict()}

    def close(self) -> None:
        """Close the file."""
        self._session.close()
