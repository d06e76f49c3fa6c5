"""Trial records shared by every layer: what a protocol plans (:class:`PlannedTrial`) and what a trial recorded
(:class:`TrialData`). Imports nothing else of rigctl's but :mod:`rigctl.core.sensor` and :mod:`rigctl.core.onboard`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.core.onboard import OnboardEncoding
from rigctl.core.sensor import PAPER_SENSOR, LayoutError, SensorLayout

__all__ = ["PlannedTrial", "TrialData", "REPEATED_SAMPLES_FLAG", "CONSTANT_PROFILES", "has_profiles",
           "lower_envelope_rate_hz", "repeated_samples"]

#: profile names that mean "no velocity profile" (a drum trial at one speed; an imported trial)
CONSTANT_PROFILES = ("", "constant")


def has_profiles(profile: Sequence[str] | np.ndarray | None) -> bool:
    """Whether trials with these profile names ((n,) str, or None) are a velocity-profile session: any name but
    :data:`CONSTANT_PROFILES` (realtime_profiles, the handheld blocks). The exports name such trials' profiles and
    give them Fig. 4's splits."""
    return profile is not None and any(str(p) not in CONSTANT_PROFILES for p in np.asarray(profile).ravel())

#: the share of a trial's samples repeating the one before above which the trial is flagged (a board or driver that
#: holds its last reading: issue 77, 2,396 of 12,000 rows held by a plugin board read "0 dropped")
REPEATED_SAMPLES_FLAG = 0.01


@dataclass(frozen=True)
class PlannedTrial:
    """One trial of a protocol's plan (one row of a session's ``/plan`` table).

    Attributes
    ----------
    trial_id : int (0-based, plan order)
    texture : str, a label of the session's texture set (the paper's A-P by default; any length)
    speed_mm_s : float, drum surface speed, mm/s; for a ramp, the mean speed over the trial; NaN when unknown
        (imported recordings)
    force_g : float, contact force setpoint, g; NaN when unknown
    duration_s : float, trial length, s; the runner records ``samples_at(rate_hz)`` frames
    profile : str, the velocity profile's name ("constant" when the protocol names none)
    ramp_start_mm_s, ramp_end_mm_s : float, mm/s, NaN for a constant speed
    repeat : int, 0-based repetition of this condition
    """

    trial_id: int
    texture: str
    speed_mm_s: float
    force_g: float
    duration_s: float
    profile: str = "constant"
    ramp_start_mm_s: float = math.nan
    ramp_end_mm_s: float = math.nan
    repeat: int = 0

    @property
    def is_ramp(self) -> bool:
        return not (math.isnan(self.ramp_start_mm_s) or math.isnan(self.ramp_end_mm_s))

    def samples_at(self, rate_hz: float) -> int:
        """Frames the trial records at ``rate_hz`` (Hz): ``round(duration_s * rate_hz)``."""
        return int(round(self.duration_s * float(rate_hz)))

    @classmethod
    def from_row(cls, row: Any) -> "PlannedTrial":
        """From a row of a session's plan (``rigctl.storage`` ``Session.plan``) or a ``/plan`` record."""
        def s(v: Any) -> str:
            return v.decode() if isinstance(v, bytes) else str(v)

        return cls(
            trial_id=int(row["trial_id"]), texture=s(row["texture"]), speed_mm_s=float(row["speed_mm_s"]),
            force_g=float(row["force_g"]), duration_s=float(row["duration_s"]), profile=s(row["profile"]),
            ramp_start_mm_s=float(row["ramp_start_mm_s"]), ramp_end_mm_s=float(row["ramp_end_mm_s"]),
            repeat=int(row["repeat"]),
        )


#: a trial's traces: (values, their times)
TRACES = (("force_g", "force_time_s"), ("speed_mm_s", "speed_time_s"), ("position_mm", "position_time_s"))


def _empty(dtype: Any) -> np.ndarray:
    return np.zeros(0, dtype=dtype)


