"""The handheld system's shared terms (the paper's real-time experiment): the plate, its axis, a recorded scan and
what records one. Imports nothing else of rigctl's but :mod:`rigctl.core.sensor`, :mod:`rigctl.core.trial` and
:mod:`rigctl.core.clocksync`.

The paper (Materials and Methods, "Real-time Texture Classification - Processing Pipeline"): flat plates of textures
A, B, D, L and N, 300 mm x 36 mm, the middle 200 mm used; an operator moves a 3x3 sensor on a 3D-printed finger along
a plate, a motion tracker on the wrist gives the position, and the velocity is averaged every 100 ms. Here a scan is
one pass of the finger along a plate: the taxel frames and the tracker samples of that pass on one clock
(:class:`RawScan`), which :mod:`rigctl.acquisition.handheld` cuts into a trial by position (the finger entering and
leaving the middle 200 mm). What produces scans is a :class:`ScanSource`: the simulated operator
(:class:`rigctl.simulation.operator.SimulatedOperator`) or a live taxel board with a tracker stream.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from rigctl.core.clocksync import DeviceClockFit
from rigctl.core.onboard import OnboardEncoding
from rigctl.core.sensor import SensorLayout
from rigctl.core.trial import PlannedTrial

__all__ = ["PLATE_LENGTH_MM", "PLATE_WIDTH_MM", "USED_LENGTH_MM", "USED_START_MM", "USED_END_MM",
           "HANDHELD_TEXTURES", "PlateAxis", "RawScan", "ScanSource", "ScanError", "Tracker", "wait_for_pass",
           "refuse_older_than_cue", "checked_since",
           "PAST_END_MM", "MARGIN_S", "STAMP_AHEAD_S", "STAMP_BEHIND_S", "SPEED_FLOOR_MM_S", "WINDOW_S",
           "position_window_speed", "position_window_speeds"]

#: a texture plate's length and width, mm (Methods)
PLATE_LENGTH_MM = 300.0
PLATE_WIDTH_MM = 36.0
#: the middle of the plate used for classification, mm (Methods: "the middle 200 mm")
USED_LENGTH_MM = 200.0
#: where the used part starts and ends along the plate, mm from the plate's start
USED_START_MM = (PLATE_LENGTH_MM - USED_LENGTH_MM) / 2.0
USED_END_MM = USED_START_MM + USED_LENGTH_MM
#: the paper's five plates (Fig. 2B letters)
HANDHELD_TEXTURES = ("A", "B", "D", "L", "N")
#: how far past the used part's end the finger must be before a live scan counts as over, mm
PAST_END_MM = 10.0
#: tracker time a live scan keeps before the cue and waits after the exit, s
MARGIN_S = 0.3
#: how far a tracker sample's time on the host clock may lie after its arrival, s: no sample is stamped after it
#: arrived (liblsl's time correction between two PCs is good to about a millisecond; the rest is margin). Beyond it
#: the tracker's stamps are on another clock than the one they are read on, and its scans are refused
STAMP_AHEAD_S = 0.1
#: how long the link may at least take, s: over a whole pass the tracker's least late sample (stamp to arrival) must
#: come within this. A host's load delays some samples' arrival, never all of a pass's; a pass whose every sample
#: arrived this much after its stamp was stamped on a clock behind this one (a bridge stamping its own send time
#: late, a wrong offset), and its positions would be put that far from the taxels: refused
STAMP_BEHIND_S = 0.25
#: the real-time window the finger's speed is measured over, s (Methods: "averaged every 100 ms")
WINDOW_S = 0.1
#: the slowest speed a window is scaled with, mm/s. A window in which the finger stood still or slid back (a hand
#: hesitates, slips back a few mm) has a position change <= 0; eq. 2 has no meaning for it, so it is scaled with
#: 0 mm/s (its spikes land on one instant of scaled time, it adds no scaled time), on the host as on the on-board
#: encoder (which takes speeds 0-655.35 mm/s), and the trial counts such windows (``floored_windows``)
SPEED_FLOOR_MM_S = 0.0


def position_window_speed(t: np.ndarray, along_mm: np.ndarray, t0: float, t1: float) -> float:
    """The finger's speed over ``[t0, t1)`` (s) as the paper measures it: the position's change over the span divided
    by its length, mm/s (the position linearly interpolated between tracker samples ``t`` (k,) s increasing,
    ``along_mm`` (k,) mm; held at the ends); negative when the finger went back. Not floored."""
    x0, x1 = np.interp([t0, t1], t, along_mm)
    return float(x1 - x0) / (t1 - t0)


def position_window_speeds(t: np.ndarray, along_mm: np.ndarray, origin_s: float, n_windows: int,
                           window_s: float = WINDOW_S) -> np.ndarray:
    """(n_windows,) mm/s, each window ``[origin + w window_s, origin + (w + 1) window_s)``'s
    :func:`position_window_speed` floored at :data:`SPEED_FLOOR_MM_S` (the host's speeds, equal to those the host
    sends the on-board encoder: :func:`rigctl.devices.onboard_finger.window_speed_mm_s`)."""
    edges = origin_s + window_s * np.arange(n_windows + 1)
    x = np.interp(edges, np.asarray(t, np.float64), np.asarray(along_mm, np.float64))
    return np.maximum((x[1:] - x[:-1]) / (edges[1:] - edges[:-1]), SPEED_FLOOR_MM_S)


class ScanError(RuntimeError):
    """A scan could not be recorded or cut (no tracker samples, the finger never crossed the used part, ...)."""


@dataclass(frozen=True)
class PlateAxis:
    """The plate's axis in the tracker's frame, calibrated by touching the finger to the plate's two ends.

    Attributes
    ----------
    start_xyz, end_xyz : (3,) mm, the tracked point with the finger on the plate's start and on its end.
    length_mm : the plate's length, mm (:data:`PLATE_LENGTH_MM`); the two touches must be this far apart within
        ``tolerance`` (10 %), else the calibration is refused.
    """

    start_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    end_xyz: tuple[float, float, float] = (PLATE_LENGTH_MM, 0.0, 0.0)
    length_mm: float = PLATE_LENGTH_MM

    def __post_init__(self) -> None:
        d = np.subtract(self.end_xyz, self.start_xyz)
        span = float(np.linalg.norm(d))
        if not math.isfinite(span) or abs(span - self.length_mm) > 0.1 * self.length_mm:
            raise ValueError(f"the plate's two ends are {span:.1f} mm apart in the tracker's frame, not "
                             f"{self.length_mm:g} mm (+-10 %): touch the finger to each end again, or check the "
                             "tracker's unit (mm)")

    @property
    def unit(self) -> np.ndarray:
        """(3,) unit vector from the start to the end."""
        d = np.subtract(self.end_xyz, self.start_xyz).astype(np.float64)
        return d / np.linalg.norm(d)

    def along_mm(self, xyz: np.ndarray) -> np.ndarray:
        """(k,) position along the plate, mm from its start (scaled so the two touches are 0 and ``length_mm``),
        of (k, 3) tracked points (mm)."""
        p = np.asarray(xyz, np.float64).reshape(-1, 3) - np.asarray(self.start_xyz, np.float64)
        span = float(np.linalg.norm(np.subtract(self.end_xyz, self.start_xyz)))
        return (p @ self.unit) * (self.length_mm / span)

    @classmethod
    def from_touches(cls, start: np.ndarray, end: np.ndarray, length_mm: float = PLATE_LENGTH_MM) -> "PlateAxis":
        """From tracked samples (k, 3) mm held at each end (their medians). Raises ValueError as the constructor."""
        s = np.median(np.asarray(start, np.float64).reshape(-1, 3), axis=0)
        e = np.median(np.asarray(end, np.float64).reshape(-1, 3), axis=0)
        return cls(tuple(map(float, s)), tuple(map(float, e)), length_mm)  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        return {"start_xyz": list(self.start_xyz), "end_xyz": list(self.end_xyz), "length_mm": self.length_mm}


@dataclass
class RawScan:
    """One pass of the finger along a plate, before it is cut into a trial.

    Attributes
    ----------
    taxels : (n, n_channels) uint16 ADC counts, the taxel board's frames of the pass (and some before and after).
    seq : (n,) uint16 frame sequence numbers.
    host_time_s : (n,) float64 host receive time of each frame, s (the host's clock; any origin shared with
        ``tracker_time_s``).
    tracker_time_s : (k,) float64 the tracker samples' times on the same host clock, s (a tracker stream's LSL
        timestamps with the LSL <-> host offset applied).
    tracker_xyz : (k, 3) float64 tracked position, mm, in the tracker's frame (NaN rows: none; see ``along_mm``).
    along_mm : (k,) float64 position along the plate, mm from its start, when the source gives it directly
        (the simulated operator); else computed from ``tracker_xyz`` with the rig's :class:`PlateAxis`.
    velocity_mm_s : (k,) float64 velocity along the plate from the tracker, mm/s, when the source gives it (a
        velocity channel); else computed from the position.
    attrs : what the source knows of the pass (simulated: the operator's intent and variability), JSON-able.
    frame_time_s : (n,) float64 each frame's time on the host clock when the source knows it already (a recorded
        session replayed: its trial's fitted clock); None: fitted from ``seq`` and ``host_time_s`` (a live board).
    time_origin_s : the host clock's time at 0 of the times above when they are relative (a replayed trial's times
        count from its first frame, exactly as recorded): added to the boundaries the cut reports.
    clock_fit : the source's fit of the board's clock over its whole stream (a live board: every scan's frames are
        added to it, so one scan's late frames bend nothing); None: a fit of this scan's frames alone.
    onboard : a pass the taxel board encoded itself (``--onboard-encoder``): its record; then ``taxels`` has no rows.
    onboard_start_s : with ``onboard``: the time of the board's first encoded sample on the tracker's clock, s.
    """

    taxels: np.ndarray
    seq: np.ndarray
    host_time_s: np.ndarray
    tracker_time_s: np.ndarray
    tracker_xyz: np.ndarray | None = None
    along_mm: np.ndarray | None = None
    velocity_mm_s: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    frame_time_s: np.ndarray | None = None
    time_origin_s: float = 0.0
    clock_fit: DeviceClockFit | None = None
    onboard: OnboardEncoding | None = None
    onboard_start_s: float = math.nan


@runtime_checkable
class ScanSource(Protocol):
    """What a handheld rig records from: a taxel source and a motion source on one clock.

    ``layout`` is the taxel sensor; ``scan(planned, stop=)`` waits for the operator (cued by the rig) to pass the
    finger along the plate ``planned.texture`` with the velocity profile ``planned.profile`` and returns the pass;
    raises :class:`ScanError`, or returns None when ``stop()`` turned true. ``describe()`` a JSON-able dict for the
    session's ``rig_config``.
    """

    layout: SensorLayout

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """One pass (see the class docstring)."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-able: the source's kind and settings."""
        ...

    def close(self) -> None:
        """Release the source's links (never raises)."""
        ...


class Tracker(Protocol):
    """A live motion source of the handheld rig: a tracker's LSL stream
    (:class:`rigctl.simulation.handheld_lsl.LslTracker`) or a serial motion board
    (:class:`rigctl.devices.motion.SerialMotion`). ``since(t0)`` gives the samples with host time >= ``t0``
    (``time.monotonic`` s): times (k,) s and positions (k, 3) x, y, z in the tracker's frame, (k, 1) along the
    plate, or (k, 2) along the plate and the velocity along it (mm/s, NaN where not measured); ``channels`` has 3
    entries for x, y, z. A tracker that also has ``since_received(t0)`` (the same and each sample's arrival on the
    host clock, (k,) s) lets :func:`wait_for_pass` refuse a scan older than its cue."""

    name: str
    channels: tuple[int, ...]

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]: ...

    def describe(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


def _samples(tracker: Tracker, t0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The tracker's samples from ``t0`` (:meth:`Tracker.since`) and their arrival times when it knows them."""
    received = getattr(tracker, "since_received", None)
    if callable(received):
        t, x, arrived = received(t0)
        return t, x, arrived
    t, x = tracker.since(t0)
    return t, x, None


def _refuse_stamped_ahead(t: np.ndarray, arrived: np.ndarray) -> None:
    ahead = float(np.max(t - arrived)) if t.size else 0.0
    if ahead > STAMP_AHEAD_S:
        raise ScanError(f"the tracker's samples are stamped {ahead:.3f} s after they arrived: its clock is not this "
                        "machine's and liblsl's time correction does not see it (a bridge stamping another clock "
                        "than LSL's local_clock?): the scan is refused, not recorded")


def checked_since(tracker: Tracker, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """``tracker.since(t0)``, refused (ScanError) when a sample is stamped more than :data:`STAMP_AHEAD_S` after it
    arrived (a tracker that knows its samples' arrival): the scan would take a pass older than its cue."""
    t, x, arrived = _samples(tracker, t0)
    if arrived is not None:
        _refuse_stamped_ahead(t, arrived)
    return t, x


def refuse_older_than_cue(t: np.ndarray, arrived: np.ndarray, entry: int, t_cue: float) -> None:
    """Raise ScanError when a pass (tracker times ``t`` (k,) s on the host clock, their arrivals ``arrived`` (k,) s,
    the finger inside the plate's used part from sample ``entry`` on) is older than its cue at ``t_cue``: a sample
    stamped more than :data:`STAMP_AHEAD_S` after it arrived (the stamps on another clock: every pass would look newer
    than every cue), every sample stamped more than :data:`STAMP_BEHIND_S` before it arrived (a clock behind: the
    positions off the taxels by that much), or the finger's entry arrived more than :data:`MARGIN_S` before the cue
    (a pass the operator made before being told). Such a scan is refused, never recorded; its trial is cued again."""
    _refuse_stamped_ahead(t, arrived)
    behind = float(np.min(arrived - t)) if t.size else 0.0
    if behind > STAMP_BEHIND_S:
        raise ScanError(f"the tracker's samples are all stamped at least {behind:.3f} s before they arrived (more "
                        f"than the link's {STAMP_BEHIND_S:g} s): its clock is behind this machine's (a bridge stamping "
                        "another clock than LSL's local_clock, or a wrong time offset), so the positions would not "
                        "match the taxels: the scan is refused, not recorded")
    early = t_cue - float(arrived[entry])
    if early > MARGIN_S:
        raise ScanError(f"a scan older than its cue: the finger entered the plate's used part {early:.3f} s before "
                        f"the cue (by the samples' arrival, stamped {float(t[entry]) - t_cue:+.3f} s from it): "
                        "refused, not recorded")


def _positions_seen(pos: np.ndarray) -> str:
    """``": along the plate it saw 0.02 to 0.29 (mm?): ..."``: what the tracker's positions were, and a unit that
    fits them better when they span a pass in metres or centimetres (a tracker without unit metadata), for the
    message of a scan that never came."""
    pos = pos[np.isfinite(pos)] if pos.size else pos
    if not pos.size:
        return ""
    lo, hi = float(pos.min()), float(pos.max())
    seen = f"; along the plate it saw {lo:.3g} to {hi:.3g} mm (a pass goes {USED_START_MM:g} to {USED_END_MM:g})"
    for unit, factor in (("metres", 1000.0), ("centimetres", 10.0)):
        if lo * factor < USED_START_MM and hi * factor > USED_END_MM:
            return (f"{seen}: those are a whole pass in {unit}; rigctl takes mm (scale the tracker's stream to mm, "
                    "or give its unit in the stream's metadata)")
    return seen


def wait_for_pass(tracker: Tracker, along: Callable[[np.ndarray], np.ndarray], t_cue: float, *,
                  stop: Callable[[], bool] | None = None, timeout_s: float = 60.0,
                  poll_s: float = 0.02) -> tuple[np.ndarray, np.ndarray] | None:
    """After a cue at ``t_cue`` (``time.monotonic`` s): wait until the tracked finger has been before the plate's used
    part and then :data:`PAST_END_MM` past its end, then :data:`MARGIN_S` / 2 more; returns the tracker's samples from
    ``t_cue - MARGIN_S`` (times (k,) s, positions (k, channels)), or None when ``stop()`` turned true. ``along(x)``
    turns the positions into mm along the plate. Raises ScanError when no pass comes within ``timeout_s``, or when
    the pass is older than its cue (:func:`refuse_older_than_cue`, a tracker that knows its samples' arrival)."""
    while True:
        if stop is not None and stop():
            return None
        t, x, arrived = _samples(tracker, t_cue - MARGIN_S)
        if arrived is not None:  # refused as soon as one sample shows it, not after a whole pass
            _refuse_stamped_ahead(t, arrived)
        pos = along(x) if t.size else np.zeros(0)
        entered = np.flatnonzero(pos < USED_START_MM)
        if entered.size and np.any(pos[entered[0]:] > USED_END_MM + PAST_END_MM):
            break
        if time.monotonic() - t_cue > timeout_s:
            raise ScanError(f"no pass of the finger through the plate within {timeout_s:g} s (the tracker sent "
                            f"{t.size} samples){_positions_seen(pos)}")
        time.sleep(poll_s)
    if arrived is not None:
        inside = np.flatnonzero(pos[entered[0]:] >= USED_START_MM)
        refuse_older_than_cue(t, arrived, entered[0] + int(inside[0]), t_cue)
    time.sleep(MARGIN_S / 2)
    return tracker.since(t_cue - MARGIN_S)
