"""The simulated operator: a person moving the paper's 3x3 finger along flat texture plates, tracked on the wrist.

The paper's real-time experiment (Results, "Real-time Texture Classification with Speed Invariant Representation";
Materials and Methods, "Real-time Texture Classification"): an operator moves a 3x3 sensor on a 3D-printed finger
across flat plates of textures A, B, D, L and N (300 x 36 mm, the middle 200 mm used) with one of five velocity
profiles (slow, medium, fast, slow-to-fast, fast-to-slow), "unconstrained" but purposefully varying the intended
profile; an infrared tracker (HTC Vive) on the wrist gives the position, from which the velocity is computed.

Here each scan is generated on a simulated clock (no real-time pacing): the finger is put down near the plate's
start, pressed, moved along the plate following the planned profile with the variability of a human hand, and
stopped near the plate's end. The taxel readings come from the rig's physical sensor model
(:meth:`rigctl.simulation.model.SensorModel.render`, its top layer: :data:`rigctl.core.sensor.PAPER_FINGER`) along
the finger's path at its pressure; the tracker samples the wrist at 90-120 Hz with timing jitter, position noise and
the occasional dropout (a lost sample or a short burst, as a Vive loses line of sight), in the tracker's own frame
(the plate lies along an arbitrary direction there: :meth:`SimulatedOperator.touch_ends` gives what touching the
finger to the plate's two ends reads, from which the rig calibrates the axis).

Human variability (:class:`OperatorConfig`, each figure a guess at a careful operator, documented as such):

- speed: a per-scan bias (lognormal, 12 %) and a slow wobble (Ornstein-Uhlenbeck, 10 %, 0.25 s), smoothed by the
  arm's response (80 ms);
- pauses: in 20 % of the scans the finger stops for 80-250 ms somewhere in the used part (hesitation);
- back-slips: half of those pauses (10 % of the scans) end with the finger sliding back 1-3 mm over 60-120 ms
  before it goes on (a hand resettling its grip): one or two 100 ms windows still or backward, which the rig
  scales with 0 mm/s (:data:`rigctl.core.handheld.SPEED_FLOOR_MM_S`) and counts (``floored_windows``);
- pressure: a per-scan level (500 g nominal, 15 %) and a drift within the scan (8 %, 0.8 s), which scales the
  readings through the model's force response;
- path: the finger wanders sideways (1.5 mm, 0.5 s), seen by the tracker and rolling the contact a little
  (taxel levels +-2 % per 1.5 mm).

A session (each :class:`SimulatedOperator` is one: its seed draws these once, from a generator of their own, so the
scans' other draws are unchanged; ``session_errors()`` gives them; set the four sizes to 0 for an exact one):

- ``touch_error_mm`` (1.5 mm sd per end): the plate's axis is calibrated by touching the fingertip to the plate's
  two ends (:meth:`SimulatedOperator.touch_ends`), placed by eye on a 36 mm wide plate's edge; a guess at a careful
  hand, stated. The two errors move the axis's origin by the start's error and scale it by the difference.
- ``strap_offset_mm`` (2 mm sd along the plate and sideways) and ``strap_rotation_deg`` (0.5 degree sd about the
  vertical): the tracker is strapped to the wrist again for each session and the calibration (the rig config's
  plate axis) is not redone, so the tracked point sits a little elsewhere on the hand. The tracker itself is
  sub-millimetre (Niehorster, Li and Lappe 2017); a strap on a wrist moves by millimetres (a guess, stated).
- ``session_speed_error`` (2 % sd): the session's tracked velocity is the fingertip's times 1 + b (about the used
  part's start: the wrist's lever, 100-150 mm, at a slightly different posture each session; 1.2 degrees of
  posture is 2 %), on top of ``tracker_speed_error``'s per-scan error.
- hesitations: the pauses and back-slips above (20 % and 10 % of the scans).

Together a session's plate-axis offset (``session_offset_mm``: where the rig reads the finger at the used part's
start minus where it is) has an sd of about 3 mm (2.7 mm from the touch and the strap, plus 1 mm from the speed bias
at the used part's end).

The tracker on the wrist (``tracker_speed_error``, 0 by default: the tracker follows the fingertip's path): the
paper's Vive tracker rides on the wrist, 100-150 mm behind the fingertip, so a wrist that bends or rolls during a
scan moves the tracker more or less than the fingertip: 3.8 degrees of wrist rotation over a 200 mm scan at a 150 mm
lever is a 5 % difference. The tracked velocity is then the fingertip's times 1 + e(t): e a per-scan bias (normal,
standard deviation ``tracker_speed_error``) plus a slow drift (Ornstein-Uhlenbeck, half that, 1 s). The tracker's own
error is far smaller (a Vive's position precision is sub-millimetre at rest: Niehorster, Li and Lappe 2017,
i-Perception 8(3)); the wrist's lever is the guess, stated as the parameter (results: 0, 5 and 10 %).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from rigctl.core.handheld import (
    PLATE_LENGTH_MM,
    USED_LENGTH_MM,
    USED_START_MM,
    PlateAxis,
    RawScan,
)
from rigctl.core.sensor import PAPER_FINGER, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import PlannedTrial
from rigctl.simulation.model import RigConfig, SensorModel
from rigctl.simulation.noise import one_pole
from rigctl.simulation.textures import get_texture

__all__ = ["OperatorConfig", "SimulatedOperator", "operator_passes", "plate_axis_of", "profile_speeds", "publish_tracker"]


@dataclass(frozen=True)
class OperatorConfig:
    """The simulated operator's hand and tracker (module docstring). Speeds relative, times s, lengths mm, forces g."""

    speed_bias: float = 0.12
    speed_bias_range: tuple[float, float] = (0.72, 1.38)  # keeps a scan within the plan's length check (0.5-2x)
    speed_wobble: float = 0.10
    speed_wobble_tau_s: float = 0.25
    arm_tau_s: float = 0.08
    pause_probability: float = 0.2
    pause_s: tuple[float, float] = (0.08, 0.25)
    slip_probability: float = 0.5  # of a pause ending in a slide back
    slip_mm: tuple[float, float] = (1.0, 3.0)
    slip_s: tuple[float, float] = (0.06, 0.12)
    pressure_g: float = 500.0
    pressure_spread: float = 0.15
    pressure_drift: float = 0.08
    pressure_drift_tau_s: float = 0.8
    path_wobble_mm: float = 1.5
    path_wobble_tau_s: float = 0.5
    path_contact_gain: float = 0.02  # relative taxel level per path_wobble_mm sideways
    start_mm: float = 15.0  # where the finger is put down
    stop_mm: float = 285.0  # where it is stopped
    press_s: float = 0.3  # pressed, still, before moving
    hold_s: float = 0.2  # still, after stopping
    tracker_rate_hz: tuple[float, float] = (90.0, 120.0)  # drawn once per operator (a tracker's fixed rate)
    tracker_jitter_s: float = 0.0015
    tracker_noise_mm: float = 0.3
    tracker_dropout: float = 0.01  # a lost sample
    tracker_burst: float = 0.002  # a burst of 5-25 lost samples starts
    tracker_speed_error: float = 0.0  # the wrist's velocity error: per-scan bias sd (relative), drift half that
    tracker_speed_drift_tau_s: float = 1.0
    frame_delay_s: float = 0.0005  # mean host receive delay of a taxel frame (exponential)
    # a session's errors (module docstring, "A session"): drawn once per operator (seed) from a generator of their own
    touch_error_mm: float = 1.5  # sd of each calibration touch along the plate (a fingertip put on an end by eye)
    strap_offset_mm: float = 2.0  # sd of the re-strapped tracker's offset along the plate (and sideways), mm
    strap_rotation_deg: float = 0.5  # sd of the re-strapped tracker frame's rotation about the vertical
    session_speed_error: float = 0.02  # sd of the session's tracked-velocity bias (the strap's lever), relative


