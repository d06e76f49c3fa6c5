"""The handheld rig: the paper's real-time system, an operator scanning flat plates with the sensor on a finger.

There is no drum. A trial's motion is the operator's scan: :meth:`HandheldRig.record_trial` prompts the operator
(which plate, which velocity profile, go), waits for one pass of the finger from its :class:`rigctl.core.handheld.
ScanSource` (the simulated operator, or a taxel board with a tracker stream), and cuts it by position
(:func:`cut_scan`): the trial starts when the finger enters the plate's middle 200 mm and ends when it leaves it
(Methods: the scan ends "once the finger has reached the end of the texture plate (determined by the position
information from the motion tracker)"). So the run engine (:func:`rigctl.acquisition.runner.run_protocol`) records a
handheld protocol exactly as a drum protocol: mount (here: ask for) the plate, record the trial, write it.

Each trial keeps, beside its taxels:

- the finger's speed of each 100 ms real-time window as the trial's speed trace (``speed_mm_s``, ``speed_time_s``):
  the paper's window speed, the position's change over the window (:func:`rigctl.core.handheld.
  position_window_speeds`, the windows counted from the trial's first sample as the encoder counts them, the speed
  the host sends the on-board encoder too), floored at :data:`rigctl.core.handheld.SPEED_FLOOR_MM_S` (a window in
  which the hand stood still or slipped back is scaled with 0 mm/s; ``floored_windows`` counts them), written as a
  step trace (two samples a window, 0.25 ms inside its edges) so that :func:`rigctl.encoding.speed.window_speeds`
  reads each window's speed back;
- the tracker's position along the plate (``position_mm``, ``position_time_s``, mm from the plate's start);
- the two boundaries (``scan_enter_s``, ``scan_leave_s``: host clock; ``boundary = "position"``), the tracker's
  measured rate and dropouts, the taxel board's clock fit (:mod:`rigctl.acquisition.clock`).

The taxel frames are put on the host clock by the board's clock fit (:class:`rigctl.core.clocksync.DeviceClockFit`,
the lower envelope of the frames' receive times), the tracker samples by their source (an LSL stream's timestamps
with the LSL <-> host offset): the cut is made on that one clock.
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from rigctl.acquisition.clock import trial_clock_attrs
from rigctl.acquisition.protocol import PlannedTrial, Settle
from rigctl.acquisition.rig import Rig, RigError, StopFlag
from rigctl.acquisition.rigconfig import config_path, load_rig_config
from rigctl.acquisition.safety import SafetyLatch
from rigctl.core.clocksync import DeviceClockFit
from rigctl.core.handheld import (
    PLATE_LENGTH_MM,
    PLATE_WIDTH_MM,
    SPEED_FLOOR_MM_S,
    USED_END_MM,
    USED_START_MM,
    WINDOW_S,
    PlateAxis,
    RawScan,
    ScanError,
    ScanSource,
    position_window_speeds,
)
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import TrialData

__all__ = ["HandheldRig", "NoDrumError", "cut_scan", "plate_axis_from_config", "velocity_from_position", "VELOCITY_WINDOW_S"]

log = logging.getLogger(__name__)

#: the span the tracker's velocity is averaged over, s (the paper: every 100 ms)
VELOCITY_WINDOW_S = 0.1
#: tracker samples kept before the entry and after the exit, s (the velocity at the trial's edges)
TRACE_MARGIN_S = 0.2
#: the longest the tracker may lose the finger within a scan, s: a longer gap leaves the window speeds of the gap
#: unknown (a 0.5 s occlusion made them up to 14x wrong), so the scan is refused and cued again. The simulated
#: operator's tracker loses bursts of up to 25 samples at 90 Hz (0.28 s), as a Vive that loses line of sight
MAX_TRACKER_GAP_S = 0.3
#: the farthest the tracked point may be from the plate's calibrated axis within a scan, mm: half the plate's width
#: (a finger slid off the plate's side, or lifted and carried in the air, is farther)
OFF_PLATE_MM = PLATE_WIDTH_MM / 2.0


class NoDrumError(RigError, AttributeError):
    """The handheld rig has no drum: a drum command was asked of it."""


class _NoDrum:
    """Stands where a drum rig has its controller: every attribute is a :class:`NoDrumError`."""

    def __getattr__(self, name: str) -> Any:
        raise NoDrumError(f"the handheld rig has no drum (asked for {name!r}): the operator moves the finger")


def velocity_from_position(time_s: np.ndarray, along_mm: np.ndarray, at_s: np.ndarray | None = None,
                           window_s: float = VELOCITY_WINDOW_S) -> np.ndarray:
    """Velocity along the plate, mm/s: the mean over ``window_s`` centred on each time of ``at_s`` (default the
    samples' own times), ``(x(t + w/2) - x(t - w/2)) / w`` with the position linearly interpolated between tracker
    samples (held at the ends). ``time_s`` (k,) s increasing, ``along_mm`` (k,) mm. Raises ScanError with fewer
    than two samples."""
    t = np.asarray(time_s, np.float64)
    x = np.asarray(along_mm, np.float64)
    if t.size < 2:
        raise ScanError("fewer than two tracker samples: no velocity")
    at = t if at_s is None else np.asarray(at_s, np.float64)
    h = window_s / 2.0
    return (np.interp(at + h, t, x) - np.interp(at - h, t, x)) / window_s


def window_speed_trace(t: np.ndarray, along_mm: np.ndarray, origin_s: float, duration_s: float,
                       window_s: float = WINDOW_S) -> tuple[np.ndarray, np.ndarray, int]:
    """A trial's speed trace: each real-time window of ``[origin, origin + duration_s)`` (s, the tracker's clock), its
    :func:`rigctl.core.handheld.position_window_speeds` as a step trace on the trial's axis (0 at ``origin``): times
    (2 n,) s, two per window ``window_s / 400`` inside its edges, and speeds (2 n,) mm/s; and how many windows were
    floored (the finger still or going back)."""
    n = max(1, int(np.ceil(round(duration_s / window_s, 9))))
    raw = np.diff(np.interp(origin_s + window_s * np.arange(n + 1), t, along_mm))
    v = position_window_speeds(t, along_mm, origin_s, n, window_s)
    lo = window_s * np.arange(n) + window_s / 400
    hi = window_s * np.arange(1, n + 1) - window_s / 400
    return (np.column_stack([lo, hi]).reshape(-1), np.repeat(v, 2),
            int(np.sum(raw <= SPEED_FLOOR_MM_S * window_s)))


def occluded_windows(t: np.ndarray, origin_s: float, duration_s: float, window_s: float = WINDOW_S) -> list[int]:
    """The real-time windows of ``[origin, origin + duration_s)`` (numbered from 0 as :func:`window_speed_trace`
    numbers them) that a tracker gap overlaps: an interval between two samples ``t`` (s) longer than 1.5 x their
    median (the finger occluded, a lost stream), over which the window's speed was interpolated, not measured (issue
    78: a 0.5 s occlusion made window speeds up to 14x wrong; gaps over :data:`MAX_TRACKER_GAP_S` refuse the scan)."""
    gaps = np.diff(t)
    if gaps.size == 0:
        return []
    n = max(1, int(np.ceil(round(duration_s / window_s, 9))))
    long = np.flatnonzero(gaps > 1.5 * float(np.median(gaps)))
    out: set[int] = set()
    for i in long:  # the windows the open interval (t[i], t[i + 1]) overlaps
        first = int(np.floor((t[i] - origin_s) / window_s))
        last = int(np.ceil((t[i + 1] - origin_s) / window_s)) - 1
        out.update(range(max(first, 0), min(last, n - 1) + 1))
    return sorted(out)


def _occlusion_attrs(t: np.ndarray, origin_s: float, duration_s: float) -> dict[str, Any]:
    """``occluded_windows`` (how many) and ``occluded_window_ids`` (their numbers, comma-separated; "" for none):
    :func:`occluded_windows`, named in the log too."""
    ids = occluded_windows(t, origin_s, duration_s)
    if ids:
        log.warning("tracker gaps over windows %s of the scan: their speeds are interpolated across the gap",
                    ",".join(map(str, ids)))
    return {"occluded_windows": len(ids), "occluded_window_ids": ",".join(map(str, ids))}


def _crossing(t: np.ndarray, x: np.ndarray, level: float, after: int = 0) -> tuple[int, float] | None:
    """The first sample index ``i > after`` where ``x`` rises through ``level`` (``x[i-1] < level <= x[i]``) and the
    interpolated crossing time, or None."""
    above = x[after:] >= level
    rising = np.flatnonzero(above[1:] & ~above[:-1])
    if not rising.size:
        return None
    i = after + int(rising[0]) + 1
    return i, _crossing_time(t, x, level, i)


def _crossing_time(t: np.ndarray, x: np.ndarray, level: float, i: int) -> float:
    """When ``x`` crossed ``level`` between samples ``i - 1`` and ``i``, interpolated linearly (s)."""
    x0, x1, t0, t1 = x[i - 1], x[i], t[i - 1], t[i]
    return float(t0 + (level - x0) / (x1 - x0) * (t1 - t0)) if x1 != x0 else float(t1)


def _last_crossing(t: np.ndarray, x: np.ndarray, level: float, before: int) -> tuple[int, float, int] | None:
    """The last sample index ``i <= before`` where ``x`` rises through ``level`` and its interpolated time, and how
    many rising crossings came before it (passes begun and abandoned), or None."""
    above = x[: before + 1] >= level
    rising = np.flatnonzero(above[1:] & ~above[:-1])
    if not rising.size:
        return None
    i = int(rising[-1]) + 1
    return i, _crossing_time(t, x, level, i), int(rising.size - 1)


def _check_one_pass(t: np.ndarray, xyz: np.ndarray | None, axis: PlateAxis | None, i_in: int, i_out: int) -> None:
    """Refuse (ScanError) a pass in which the tracker lost the finger longer than :data:`MAX_TRACKER_GAP_S` or the
    tracked point left the plate (:data:`OFF_PLATE_MM` from its calibrated axis: slid off its side or lifted)."""
    span = t[max(i_in - 1, 0): i_out + 1]
    gaps = np.diff(span)
    if gaps.size and float(gaps.max()) > MAX_TRACKER_GAP_S:
        at = float(span[int(np.argmax(gaps))] - t[i_in])
        raise ScanError(f"the tracker lost the finger for {float(gaps.max()):.2f} s during the pass ({at:+.2f} s from "
                        f"its entry; more than {MAX_TRACKER_GAP_S:g} s): the window speeds there are unknown, the scan "
                        "is refused; scan again")
    if xyz is None or axis is None:
        return
    p = np.asarray(xyz[i_in: i_out + 1], np.float64) - np.asarray(axis.start_xyz, np.float64)
    off = np.linalg.norm(p - np.outer(p @ axis.unit, axis.unit), axis=1)
    if off.size and float(off.max()) > OFF_PLATE_MM:
        k = int(np.argmax(off))
        raise ScanError(f"the finger left the plate during the pass: {float(off[k]):.0f} mm from its axis "
                        f"{float(t[i_in + k] - t[i_in]):.2f} s after its entry (more than {OFF_PLATE_MM:g} mm: slid off "
                        "its side or lifted): the scan is refused, not recorded; scan again with the finger on the "
                        "plate")


def cut_scan(raw: RawScan, layout: SensorLayout, axis: PlateAxis | None = None, *,
             used_mm: tuple[float, float] = (USED_START_MM, USED_END_MM),
             velocity_window_s: float = VELOCITY_WINDOW_S) -> TrialData:
    """One scan -> one trial, cut by position (module docstring).

    Parameters
    ----------
    raw : the pass (taxels on the board's clock, tracker samples on the host clock).
    layout : the taxel sensor.
    axis : the plate's calibrated axis (needed when ``raw`` gives tracker-frame points only).
    used_mm : where the used part starts and ends along the plate, mm (the paper's middle 200 mm: 50-250).

    Returns
    -------
    TrialData: the frames whose fitted host time lies in [entry, exit); the frames' receive times (``host_time_s``)
    and the speed and position traces on one axis whose 0 is the first kept frame's fitted time (so the traces line
    up with the samples, ``i / rate``, however late a busy host received the frames; ``trial_time_origin_s`` is that
    0 on the host clock); attrs (boundaries, tracker, clock fit, the source's).

    Raises
    ------
    ScanError: no tracker position, the finger never entered or never left the used part, no frame inside; or the
    pass was not one continuous pass on the plate: the tracker lost it longer than :data:`MAX_TRACKER_GAP_S`, or it
    left the plate (:data:`OFF_PLATE_MM`; with tracker-frame points and the plate's axis).

    One scan is one continuous pass: the exit is the first time the finger reaches the used part's end, the entry the
    last time it came into the used part before that (so a pass begun, abandoned and brought back in the air is not
    merged with the next one: ``abandoned_passes`` counts them in the trial's attributes).
    """
    t = np.asarray(raw.tracker_time_s, np.float64)
    if raw.along_mm is not None:
        along = np.asarray(raw.along_mm, np.float64)
    elif raw.tracker_xyz is not None and axis is not None:
        along = axis.along_mm(raw.tracker_xyz)
    else:
        raise ScanError("the scan has no position along the plate (give the tracker's position and calibrate the "
                        "plate's axis)")
    ok = np.isfinite(t) & np.isfinite(along)
    xyz = None if raw.tracker_xyz is None or raw.along_mm is not None else np.asarray(raw.tracker_xyz)[ok]
    t, along = t[ok], along[ok]
    order = np.argsort(t, kind="stable")
    t, along = t[order], along[order]
    xyz = None if xyz is None else xyz[order]
    first = _crossing(t, along, used_mm[0]) if t.size >= 2 else None
    if first is None:
        raise ScanError(f"the finger never entered the used part of the plate (from {used_mm[0]:g} mm; the tracker "
                        f"saw {np.nanmin(along) if along.size else math.nan:.0f}-"
                        f"{np.nanmax(along) if along.size else math.nan:.0f} mm)")
    leave = _crossing(t, along, used_mm[1], after=first[0] - 1)
    if leave is None:
        raise ScanError(f"the finger never left the used part of the plate (past {used_mm[1]:g} mm)")
    enter = _last_crossing(t, along, used_mm[0], before=leave[0])
    assert enter is not None  # the first entry is one
    _check_one_pass(t, xyz, axis, enter[0], leave[0])
    t_in, t_out = enter[1], leave[1]
    near = (t >= t_in - TRACE_MARGIN_S) & (t <= t_out + TRACE_MARGIN_S)
    if raw.onboard is not None:  # encoded on the board: its record, no taxel frames; times from its first sample
        origin = float(raw.onboard_start_s)
        span_s = raw.onboard.samples / layout.sample_rate_hz if raw.onboard.samples else t_out - origin
        st, sv, floored = window_speed_trace(t, along, origin, span_s)
        return TrialData(taxels=np.zeros((0, layout.n_channels), np.uint16), speed_mm_s=sv,
                         speed_time_s=st, position_mm=along[near], position_time_s=t[near] - origin,
                         attrs={**_tracker_attrs(raw, t, t_in, t_out, near, used_mm, enter[2]), "floored_windows": floored,
                                **_occlusion_attrs(t, origin, span_s),
                                "trial_time_origin_s": raw.time_origin_s + origin, **dict(raw.attrs)},
                         layout=layout, onboard=raw.onboard)
    fit = raw.clock_fit or DeviceClockFit(layout.sample_rate_hz)
    counts = fit.add(np.asarray(raw.seq), np.asarray(raw.host_time_s, np.float64))
    mapping = fit.mapping()
    if raw.frame_time_s is not None:  # the source's own frame times (a replayed session's fitted clock)
        frame_t = np.asarray(raw.frame_time_s, np.float64)
    else:
        frame_t = (mapping.host_time(counts) if mapping is not None else
                   raw.host_time_s[0] + (counts - counts[0]) / layout.sample_rate_hz)
    keep = np.flatnonzero((frame_t >= t_in) & (frame_t < t_out))
    if keep.size == 0:
        raise ScanError("no taxel frame between the finger's entry and exit (is the taxel board streaming?)")
    host = np.asarray(raw.host_time_s, np.float64)[keep]
    origin = float(frame_t[keep[0]])  # the first kept frame's time on the board's clock, not its (late) receipt
    seq = np.asarray(raw.seq, np.uint16)[keep]
    steps = np.bitwise_and(np.diff(seq.astype(np.int64)), 0xFFFF)
    st, sv, floored = window_speed_trace(t, along, origin, keep.size / layout.sample_rate_hz)
    attrs: dict[str, Any] = {**_tracker_attrs(raw, t, t_in, t_out, near, used_mm, enter[2]), "floored_windows": floored,
                             **_occlusion_attrs(t, origin, keep.size / layout.sample_rate_hz),
                             **trial_clock_attrs(fit, counts[keep], host),
                             "trial_time_origin_s": raw.time_origin_s + origin,  # the host-clock time of time 0
                             **dict(raw.attrs)}
    return TrialData(taxels=np.asarray(raw.taxels)[keep], seq=seq, flags=np.zeros(keep.size, np.uint8),
                     host_time_s=host - origin, speed_mm_s=sv, speed_time_s=st,
                     position_mm=along[near], position_time_s=t[near] - origin,
                     dropped_frames=int(np.sum(steps - 1)) if steps.size else 0, attrs=attrs, layout=layout)


def _tracker_attrs(raw: RawScan, t: np.ndarray, t_in: float, t_out: float, near: np.ndarray,
                   used_mm: tuple[float, float], abandoned: int = 0) -> dict[str, Any]:
    """The trial's attributes from the tracker: the boundaries, the used part, the scan's duration and mean speed,
    the tracker's samples, rate and dropouts."""
    gaps = np.diff(t)
    period = float(np.median(gaps)) if gaps.size else math.nan
    return {"boundary": "position", "scan_enter_s": raw.time_origin_s + t_in, "scan_leave_s": raw.time_origin_s + t_out,
            "used_start_mm": float(used_mm[0]), "used_end_mm": float(used_mm[1]),
            "scan_duration_s": t_out - t_in, "scan_mean_speed_mm_s": (used_mm[1] - used_mm[0]) / (t_out - t_in),
            "tracker_samples": int(near.sum()), "tracker_rate_hz": 1.0 / period if period > 0 else math.nan,
            "tracker_dropouts": int(np.sum(gaps > 1.5 * period)) if gaps.size else 0,
            "abandoned_passes": int(abandoned)}


def _check_scan_length(data: TrialData, planned: PlannedTrial, rate_hz: float) -> None:
    """Refuse (ScanError: the run engine cues the scan again) a scan the session's validator would exclude as damaged
    by its length (:func:`rigctl.storage.validate.length_bounds`: half to twice the cue's duration), naming the
    speed the operator scanned at and the one asked for; it was recorded complete, then excluded."""
    from rigctl.storage.validate import length_bounds

    n = data.n_samples or (int(data.onboard.samples) if data.onboard is not None else 0)  # the board's count
    lo, hi = length_bounds(planned.duration_s, rate_hz)
    if lo <= n + data.dropped_frames <= hi:
        return
    took = n / rate_hz
    mean = float(data.attrs.get("scan_mean_speed_mm_s", math.nan))
    word = "slower" if n > hi else "faster"
    raise ScanError(f"the scan took {took:.2f} s ({mean:.0f} mm/s), more than 2x {word} than the cue's "
                    f"{planned.duration_s:.2f} s at {planned.speed_mm_s:g} mm/s: scan again at about "
                    f"{planned.speed_mm_s:g} mm/s")


def plate_axis_from_config(host_config: dict[str, Any]) -> PlateAxis | None:
    """The plate axis of a rig config's ``handheld`` block (:meth:`PlateAxis.to_dict`), None without one. Raises
    ValueError for a bad block."""
    block = host_config.get("handheld")
    if not block:
        return None
    try:
        s, e = (tuple(float(v) for v in block[k]) for k in ("start_xyz", "end_xyz"))
        return PlateAxis(s, e, float(block.get("length_mm", PLATE_LENGTH_MM)))  # type: ignore[arg-type]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"the rig config's handheld block is not a plate axis ({exc}): calibrate it again") from None


class HandheldRig(Rig):
    """A rig whose trials are an operator's scans (module docstring); open it with ``rigctl.rigs.open_rig(
    "handheld")``.

    It stands where a drum :class:`rigctl.acquisition.rig.Rig` does for the run engine (``record_trial``,
    ``mount_texture``, ``safe_stop``, ``recover``, ``check_links``, ``describe``); there is no drum (``drum`` raises
    :class:`NoDrumError`, a RigError).

    Parameters
    ----------
    source : the scans (:class:`rigctl.core.handheld.ScanSource`).
    axis : the plate's calibrated axis in the tracker's frame (None: the source gives positions along the plate,
        or the rig config's ``handheld`` block: ``start_xyz``, ``end_xyz``, ``length_mm``).
    prompt : ``prompt(text)`` the operator reads (the plate, the profile, the go cue); default: logged.
    textures : the plates' texture set.
    host_config_path : the rig config file.
    """

    has_drum = False

    def __init__(self, source: ScanSource, *, axis: PlateAxis | None = None,
                 prompt: Callable[[str], Any] | None = None, textures: TextureSet | None = None,
                 host_config_path: str | None = None, mode: str = "handheld") -> None:
        self.source = source
        self.backend = source  # type: ignore[assignment]  # what describes the rig (no drum backend)
        self.drum = _NoDrum()
        self.stream = source  # type: ignore[assignment]
        self.mode = mode
        self.prompt = prompt
        self.texture: str | None = None
        self.settle = Settle()
        self.replay_continuous = False
        self.host_config = load_rig_config(host_config_path)
        self.host_config_path = str(config_path(host_config_path))
        self.axis = axis or plate_axis_from_config(self.host_config)
        self._textures = textures or getattr(source, "textures", None) or PAPER_TEXTURES
        self._closed = False
        self._lock = threading.RLock()
        self.drum_boot_count = None
        self.drum_resets = 0
        self.warnings: list[str] = []
        self.last_capture_frames = None
        self.stop_acknowledged = None
        self.clock_fit = None
        self.safety = SafetyLatch()  # the safety policy's latch (rigctl.acquisition.safety): nothing latches here
        self.homed_once = False
        #: ``on_marker(event, host_time_s, fields)`` receivers (the LSL publisher): scan_enter / scan_leave
        self.marker_listeners: list[Callable[[str, float, dict[str, Any]], Any]] = []
        #: ``on_cue(cue, text, fields)`` receivers of what the operator is told (the rig owner's event stream):
        #: ``plate`` (move to plate ``texture``) and ``go`` (scan it now with ``profile``); fields: texture, profile,
        #: trial_id, speeds
        self.cue_listeners: list[Callable[[str, str, dict[str, Any]], Any]] = []

    @property
    def layout(self) -> SensorLayout:
        return self.source.layout

    def _say(self, text: str) -> None:
        if self.prompt is not None:
            self.prompt(text)
        else:
            log.info("%s", text)

    def _cue(self, cue: str, text: str, fields: dict[str, Any]) -> None:
        for listener in list(self.cue_listeners):
            listener(cue, text, fields)

    def describe(self) -> dict:
        """JSON-able: mode, the source's description, the plate axis, the sensor, the texture set, the rig config."""
        return {"mode": self.mode, "drum_port": None, "taxel_port": None, "seed": getattr(self.source, "seed", None),
                "scan_source": self.source.describe(), "plate_axis": None if self.axis is None else self.axis.to_dict(),
                "sensor_layout": self.layout.to_dict(), "texture_set": self.textures.to_dict(),
                "host_config_path": self.host_config_path, "host_config": self.host_config}

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.source.close()

    def apply_settle(self, settle: Settle) -> None:
        self.settle = settle  # no force loop, no drum speed: nothing to write

    def release(self, timeout_s: float = 20.0) -> None:
        """Nothing holds the sensor: the operator lifts the finger."""

    def press(self, force_g: float, *, timeout_s: float | None = None, stop_event: Any = None) -> float:
        raise NoDrumError("the handheld rig has no actuator: the operator presses the finger")

    def mount_texture(self, label: str, prompt: Callable[[str], Any] | None = None) -> None:
        """Ask the operator to move to plate ``label`` (a label of :attr:`textures`); with ``prompt`` (the run's plate
        confirmation: the CLI's Enter on the terminal, a face's dialog) the cue asks for a confirmation and this
        returns once ``prompt(text)`` has: the first scan is cued only then. Without one, nothing waits and the cue
        does not ask for a confirmation."""
        label = self.textures.resolve(str(label))
        text = f"plate {label}: put the finger at the start of plate {label}" + (", then confirm" if prompt else "")
        self._cue("plate", text, {"texture": label, "confirm": prompt is not None})
        (prompt or self._say)(text)
        self.texture = label

    def safe_stop(self) -> bool:
        return True  # nothing moves by itself

    def announce_stop(self, reason: str) -> None:
        """STOP (the operator's, the dead man's switch): tell the operator to lift the finger (a ``stop`` cue; the run
        pauses, the scan in progress is discarded and cued again on resume)."""
        text = f"STOP ({reason}): lift the finger off the plate; the scan is cued again when the block resumes"
        self._cue("stop", text, {"reason": reason})
        self._say(text)

    def recover(self) -> str | None:
        return self.check_links()

    def wait_at_rest(self, timeout_s: float = 20.0) -> None:
        """Nothing to wait for: no actuator (the operator lifts the finger)."""
        return None

    def check_links(self, *, restart: bool = True, timeout_s: float | None = None) -> str | None:
        problem = getattr(self.source, "link_problem", None)
        return problem() if callable(problem) else None

    def record_trial(self, planned: PlannedTrial, *, stop_event: StopFlag | None = None) -> TrialData:
        """One scan of plate ``planned.texture`` with the profile ``planned.profile`` (the operator prompted), cut
        by position (:func:`cut_scan`). Raises ValueError (another plate than the one asked for), ScanError,
        :class:`rigctl.acquisition.rig.TrialAborted` (``stop_event``)."""
        from rigctl.acquisition.rig import TrialAborted

        if self.texture is not None and planned.texture != self.texture:
            raise ValueError(f"trial {planned.trial_id} is on plate {planned.texture} but the operator is on "
                             f"{self.texture}")
        ramp = (f" from {planned.ramp_start_mm_s:g} to {planned.ramp_end_mm_s:g} mm/s" if planned.is_ramp else
                f" at about {planned.speed_mm_s:g} mm/s")
        cue = f"plate {planned.texture}, profile {planned.profile}{ramp}: go"
        with self._lock:
            start, end = ((planned.ramp_start_mm_s, planned.ramp_end_mm_s) if planned.is_ramp else
                          (planned.speed_mm_s, planned.speed_mm_s))
            self._cue("go", cue, {"texture": planned.texture, "profile": planned.profile,
                                  "trial_id": planned.trial_id, "start_mm_s": float(start), "end_mm_s": float(end)})
            self._say(cue)
            started = _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")
            raw = self.source.scan(planned, stop=lambda: bool(stop_event and stop_event.is_set()))
            if raw is None:
                raise TrialAborted("stopped before the scan")
            data = cut_scan(raw, self.layout, self.axis)
            _check_scan_length(data, planned, self.layout.sample_rate_hz)
        data.attrs.setdefault("started_utc", started)
        for listener in list(self.marker_listeners):
            fields = {"texture": planned.texture, "profile": planned.profile, "trial_id": planned.trial_id}
            listener("scan_enter", float(data.attrs["scan_enter_s"]), fields)
            listener("scan_leave", float(data.attrs["scan_leave_s"]), fields)
        return data