@dataclass
class TrialData:
    """Everything recorded in one trial.

    Attributes
    ----------
    taxels : (n_samples, n_channels) uint16
        ADC counts (0 .. 2**adc_bits - 1) at ``layout.sample_rate_hz``, channels in ``layout`` order (the paper's
        sensor: 0-8 top layer, type I; 9-17 bottom layer, type II; row-major 3x3).
    layout : :class:`rigctl.core.sensor.SensorLayout`
        The sensor the readings come from (default :data:`rigctl.core.sensor.PAPER_SENSOR`); its channel count must
        match ``taxels``.
    seq : (n,) uint16
        The board's frame sequence numbers (gaps = dropped frames). Default: ``arange(n) % 65536``.
    flags : (n,) uint8
        Frame flags (``rigctl.devices.wire.FrameFlag``). Default: zeros.
    host_time_s : (n,) float64
        Host receive time of each frame, s since the trial's first frame. Default: ``arange(n) / sample_rate_hz``.
    force_g, force_time_s : (m,) float64
        Load-cell force trace (g) and its host times (s, same clock and origin as ``host_time_s``).
    speed_mm_s, speed_time_s : (k,) float64
        Measured drum surface speed trace (mm/s) and its host times (s); on the handheld rig the tracker's velocity
        along the plate.
    position_mm, position_time_s : (j,) float64
        Handheld rig only (else empty): the tracker's position along the plate, mm from its start, and its host times
        (s, same clock and origin as ``host_time_s``).
    dropped_frames : int
        Frames missing from ``seq`` within the trial.
    crc_errors : int
        Frames rejected by their CRC while the trial was captured.
    attrs : dict
        Trial attributes (setpoints, texture, profile, started_utc, ...); JSON-able scalars and strings.
    onboard : :class:`rigctl.core.onboard.OnboardEncoding` or None
        A scan the taxel board encoded itself (the handheld rig's ``--onboard-encoder``): its spikes, counts frame,
        applied speeds and flags; such a trial has no raw taxels (``taxels`` has 0 rows).

    Raises
    ------
    rigctl.core.sensor.LayoutError (a ValueError)
        If ``taxels`` is not ``(n, layout.n_channels)``, holds values above ``layout.adc_max`` or non-integer values.
    ValueError
        If a per-sample array does not have ``n`` rows, or a trace and its times differ in length.
    """

    taxels: np.ndarray
    seq: np.ndarray | None = None
    flags: np.ndarray | None = None
    host_time_s: np.ndarray | None = None
    force_g: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    force_time_s: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    speed_mm_s: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    speed_time_s: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    position_mm: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    position_time_s: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    dropped_frames: int = 0
    crc_errors: int = 0
    attrs: dict = field(default_factory=dict)
    layout: SensorLayout = PAPER_SENSOR
    onboard: OnboardEncoding | None = None

    def __post_init__(self) -> None:
        taxels = self.layout.check_readings(self.taxels)
        if taxels.dtype.kind == "f":
            if taxels.size and not np.all(np.isfinite(taxels) & (taxels == np.round(taxels))):
                raise LayoutError("taxels must be integer ADC counts; got non-integer floats (scale volts to "
                                  "counts first, e.g. `rigctl import --volts-ref`)")
        if taxels.size and taxels.dtype != np.uint16:
            lo, hi = taxels.min(), taxels.max()
            if lo < 0 or hi > self.layout.adc_max:
                raise LayoutError(f"taxels must be ADC counts 0..{self.layout.adc_max} ({self.layout.adc_bits}-bit), "
                                  f"got {lo}..{hi}")
        elif taxels.size and int(taxels.max()) > self.layout.adc_max:
            raise LayoutError(f"taxels must be ADC counts 0..{self.layout.adc_max} ({self.layout.adc_bits}-bit), got "
                              f"a maximum of {int(taxels.max())}")
        self.taxels = taxels.astype(np.uint16, copy=False)
        n = taxels.shape[0]
        self.seq = (np.arange(n) % 65536).astype(np.uint16) if self.seq is None else np.asarray(self.seq, np.uint16)
        self.flags = np.zeros(n, np.uint8) if self.flags is None else np.asarray(self.flags, np.uint8)
        if self.host_time_s is None:
            self.host_time_s = np.arange(n, dtype=np.float64) / self.layout.sample_rate_hz
        else:
            self.host_time_s = np.asarray(self.host_time_s, np.float64)
        for name in ("seq", "flags", "host_time_s"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must be ({n},) like taxels, got {getattr(self, name).shape}")
        for value, times in TRACES:
            v = np.asarray(getattr(self, value), np.float64).reshape(-1)
            t = np.asarray(getattr(self, times), np.float64).reshape(-1)
            if v.shape != t.shape:
                raise ValueError(f"{value} {v.shape} and {times} {t.shape} must have the same length")
            setattr(self, value, v)
            setattr(self, times, t)
        self.dropped_frames = int(self.dropped_frames)
        self.crc_errors = int(self.crc_errors)
        self.attrs = dict(self.attrs)

    @property
    def n_samples(self) -> int:
        """Number of taxel frames (rows of ``taxels``)."""
        return int(self.taxels.shape[0])

    @property
    def rate_hz(self) -> float:
        """Nominal sample rate, Hz (``layout.sample_rate_hz``)."""
        return self.layout.sample_rate_hz

    @property
    def duration_s(self) -> float:
        """``n_samples / rate_hz``, s."""
        return self.n_samples / self.layout.sample_rate_hz

    def host_rate_hz(self) -> float:
        """Device sample rate measured on the host clock over this trial's frames, frames/s
        (:func:`lower_envelope_rate_hz` of ``seq`` and ``host_time_s`` at ``layout.sample_rate_hz``); NaN with fewer
        than 6 samples."""
        assert self.seq is not None and self.host_time_s is not None
        return lower_envelope_rate_hz(self.seq, self.host_time_s, self.layout.sample_rate_hz)


def repeated_samples(taxels: np.ndarray) -> int:
    """Samples (rows of ``taxels``, (n_samples, n_channels)) identical on every channel to the one before: a held
    reading, counted like a dropped frame. 0 for one channel (a single ADC repeats its value by chance)."""
    x = np.asarray(taxels)
    if x.ndim != 2 or x.shape[1] < 2 or x.shape[0] < 2:
        return 0
    return int(np.count_nonzero(np.all(x[1:] == x[:-1], axis=1)))


def lower_envelope_rate_hz(seq: np.ndarray, host_time_s: np.ndarray, rate_hz: float) -> float:
    """A device's frame rate measured on the host clock, frames/s.

    A frame's host receive time is its true time plus a non-negative delivery delay (USB/OS batching,
    scheduling): ``t_k = t_0 + k / rate + d_k`` with ``d_k >= 0``, where ``k`` counts dropped frames too (from
    ``seq``). The rate comes from the lower envelope of ``(k, t_k)``, not a least-squares fit (which delays bias):
    the line below every frame that lies closest to them on average, i.e. the lower convex hull's edge above the
    mean frame index (minimising ``sum(t_k - line(k))`` under ``line(k) <= t_k`` puts the line on that edge). Its
    slope is exact as long as the frames stamped with the least delay around the middle of the history are not
    all late: a stretch of late deliveries at either end (a loaded host's reader stalled 0.2-1.7 s at a stream's
    start, seen under CI load) leaves it unmoved, where the earlier estimate (the least-delayed frame of the first
    and last thirds) read 1,390 Hz for a 1 kHz board when the whole first third came late. The taxel reader stamps
    a chunk as a fresh burst arrives (``rigctl.devices.taxel_stream``), and the runner measures over the stream's
    history up to a trial's end, not the trial alone.

    Parameters
    ----------
    seq : (n,) uint16, the device's frame sequence numbers (gaps = dropped frames; wrap at 65536)
    host_time_s : (n,) float64, host receive times, s (any origin)
    rate_hz : float, the nominal frame rate, Hz (the lag of each frame is taken against it; any value near the
        true rate gives the same result)

    Returns
    -------
    float
        frames/s; NaN with fewer than 6 frames or a history that does not move forward in time.
    """
    n = len(seq)
    if n < 6:
        return math.nan
    s = np.asarray(seq, dtype=np.int64)
    t = np.asarray(host_time_s, dtype=np.float64)
    steps = ((s[1:] - s[:-1]) & 0xFFFF).astype(np.int64)
    steps[steps == 0] = 1
    index = np.concatenate(([0], np.cumsum(steps))).astype(np.float64)
    lag = (t - t[0]) - index / float(rate_hz)  # delay + drift, relative to the nominal rate, s
    slope = _lower_hull_slope(index, lag, float(index.mean()), plausible=_PLAUSIBLE_RATE_ERROR / float(rate_hz))
    period = 1.0 / float(rate_hz) + slope
    return 1.0 / period if period > 0 else math.nan


#: a lower-hull edge whose lag slope is more than this fraction of a period per frame is delivery, not the device's
#: clock (a reader catching up after a stall reads the queued frames at once: slopes near -1 period per frame); a
#: board's clock is within +-0.5 % (resonator), a wrong crystal or firmware (e.g. 8 MHz for 16 MHz: -50 %) shows as
#: every edge outside this, and the estimate falls back to the whole hull
_PLAUSIBLE_RATE_ERROR = 0.2


def _lower_hull_slope(x: np.ndarray, y: np.ndarray, at: float, plausible: float = math.inf) -> float:
    """Slope of the lower convex hull of the points ``(x, y)`` (``x`` increasing) on the edge above ``x = at``.

    With ``plausible`` (a bound on ``|slope|``), ``at`` is moved to the middle of the longest run of consecutive
    hull edges within it (by ``x`` span), if there is one: a stretch of late points that holds ``at`` (a reader that
    stalled for more than half of the history, then read the queue at once: CI at load 8-10 read 2,268 Hz for a
    1 kHz board) does not then pick the edge.

    Candidates are the points on or below the end-to-end chord (every lower-hull vertex is), thinned to the convex
    hull's vertices by qhull (``scipy.spatial.ConvexHull``); Andrew's monotone chain then keeps the lower ones."""
    chord = y[0] + (y[-1] - y[0]) * (x - x[0]) / (x[-1] - x[0])
    resid = y - chord
    below = resid <= 0
    below[0] = below[-1] = True
    px, py = x[below], y[below]
    if len(px) > 64:  # qhull (scipy) thins the candidates to the hull's vertices; the chain below picks the lower ones
        from scipy.spatial import ConvexHull, QhullError

        span_y = float(np.ptp(py)) or 1.0
        try:
            vertices = np.sort(ConvexHull(np.column_stack(((px - px[0]) / (px[-1] - px[0]), (py - py[0]) / span_y))).vertices)
        except QhullError:  # collinear: every candidate is on the line
            vertices = np.array([0, len(px) - 1])
        px, py = px[vertices], py[vertices]
    hull: list[int] = []
    for i in range(len(px)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            # drop b if it is not strictly below the segment a -> i (cross product <= 0: a right turn or straight)
            if (px[b] - px[a]) * (py[i] - py[a]) - (py[b] - py[a]) * (px[i] - px[a]) <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    hx = px[hull]
    hy = py[hull]
    if math.isfinite(plausible) and len(hull) >= 2:
        ok = np.abs(np.diff(hy) / np.diff(hx)) <= plausible
        best, best_span, run_start = None, 0.0, None
        for e in range(len(ok) + 1):
            if e < len(ok) and ok[e]:
                if run_start is None:
                    run_start = e
            elif run_start is not None:
                span = float(hx[e] - hx[run_start])
                if span > best_span:
                    best, best_span = (run_start, e), span
                run_start = None
        if best is not None:
            at = 0.5 * float(hx[best[0]] + hx[best[1]])
    k = int(np.searchsorted(hx, at, side="right")) - 1
    k = min(max(k, 0), len(hull) - 2)
    i, j = hull[k], hull[k + 1]
    return float((py[j] - py[i]) / (px[j] - px[i]))