def profile_speeds(planned: PlannedTrial) -> tuple[float, float]:
    """The intended speeds at the used part's start and end, mm/s: a ramp's ends, or the constant speed twice.
    Raises ValueError for a plan without a positive speed."""
    if planned.is_ramp:
        a, b = float(planned.ramp_start_mm_s), float(planned.ramp_end_mm_s)
    else:
        a = b = float(planned.speed_mm_s)
    if not (a > 0 and b > 0 and math.isfinite(a + b)):
        raise ValueError(f"trial {planned.trial_id}: the operator needs a positive intended speed, got {a:g}/{b:g}")
    return a, b


def _ou(rng: np.random.Generator, n: int, dt: float, tau_s: float, sd: float) -> np.ndarray:
    """(n,) Ornstein-Uhlenbeck noise of standard deviation ``sd`` and time constant ``tau_s`` at step ``dt``."""
    a = math.exp(-dt / tau_s)
    x0 = rng.standard_normal() * sd
    out = one_pole(math.sqrt(1 - a * a) * sd, a, rng.standard_normal(n))
    return np.asarray(out + x0 * a ** np.arange(1, n + 1), np.float64)


class SimulatedOperator:
    """A :class:`rigctl.core.handheld.ScanSource`: scans generated on a simulated clock (module docstring).

    Parameters
    ----------
    config : the hand and tracker (:class:`OperatorConfig`).
    seed : the random seed (every scan's variability, the tracker's rate, the plate's pose in the tracker's frame).
    rig_config : the physical model's configuration (the sensor model).
    textures : the plates' texture set (the paper's A-P; the paper used A, B, D, L, N).
    session_seed : the seed of the session's errors (module docstring, "A session"; None: ``seed``): two blocks of
        one session (a calibration block and the real-time block) share it.
    """

    layout: SensorLayout = PAPER_FINGER

    def __init__(self, config: OperatorConfig | None = None, *, seed: int = 0, rig_config: RigConfig | None = None,
                 textures: TextureSet | None = None, session_seed: int | None = None) -> None:
        self.config = config or OperatorConfig()
        self.seed = int(seed)
        self.rng = np.random.default_rng([self.seed, 3737])
        self.rig_config = rig_config or RigConfig()
        self.sensor = SensorModel(self.rig_config.sensor)
        self.textures = textures or PAPER_TEXTURES
        c = self.config
        self.tracker_rate_hz = float(self.rng.uniform(*c.tracker_rate_hz))
        # the plate in the tracker's frame: rotated about the vertical, offset (a lab's room coordinates, mm)
        self._yaw = float(self.rng.uniform(-math.pi, math.pi))
        self._origin = np.array([self.rng.uniform(-800, 800), self.rng.uniform(-800, 800), 850.0])
        # the session's errors (module docstring): a generator of their own, so the draws above stay as they were
        self.session_seed = self.seed if session_seed is None else int(session_seed)
        srng = np.random.default_rng([self.session_seed, 3738])
        self.touch_error_mm = (float(srng.normal(0.0, c.touch_error_mm)), float(srng.normal(0.0, c.touch_error_mm)))
        self.strap_offset_mm = (float(srng.normal(0.0, c.strap_offset_mm)), float(srng.normal(0.0, c.strap_offset_mm)))
        self.strap_rotation_rad = float(np.deg2rad(srng.normal(0.0, c.strap_rotation_deg)))
        self.session_speed_bias = float(srng.normal(0.0, c.session_speed_error))
        self.clock_s = 0.0  # the simulated host clock
        self.count = 0  # the taxel board's running frame count
        self.scans = 0

    # ------------------------------------------------------------------------------------------------- geometry
    def to_tracker(self, along_mm: np.ndarray, side_mm: np.ndarray) -> np.ndarray:
        """(k, 3) tracker-frame points (mm) of plate coordinates: along the plate and sideways, mm."""
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        x = np.asarray(along_mm, np.float64)
        y = np.asarray(side_mm, np.float64)
        return np.stack([self._origin[0] + c * x - s * y, self._origin[1] + s * x + c * y,
                         np.full(x.shape, self._origin[2])], axis=1)

    def session_tracked(self, along_mm: np.ndarray, side_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where this session's tracker reads a fingertip at plate coordinates (mm along, sideways) to be, in the
        calibration's plate coordinates (mm): the session's velocity bias about the used part's start, the
        re-strapped tracker's offset and its frame's rotation (module docstring, "A session")."""
        a = np.asarray(along_mm, np.float64)
        y = np.asarray(side_mm, np.float64)
        a = USED_START_MM + (a - USED_START_MM) * (1.0 + self.session_speed_bias)
        c, s = math.cos(self.strap_rotation_rad), math.sin(self.strap_rotation_rad)
        return (c * a - s * y + self.strap_offset_mm[0], s * a + c * y + self.strap_offset_mm[1])

    @property
    def session_offset_mm(self) -> float:
        """The session's plate-axis offset at the used part's start, mm: where the rig's calibrated axis (from
        :meth:`touch_ends`) reads the fingertip minus where it is (positive: the rig cuts early)."""
        e0, e1 = self.touch_error_mm
        a, _ = self.session_tracked(np.array([USED_START_MM]), np.zeros(1))
        scale = PLATE_LENGTH_MM / (PLATE_LENGTH_MM + e1 - e0)
        return float((a[0] - e0) * scale - USED_START_MM)

    def touch_ends(self, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """What the tracker reads while the finger touches the plate's start and then its end: two (n, 3) arrays
        of tracker-frame points, mm (the axis calibration's input; each end off along the plate by the session's
        touch error, :attr:`touch_error_mm`)."""
        c = self.config
        out = []
        for along, err in zip((0.0, PLATE_LENGTH_MM), self.touch_error_mm):
            pts = self.to_tracker(np.full(n, along + err), np.zeros(n))
            out.append(pts + self.rng.normal(0.0, c.tracker_noise_mm, pts.shape))
        return out[0], out[1]

    def describe(self) -> dict[str, Any]:
        """JSON-able: kind, seed, the operator and tracker settings, the tracker's rate."""
        return {"kind": "simulated_operator", "seed": self.seed, "operator": asdict(self.config),
                "tracker_rate_hz": self.tracker_rate_hz, "session": self.session_errors(),
                "sensor_layout": self.layout.to_dict()}

    def session_errors(self) -> dict[str, float | int]:
        """JSON-able: this session's drawn errors (mm, degrees, relative) and the plate-axis offset they make."""
        return {"session_seed": self.session_seed, "touch_error_start_mm": self.touch_error_mm[0],
                "touch_error_end_mm": self.touch_error_mm[1],
                "strap_offset_along_mm": self.strap_offset_mm[0], "strap_offset_side_mm": self.strap_offset_mm[1],
                "strap_rotation_deg": math.degrees(self.strap_rotation_rad),
                "session_speed_bias": self.session_speed_bias, "plate_offset_mm": self.session_offset_mm}

    def close(self) -> None:
        """Nothing to release (a simulation)."""

    # ------------------------------------------------------------------------------------------------- a scan
    def _path(self, planned: PlannedTrial, rng: np.random.Generator, dt: float) -> tuple[np.ndarray, dict]:
        """(n,) finger position along the plate (mm) every ``dt`` s, and the scan's intent and variability."""
        c = self.config
        v0, v1 = profile_speeds(planned)
        bias = float(np.clip(math.exp(c.speed_bias * rng.standard_normal()), *c.speed_bias_range))
        slowest = min(v0, v1) * c.speed_bias_range[0]
        max_n = int((c.press_s + c.hold_s + 2 * (c.stop_mm - c.start_mm) / slowest + 2.0) / dt)
        wobble = _ou(rng, max_n, dt, c.speed_wobble_tau_s, c.speed_wobble)
        pause_at = USED_START_MM + USED_LENGTH_MM * rng.uniform(0.2, 0.8)
        pause_s = rng.uniform(*c.pause_s) if rng.uniform() < c.pause_probability else 0.0
        # the slide back from a generator of its own (a child of the scan's seed): the other draws stay as they were
        srng = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])  # type: ignore[attr-defined]
        slip = srng.uniform() < c.slip_probability and pause_s > 0
        slip_mm = float(srng.uniform(*c.slip_mm)) if slip else 0.0
        slip_n = max(1, int(srng.uniform(*c.slip_s) / dt)) if slip else 0
        slip_step, slipped = slip_mm / max(slip_n, 1), 0
        # the step loop in Python floats and conditional expressions (numpy scalars and min/max calls cost several
        # times as much per step; the same IEEE double operations and choices as min(max(q, 0.0), 1.0) etc.)
        x, v, n_press = c.start_mm, 0.0, int(c.press_s / dt)
        path = [x] * n_press
        k, paused_until = n_press, -1
        a = dt / c.arm_tau_s
        wob, stop_mm, pausing = wobble.tolist(), c.stop_mm, bool(pause_s)
        used_start, used_mm = USED_START_MM, USED_LENGTH_MM
        while x < stop_mm - 0.05 and k < max_n:
            q = (x - used_start) / used_mm
            q = 0.0 if 0.0 > q else q
            p = 1.0 if 1.0 < q else q
            target = (v0 + (v1 - v0) * p) * bias * (1.0 + wob[k])
            slow = (stop_mm - x) / 20.0  # slowing down to stop at the end: min(1.0, max(0.08, slow))
            slow = slow if slow > 0.08 else 0.08
            target *= slow if slow < 1.0 else 1.0
            if pausing and paused_until < 0 and x >= pause_at:
                paused_until = k + int(pause_s / dt)
            if k < paused_until:
                target = 0.0
            if paused_until >= 0 and k >= paused_until and slipped < slip_n:  # the slide back, then on again
                x -= slip_step
                v = 0.0
                slipped += 1
                path.append(x)
                k += 1
                continue
            v += ((0.0 if 0.0 > target else target) - v) * a
            x += v * dt
            path.append(x)
            k += 1
        pos = np.empty(max_n)
        pos[:k] = path
        n = min(max_n, k + int(c.hold_s / dt))
        pos[k:n] = x
        return pos[:n], {"operator_speed_bias": bias, "operator_pause_s": float(pause_s),
                         "operator_pause_at_mm": float(pause_at) if pause_s else math.nan,
                         "operator_slip_mm": slip_mm}

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """One pass along the plate ``planned.texture`` with the profile of ``planned`` (what the rig's cue asked
        for). Returns the :class:`RawScan` (taxels of :attr:`layout` at 1 kHz on
        the simulated host clock, tracker samples, the scan's variability in ``attrs``); None when ``stop()``.
        Raises ValueError for a plan without a positive speed, KeyError for an unknown texture."""
        if stop is not None and stop():
            return None
        c, layout = self.config, self.layout
        rng = np.random.default_rng([self.seed, 3737, self.scans])
        self.scans += 1
        dt = 1.0 / layout.sample_rate_hz
        tex = get_texture(planned.texture, self.textures)
        pos, attrs = self._path(planned, rng, dt)
        n = pos.size
        pressure = c.pressure_g * math.exp(c.pressure_spread * rng.standard_normal())
        force = pressure * (1.0 + _ou(rng, n, dt, c.pressure_drift_tau_s, c.pressure_drift))
        n_press = int(c.press_s / dt)
        force[: n_press // 3] *= np.linspace(0.05, 1.0, n_press // 3) if n_press >= 3 else 1.0
        side = _ou(rng, n, dt, c.path_wobble_tau_s, c.path_wobble_mm)
        cfg = self.rig_config.sensor
        contact = np.exp(cfg.contact_level_spread * rng.standard_normal(self.sensor.gain.size))
        sensitivity = (1.0 + cfg.sensitivity_drift * rng.standard_normal()) * contact
        roll = 1.0 + c.path_contact_gain * side / max(c.path_wobble_mm, 1e-9)
        taxels = self.sensor.render(tex, pos, np.maximum(force * roll, 0.0), rng, sensitivity=sensitivity)
        taxels = np.ascontiguousarray(taxels[:, : layout.n_channels])
        t0 = self.clock_s
        t_frames = t0 + np.arange(n) * dt
        host_time = t_frames + rng.exponential(c.frame_delay_s, n)
        seq = ((self.count + np.arange(n)) % 65536).astype(np.uint16)
        self.count += n
        self.clock_s = t0 + n * dt + 0.5  # half a second between scans
        t_trk, xyz = self._tracker(rng, t0, n * dt, pos, side, dt)
        attrs.update(operator_pressure_g=float(pressure), tracker_rate_hz=self.tracker_rate_hz,
                     operator_texture=str(planned.texture), operator_profile=str(planned.profile))
        return RawScan(taxels=taxels, seq=seq, host_time_s=host_time, tracker_time_s=t_trk, tracker_xyz=xyz,
                       attrs=attrs)

    def tracker_pass(self, planned: PlannedTrial) -> tuple[np.ndarray, np.ndarray]:
        """The tracker's samples of one pass (as :meth:`scan`'s, without rendering the taxels: a motion source's
        view): times (k,) s from the pass's start and tracker-frame points (k, 3) mm. Raises ValueError as
        :meth:`scan`."""
        c = self.config
        rng = np.random.default_rng([self.seed, 3740, self.scans])
        self.scans += 1
        dt = 1.0 / self.layout.sample_rate_hz
        pos, _ = self._path(planned, rng, dt)
        side = _ou(rng, pos.size, dt, c.path_wobble_tau_s, c.path_wobble_mm)
        return self._tracker(rng, 0.0, pos.size * dt, pos, side, dt)

    def _tracker(self, rng: np.random.Generator, t0: float, span_s: float, pos: np.ndarray, side: np.ndarray,
                 dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The tracker's samples of a scan: times (s, host clock) and tracker-frame points (k, 3) mm."""
        c = self.config
        k = int(span_s * self.tracker_rate_hz)
        t = np.arange(k) / self.tracker_rate_hz + rng.normal(0.0, c.tracker_jitter_s, k)
        t = np.clip(np.sort(t), 0.0, span_s - dt)
        keep = rng.uniform(size=k) >= c.tracker_dropout
        for start in np.flatnonzero(rng.uniform(size=k) < c.tracker_burst):
            keep[start: start + int(rng.integers(5, 26))] = False
        t = t[keep]
        grid = np.arange(pos.size) * dt
        if c.tracker_speed_error > 0:  # the wrist's path (module docstring), from a generator of its own
            wrng = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])  # type: ignore[attr-defined]
            err = c.tracker_speed_error * wrng.standard_normal() + _ou(
                wrng, pos.size - 1, dt, c.tracker_speed_drift_tau_s, c.tracker_speed_error / 2)
            pos = np.concatenate([pos[:1], pos[0] + np.cumsum(np.diff(pos) * (1.0 + err))])
        along, sideways = self.session_tracked(np.interp(t, grid, pos), np.interp(t, grid, side))
        along = along + rng.normal(0.0, c.tracker_noise_mm, t.size)
        sideways = sideways + rng.normal(0.0, c.tracker_noise_mm, t.size)
        xyz = self.to_tracker(along, sideways)
        xyz[:, 2] += rng.normal(0.0, c.tracker_noise_mm, t.size)
        return t0 + t, xyz



#: the profiles the simulated operator's free-running passes take in turn: (name, start and end speed, mm/s)
PASS_PROFILES = (("slow", 40.0, 40.0), ("medium", 80.0, 80.0), ("fast", 120.0, 120.0), ("slow-to-fast", 40.0, 120.0),
                 ("fast-to-slow", 120.0, 40.0))
#: after a pass the finger returns to the plate's start in this long, then rests, s
RETURN_S, REST_S = 0.6, 0.4


def operator_passes(op: SimulatedOperator, textures: tuple[str, ...] = ("A", "B", "D", "L", "N"),
                    profiles: tuple[tuple[str, float, float], ...] = PASS_PROFILES,
                    ) -> Iterator[tuple[str, np.ndarray, np.ndarray, str]]:
    """The simulated operator's free-running passes (no cue: the ``profiles`` in turn, then the next plate):
    endless ``(label, t, xyz, texture)``: each pass's tracker sample times (k,) s from the pass's start and tracker-frame
    points (k, 3) mm, the finger's return to the start included (:data:`RETURN_S`); the next pass starts
    :data:`REST_S` after the last sample. The points lie along ``op.to_tracker``'s plate (:meth:`SimulatedOperator.
    touch_ends` calibrates its axis)."""
    k = 0
    while True:
        prof, a, b = profiles[k % len(profiles)]
        tex = textures[(k // len(profiles)) % len(textures)]
        ramp = (a, b) if a != b else (math.nan, math.nan)
        t, xyz = op.tracker_pass(PlannedTrial(k, tex, (a + b) / 2, 500.0, 200.0 / ((a + b) / 2), prof, *ramp))
        back_t = t[-1] + np.arange(1, int(RETURN_S * op.tracker_rate_hz)) / op.tracker_rate_hz
        back = op.to_tracker(np.linspace(op.config.stop_mm, op.config.start_mm, back_t.size), np.zeros(back_t.size))
        yield f"pass {k}: plate {tex}, {prof}", np.concatenate([t, back_t]), np.concatenate([xyz, back]), tex
        k += 1


def plate_axis_of(op: SimulatedOperator) -> PlateAxis:
    """The plate's axis in the operator's tracker frame (its two ends, noise-free)."""
    return PlateAxis.from_touches(op.to_tracker(np.zeros(1), np.zeros(1)),
                                  op.to_tracker(np.full(1, PLATE_LENGTH_MM), np.zeros(1)))


def publish_tracker(name: str, *, seconds: float, seed: int = 0, textures: tuple[str, ...] = ("A", "B", "D", "L", "N"),
                    stop: Callable[[], bool] | None = None, on_scan: Callable[[str], Any] | None = None,
                    on_pass: Callable[[str, np.ndarray, np.ndarray], Any] | None = None,
                    on_open: Callable[[], Any] | None = None) -> int:
    """Play the simulated operator in real time and publish its wrist tracker on LSL (stream ``name``, type
    "Position", 4 channels: x, y, z in the tracker's frame and the position along the plate, mm; at the tracker's
    90-120 Hz with its jitter and dropouts): :func:`operator_passes`, until ``seconds`` have passed or ``stop()``.
    The handheld rig takes it with ``--motion lsl:NAME`` (x, y, z: the plate axis in the rig config) or
    ``lsl:NAME@3`` (along the plate). ``on_scan(text)`` hears each pass begin; ``on_pass(texture, t, along_mm)``
    gets each pass before it plays: its sample times on ``pylsl.local_clock`` (s) and the positions along the plate
    (mm; the simulated finger's taxel board follows them: :class:`rigctl.simulation.finger_board.
    SimulatedFingerBoard`); ``on_open()`` is called once the stream can be resolved. Returns the samples pushed.
    Raises LslUnavailable."""
    from rigctl.core.lsl import require_pylsl

    pylsl = require_pylsl()
    op = SimulatedOperator(seed=seed)
    axis = plate_axis_of(op)
    info = pylsl.StreamInfo(name, "Position", 4, op.tracker_rate_hz, pylsl.cf_float32, f"rigctl-operator-{name}")
    chans = info.desc().append_child("channels")
    for label in ("x_mm", "y_mm", "z_mm", "along_plate_mm"):
        chans.append_child("channel").append_child_value("label", label).append_child_value("unit", "mm")
    outlet = pylsl.StreamOutlet(info)
    if on_open is not None:
        on_open()
    t0, pushed = pylsl.local_clock(), 0
    start = t0
    for label, t, xyz, texture in operator_passes(op, textures):
        if pylsl.local_clock() - t0 >= seconds or (stop is not None and stop()):
            break
        if on_scan is not None:
            on_scan(label)
        rows = np.column_stack([xyz, axis.along_mm(xyz)]).astype(np.float32)
        if on_pass is not None:
            on_pass(texture, start + t, rows[:, 3].astype(np.float64))
        for ti, row in zip(t, rows):
            while pylsl.local_clock() < start + ti:
                time.sleep(min(0.005, max(0.0, start + ti - pylsl.local_clock())))
            outlet.push_sample(row.tolist(), start + ti)
            pushed += 1
            if stop is not None and stop():
                break
        start += t[-1] + REST_S
    return pushed
