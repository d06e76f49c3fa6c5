"""Physical model of the texture drum rig: drum + stepper, actuator + spring + load cell, and the 3x3x2 taxel sensor.

This is the physics behind the simulated rig (the Mega's control logic - states, limits, watchdog, force PI loop -
lives in :mod:`rigctl.simulation.virtual_mega`) and behind the dataset generator (:mod:`rigctl.simulation.dataset`).

Sensor model (:class:`SensorModel`), following the paper's description of the sensor (Results; Materials and
Methods, "Tactile Texture Dataset - Force Invariance Module"): two layers of a 3x3 grid of piezoresistive taxels at
5 mm pitch; the top layer (type I) has a small receptive field, the bottom layer (type II) a larger and weaker one.
For each taxel at row ``r`` (row 0 = leading edge of the drum's travel, see docs/wire-protocol.md) the surface under
it is at plate coordinate ``(x - r * pitch) mod C`` where ``x`` is the drum's surface travel since the index mark
and ``C`` the drum circumference (the plate is fixed on the drum). Per sample and taxel:

1. Contact shape (:meth:`SensorModel.tables`, at the reference force ``reference_force_g``): the pad (a linear
   "Winkler" spring layer whose surface is smoothed by its thickness, ``pad_sigma_mm``) is pressed onto the plate;
   a flat plate would be indented by ``delta = indentation_ref_mm * F / indentation_ref_force_g``; on a textured
   plate the indentation of the ridge tops ``delta0`` follows from the force balance ``mean(max(0, delta0 -
   depth(x))) = delta`` and the local pressure is ``~ max(0, delta0 - depth(x))``. The pressure profile divided by
   its mean (``shape``, mean 1), smoothed by the layer's Gaussian receptive field, is the texture's signature.
   **The shape is force-invariant**, and the modulation depth grows a little faster than the level
   (``depth_level_exponent``): that is what the real FabricSlide recordings show (scripts/fit_fabricslide.py:
   across force setpoints the texture amplitude grows as level^1.2-1.5 and the spectrum keeps its shape;
   docs/results.md, "Sensor model fitted to FabricSlide"). An earlier model let the contact width change with force;
   the force coefficients (which
   equalise the mean SA rate) cannot undo a change of shape, which made every texture x condition cell a cluster
   of its own (issue 13).
2. Level: ``L = full_scale * layer_gain * eff_T(F) * S(p)`` with ``p = F / 9 * w_r`` the row's mean pressure
   (``w_r`` the row weight from the drum's curvature), ``S(p) = p / (p + p_half)`` the piezoresistive fabric's
   saturation (doubling the force does not double the signal: the non-linearity that eq. 1's force scaling undoes),
   and ``eff_T(F)`` (:meth:`SensorModel.contact_efficiency`) the plate's mean reading relative to a flat plate's:
   force concentrated on ridge crests saturates the fabric there, so ridged plates read lower on average.
3. ``adc = round(offset_i + gain_i * g_trial * L * (1 + m(F) * (shape(x - r * pitch) - 1)) + noise)`` clipped to
   0-1023 (10 bits); ``m(F)`` = :meth:`SensorModel.depth_factor`; ``gain_i`` / ``offset_i`` are the taxel's
   calibration spread (FabricSlide's per-taxel spread, fixed by ``SensorConfig.calibration_seed``), ``g_trial`` a
   slow sensitivity drift of the fabric, ``noise`` low-pass (AR(1), corner ``noise_corner_hz``) with
   ``noise_counts`` sd, scaled from FabricSlide's noise floor.

Time dilation with speed comes from ``x(t) = x0 + integral of v``: a texture of spatial period ``P`` read at speed
``v`` gives a temporal period ``P / v``.

All rendering is vectorised in one numba kernel (time-outer, the 18 channels inner) and runs at well over 10^7
samples per second per core.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import threading
from typing import Any

import numba
import numpy as np

from rigctl.core.drum import DRUM_DIAMETER_MM, DRUM_MARKS_PER_REV, DRUM_MICROSTEPS, DRUM_STEPS_PER_REV
from rigctl.core.sensor import PAPER_SENSOR
from rigctl.core.textures import TextureSet
from rigctl.devices import wire
from rigctl.simulation.mechanics import step_mechanics
from rigctl.simulation.mux_rc import MuxFrontEnd
from rigctl.simulation.textures import TEXTURES, Texture, get_texture

#: the model renders the paper's sensor (3x3 taxels, 2 layers: 18 channels), from its SensorLayout
N_ROWS = PAPER_SENSOR.layers[0].rows
N_COLS = PAPER_SENSOR.layers[0].cols
N_LAYERS = len(PAPER_SENSOR.layers)
N_TAXELS = PAPER_SENSOR.n_channels
ADC_MAX = wire.ADC_MAX  # 1023
_TABLE_SIZE = 2048  # points per texture period in the smoothed-height lookup tables


# ----------------------------------------------------------------------------------------------------------------
# configuration (JSON-able)
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class DrumConfig:
    """Drum and stepper.

    Attributes
    ----------
    diameter_mm : float
        Drum diameter, mm (surface speed = angular speed * diameter / 2).
    steps_per_rev, microsteps : int
        Stepper full steps per revolution and microstepping factor (step rate in microsteps/s).
    max_accel_mm_s2 : float
        Acceleration limit of the surface speed, mm/s^2 (the step generator's ramp).
    runout_mm : float
        Radial runout (eccentricity) of the drum, mm: a force ripple once per revolution.
    start_at_index : bool
        Whether a simulated dataset's trials start at the drum's index mark (True, the default: the first frame is
        the one flagged SYNC_IN, as :meth:`rigctl.acquisition.rig.Rig.record_trial` records, so the trials of one
        texture are phase-aligned) or at an arbitrary drum angle (False: the plate position at the first sample is
        uniform over the circumference, as on a rig whose recorder gets no index signal; the paper describes none).
        Issue 13: which of the two a rig does decides what its unscaled windows carry (docs/results.md, 1c).
    start_jitter_mm : float
        Sd of the plate position at a trial's first sample around the index mark, mm (``start_at_index``): the
        index sensor's repeatability and the plate's mounting; the 1 ms frame latch adds a uniform 0..v*1 ms.
    driver_microsteps : int or None
        The microstep setting of the drum's stepper driver (its DIP switches), None = ``microsteps`` (what the
        firmware assumes). Another value makes the drum turn at ``microsteps / driver_microsteps`` times the speed
        the step count says (a driver left at another setting): the fault the index sensor catches.
    index_sensor : bool
        Whether an index sensor (optical/Hall, docs/wire-protocol.md 2.6) is fitted: it marks the real drum's index
        mark; without one the controller marks the index by its step count.
    marks_per_rev : int
        Slots of the speed-mark disc on the drum (the firmware's RIGCTL_DRUM_MARKS_PER_REV, spec 2.6): the drum's
        speed and slip are measured once per slot; 0: no disc (and no slip check: the firmware has no such build, a
        rig without the disc latches DRUM_SLIP at its first RUN).
    """

    diameter_mm: float = DRUM_DIAMETER_MM
    steps_per_rev: int = DRUM_STEPS_PER_REV
    microsteps: int = DRUM_MICROSTEPS
    max_accel_mm_s2: float = 500.0
    runout_mm: float = 0.02
    start_at_index: bool = True
    start_jitter_mm: float = 0.2
    driver_microsteps: int | None = None
    index_sensor: bool = True
    marks_per_rev: int = DRUM_MARKS_PER_REV

    @property
    def circumference_mm(self) -> float:
        return math.pi * self.diameter_mm

    @property
    def true_steps_per_mm(self) -> float:
        """Step pulses per mm of real surface travel (the driver's real microstep setting)."""
        return self.steps_per_rev * self.true_microsteps / self.circumference_mm

    @property
    def true_microsteps(self) -> int:
        """The driver's real microstep setting (``driver_microsteps``, or ``microsteps`` when that is None)."""
        return self.microsteps if self.driver_microsteps is None else int(self.driver_microsteps)

    @property
    def steps_per_mm(self) -> float:
        """Microsteps per mm of surface travel (10.19 for the defaults)."""
        return self.steps_per_rev * self.microsteps / self.circumference_mm


@dataclasses.dataclass
class SensorConfig:
    """3x3x2 piezoresistive taxel sensor (see the module docstring for the equations).

    Attributes
    ----------
    pitch_mm : float
        Taxel spacing, mm (paper: 5 mm).
    rf_sigma_top_mm, rf_sigma_bottom_mm : float
        Gaussian receptive-field sd along the travel, mm (top = type I small, bottom = type II larger).
    layer_gain_top, layer_gain_bottom : float
        Relative sensitivity of the layers (bottom weaker).
    p_half_top_g, p_half_bottom_g : float
        Pressure per taxel (g) at which the reading reaches half of full scale (saturation constant): 50 / 80 g,
        near the mean taxel load at 500 g (55 g), so the smooth plate reads 35-70 % of full scale over 250-1000 g
        (doubling the force raises the reading by 1.3-1.6 x, not 2 x) and the pressure peaks on ridge crests
        (several times the mean) saturate - the non-linearity that eq. 1's force scaling has to undo.
    height_gain_per_mm : float
        Unused since the contact model (kept so that rig configs stored in older session files still load).
    pad_sigma_mm : float
        Smoothing of the pad surface by its own thickness, mm (Gaussian sd, 0.6 mm): the ~1.5 mm fabric +
        silicone pad cannot follow steps narrower than about its thickness, so rectangular ridges present sloped
        flanks.
    indentation_ref_mm, indentation_ref_force_g : float
        Pad indentation on a flat plate at the reference force (linear pad spring): 0.3 mm at 1000 g over the
        15 x 15 mm sensor (0.044 N/mm^2 for 0.3 mm: a Winkler modulus of ~0.15 N/mm^3, a soft fabric/silicone
        skin). Ridges 0.5-2 mm high are then taller than the indentation at the reference force (0.15 mm at
        500 g): the pad rests on the crests and the pressure is concentrated there, deeply modulated (the paper's
        Fig. 2C raster of texture L at 500 g swings the SA rate over the whole window). Only the reference force's
        contact shape is rendered (see ``depth_level_exponent``).
    row_weights : tuple of 3 float
        Pressure share of rows 0-2 (drum curvature: the centre row is pressed hardest).
    full_scale_counts : float
        Reading (ADC counts above offset) at infinite pressure and unit gain: 420, so that the most sensitive taxel
        of the spread below (gain ~1.9) reads ~540 counts on the flat plate at 1000 g and its ridge crests on tall
        or sparse plates stay just below the 10-bit ceiling (1023; paper: "10-bit resolution"); a typical taxel
        reads ~200 (top layer) / ~90 (bottom layer) counts above offset on the flat plate at 500 g.
    gain_spread, offset_mean_counts, offset_spread_counts : float
        Per-taxel calibration spread: gain ~ N(1, gain_spread) (clipped to 0.25-2), offset ~ N(offset_mean,
        offset_spread) counts (clipped to 0-250). Source: FabricSlide (scripts/fit_fabricslide.py), where each
        taxel's level follows ``a_i + b_i F`` (R^2 0.96) with gain CV sd(b)/mean(b) = 0.43 across its 16 taxels;
        the row weights above already give a CV of 0.11, so gain_spread = sqrt(0.43^2 - 0.11^2) = 0.42. Such a
        spread leaves a few weakly loaded taxels whose SA trains at 250 g are near the Izhikevich threshold: the
        paper's 62 of 4,320 force coefficients that did not converge below the cap of 5 (Methods) come from such
        low-activity trains, and the encoder reports how many do here.
    noise_counts : float
        Sd of the sample noise, ADC counts (Irwin-Hall(4) approximation of a Gaussian, low-pass filtered, see
        ``noise_corner_hz``). Source: FabricSlide's noise floor (least textured recording, 8-16 Hz): 0.094
        counts^2/Hz at a mean level of 182 counts (middle setpoint); scaled to this sensor's mean level at 500 g
        (146 counts above offset, both layers) it is 0.061 counts^2/Hz, which a first-order noise of corner 27 Hz
        carries with sd sqrt(S0 * pi * fc / 2) = 1.6 counts.
    noise_corner_hz : float
        Corner of the noise's first-order low-pass, Hz (0 = white at 1 kHz). Source: FabricSlide's floor is nearly
        flat up to its 17.9 Hz Nyquist limit (density 4-8 Hz / 8-16 Hz = 1.14), which a first-order spectrum
        ``1 / (1 + (f / fc)^2)`` gives for fc = 27 Hz; above 18 Hz nothing is measured, and the encoder's RA path
        (20 Hz low-pass) sees only this band.
    sensitivity_drift : float
        sd of the slow relative drift of the fabric's sensitivity, e.g. 0.01 = 1 % (an Ornstein-Uhlenbeck process,
        tau 20 s, in :class:`RigModel`; drawn independently per trial in the dataset generator). 1 %: the trials of
        one condition are recorded back to back within well under a minute, so their sensitivities differ by a
        fraction of the long-term drift.
    plate_level_spread : float
        Sd of a plate's static per-taxel level pattern (relative): each plate, mounted on the drum on its own, loads
        the 18 taxels a little differently (thickness, flatness, mounting), the same at every speed and force
        (:meth:`SensorModel.plate_pattern`, seeded by the plate's label and ``calibration_seed``). Source:
        FabricSlide, where each fabric's per-taxel level pattern (log trial mean minus its mean over the taxels)
        departs from the mean pattern with sd 0.026, a pattern stable across the 30 speed x force conditions
        (correlation 0.73), so that the 16 per-taxel means alone classify the fabrics (its README: ~99 %).
    contact_level_spread : float
        Sd of the per-trial, per-taxel level jitter (relative) from re-pressing the sensor at each trial (the
        dataset generator draws it per trial). Source: FabricSlide, the same pattern within one fabric and condition
        varies from trial to trial with sd 0.028.
    reference_force_g : float
        Force whose contact shape is rendered at every force, g (the paper's middle force, 500 g).
    depth_level_exponent : float
        The relative modulation depth grows with the level: depth ~ (S(F) / S(F_ref)) ** exponent, S the
        saturating response of the centre row (so the amplitude ~ level ** (1 + exponent)). Source: FabricSlide
        (scripts/fit_fabricslide.py), over the force setpoints 120-180 (210-250 carry the arm's ~2.2 Hz force-loop
        oscillation): amplitude ~ level^beta with beta = 1.19 (Canvas) and 1.54 (Linen), the two fabrics whose
        texture stands well above the noise; mean 1.37, so 0.37. The spectrum keeps its shape (tilt -0.2 per log
        level per log frequency, within what the loop's harmonics explain): the force changes the depth, not the
        shape.
    calibration_seed : int
        Seed of the per-taxel gain/offset spread (identifies "this physical sensor").
    """

    pitch_mm: float = 5.0
    rf_sigma_top_mm: float = 0.7
    rf_sigma_bottom_mm: float = 2.0
    layer_gain_top: float = 1.0
    layer_gain_bottom: float = 0.55
    p_half_top_g: float = 50.0
    p_half_bottom_g: float = 80.0
    height_gain_per_mm: float = 0.9
    pad_sigma_mm: float = 0.6
    indentation_ref_mm: float = 0.3
    indentation_ref_force_g: float = 1000.0
    row_weights: tuple[float, float, float] = (0.8, 1.0, 0.8)
    full_scale_counts: float = 420.0
    gain_spread: float = 0.42
    offset_mean_counts: float = 60.0
    offset_spread_counts: float = 30.0
    noise_counts: float = 1.6
    noise_corner_hz: float = 27.0
    sensitivity_drift: float = 0.01
    plate_level_spread: float = 0.026
    contact_level_spread: float = 0.028
    reference_force_g: float = 500.0
    depth_level_exponent: float = 0.37
    calibration_seed: int = 20240601


@dataclasses.dataclass
class MechanicsConfig:
    """Actuator, contact spring and load cell.

    Attributes
    ----------
    contact_gap_mm : float
        Actuator travel from home to first contact of drum and sensor, mm.
    contact_stiffness_g_per_mm : float
        Spring between actuator and sensor contact (sensor pad + mount compliance), g per mm of travel past contact:
        250 by default, the soft end of the 250-2000 g/mm (0.25-2 kg/mm) the firmware's default force-loop gains
        are tuned for (docs/firmware.md, "Force loop: step responses with the HX711's delay").
    actuator_max_speed_mm_s : float
        Actuator speed limit, mm/s (commands beyond it are clipped).
    actuator_travel_mm : float
        End of actuator travel, mm from home.
    loadcell_counts_per_g : float
        HX711 counts per gram (matches the LOADCELL_SCALE_X100 default 42000 of the register map).
    loadcell_offset_counts : int
        Raw HX711 reading at zero force (what TARE removes).
    loadcell_noise_g : float
        Load-cell reading noise sd, g.
    texture_ripple : float
        Relative contact-force ripple per mm of texture height under the contact line.
    hx711_rate_sps : float
        The HX711's output data rate with its on-chip oscillator: 10 (RATE pin low, what many boards ship with) or
        80 (RATE high, what the firmware's default gains are for). Avia HX711 datasheet, "Output Data Rate and
        Format". Each reading is the sinc^4-filtered force of the last four conversion periods (the datasheet's
        settling time: 4 periods after a step), available once per period (:meth:`RigModel.advance`).
    hx711_clock_error : float
        Relative error of the HX711's on-chip oscillator (the datasheet gives the rates only as "typical"), e.g.
        0.05 = 5 % fast; the conversion period is ``1 / (rate * (1 + error))``. Must be within +-0.2.
    actuator_reversed : bool
        The actuator motor's coil pair is swapped (a bench fault): a velocity towards the sensor moves it away and
        back again (:attr:`RigModel.actuator_sign` starts from it; the simavr harness's ``--actuator-reversed``).
    actuator_stall_g : float
        The contact force at which the actuator's motor stalls (skips its steps), g; 0 = never (the default, and in
        every safety test: the firmware's protection must not rely on it). A bench sets the driver's current so the
        motor stalls near 1.5 x the largest force (docs/hardware/wiring.md, "Driver current": I = Vref / (8 R_sense),
        Allegro A4988 datasheet, "Current Regulation"; DRV8825: I = Vref / (5 R_sense), TI DRV8825 datasheet 7.3.4;
        the screw's force F = 2 pi eta T / lead, torque about proportional to current). Modelled coarsely: the actuator
        does not advance past where the contact's spring carries this force (its runout and texture ripple aside);
        the step count the controller keeps goes on. The simavr harness's ``--actuator-stall-g``.
    """

    contact_gap_mm: float = 3.0
    contact_stiffness_g_per_mm: float = 250.0
    actuator_max_speed_mm_s: float = 8.0
    actuator_travel_mm: float = 20.0
    loadcell_counts_per_g: float = 420.0
    loadcell_offset_counts: int = 83_000
    loadcell_noise_g: float = 0.8
    texture_ripple: float = 0.02
    hx711_rate_sps: float = 80.0
    hx711_clock_error: float = 0.0
    actuator_reversed: bool = False
    actuator_stall_g: float = 0.0

    def __post_init__(self):
        if self.hx711_rate_sps not in (10.0, 80.0):
            raise ValueError(f"hx711_rate_sps must be 10 or 80 (the HX711's RATE pin), got {self.hx711_rate_sps}")
        if not -0.2 < self.hx711_clock_error < 0.2:
            raise ValueError(f"hx711_clock_error must be within +-0.2, got {self.hx711_clock_error}")
        if not 0 < self.contact_stiffness_g_per_mm <= wire.CONTACT_STIFFNESS_MAX_G_PER_MM:
            raise ValueError(f"contact_stiffness_g_per_mm must be > 0 and <= {wire.CONTACT_STIFFNESS_MAX_G_PER_MM:g} (the "
                             f"stiffest contact a rig config accepts), got {self.contact_stiffness_g_per_mm}")
        if self.actuator_stall_g < 0:
            raise ValueError(f"actuator_stall_g must be >= 0 (0: no stall), got {self.actuator_stall_g}")

    @property
    def hx711_period_s(self) -> float:
        """Time between two HX711 conversions (DOUT-ready edges), s."""
        return 1.0 / (self.hx711_rate_sps * (1.0 + self.hx711_clock_error))


@dataclasses.dataclass
class RigConfig:
    """The whole simulated rig. JSON-able: ``RigConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))``."""

    drum: DrumConfig = dataclasses.field(default_factory=DrumConfig)
    sensor: SensorConfig = dataclasses.field(default_factory=SensorConfig)
    mechanics: MechanicsConfig = dataclasses.field(default_factory=MechanicsConfig)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["sensor"]["row_weights"] = list(d["sensor"]["row_weights"])
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "RigConfig":
        """Build from :meth:`to_dict` output; missing keys take defaults.

        Raises
        ------
        TypeError
            On an unknown key (names the section and key).
        """
        d = dict(d or {})
        parts: dict[str, Any] = {}
        for name, klass in (("drum", DrumConfig), ("sensor", SensorConfig), ("mechanics", MechanicsConfig)):
            sub = dict(d.pop(name, None) or {})
            known = {f.name for f in dataclasses.fields(klass)}
            unknown = set(sub) - known
            if unknown:
                raise TypeError(f"unknown key(s) in rig config [{name}]: {sorted(unknown)}")
            if "row_weights" in sub:
                sub["row_weights"] = tuple(float(w) for w in sub["row_weights"])
            parts[name] = klass(**sub)
        if d:
            raise TypeError(f"unknown section(s) in rig config: {sorted(d)}")
        return cls(**parts)

    @classmethod
    def from_json(cls, text: str) -> "RigConfig":
        return cls.from_dict(json.loads(text))


# ----------------------------------------------------------------------------------------------------------------
# sensor
# ----------------------------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True, inline="always")
def _irwin_hall(state):  # pragma: no cover - compiled
    """One sample noise draw: advance the xorshift64 ``state`` (uint64), split it into four 16-bit uniforms and sum
    them (Irwin-Hall(4), centred and scaled to unit variance): (new state, draw)."""
    state ^= state << np.uint64(13)
    state ^= state >> np.uint64(7)
    state ^= state << np.uint64(17)
    s = state
    acc = 0.0
    for _ in range(4):
        acc += float(s & np.uint64(0xFFFF))
        s >>= np.uint64(16)
    return state, (acc * (1.0 / 65536.0) - 2.0) * math.sqrt(3.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _plate_x(x, wrap):  # pragma: no cover - compiled
    """``x % wrap`` (Python's float modulo, ``wrap`` > 0), bit for bit: the remainder is exact, so on the first turn
    it is ``x`` and on the second ``x - wrap`` (exact for wrap <= x < 2 wrap: Sterbenz's lemma); only other values
    (the live rig's later turns, negative or zero ones, NaN) take the division-based modulo, which cost ~30 % of
    :func:`_render_kernel` for every sample of every row."""
    if 0.0 < x < wrap:
        return x
    if wrap <= x < 2.0 * wrap:
        return x - wrap
    return x % wrap


@numba.njit(cache=True, nogil=True)
def _render_kernel(pos, force, tables, period, depth, eff, pitch, row_w, p_half, layer_gain, full_scale, gain, sens,
                   offset, noise_sd, noise_a, seed, wrap, out):  # pragma: no cover - compiled
    n_table = tables.shape[1]
    inv = n_table / period
    state = np.uint64(seed) | np.uint64(1)
    noise = np.zeros(out.shape[1])
    drive = math.sqrt(max(0.0, 1.0 - noise_a * noise_a))
    # start the low-pass noise in its stationary state
    for ch in range(out.shape[1]):
        state, noise[ch] = _irwin_hall(state)
    # what does not change from sample to sample, each the very product the loop computed (no fastmath: the same
    # roundings in the same order): a channel's gain times the sensitivity, a layer and row's scale up to the
    # pressure (``full_scale * layer_gain * eff``, left to right)
    gs = np.empty(out.shape[1])
    for ch in range(out.shape[1]):
        gs[ch] = gain[ch] * sens
    scale = np.empty((2, 3))
    for layer in range(2):
        for r in range(3):
            scale[layer, r] = full_scale * layer_gain[layer] * eff[layer, r]
    k0s = np.empty(3, np.int64)
    k1s = np.empty(3, np.int64)
    fracs = np.empty(3)
    ps = np.empty(3)
    for i in range(pos.shape[0]):
        f9 = force[i] / 9.0
        # each row's plate coordinate, table cell and pressure (the same for both layers: computed once a sample)
        for r in range(3):
            xr = pos[i] - r * pitch
            if wrap > 0.0:
                xr = _plate_x(xr, wrap)  # the plate is fixed on the drum, its pattern repeats per turn
            u = xr * inv
            k = math.floor(u)
            fracs[r] = u - k
            k0 = int(k) % n_table
            k1 = k0 + 1
            if k1 == n_table:
                k1 = 0
            k0s[r] = k0
            k1s[r] = k1
            p = f9 * row_w[r]
            if p < 0.0:
                p = 0.0
            ps[r] = p
        for layer in range(2):
            for r in range(3):
                frac = fracs[r]
                hs = tables[layer, k0s[r]] * (1.0 - frac) + tables[layer, k1s[r]] * frac
                rel = 1.0 + depth * (hs - 1.0)
                if rel < 0.0:
                    rel = 0.0
                p = ps[r]
                # level: saturating response to the mean taxel pressure, times the plate's contact efficiency;
                # modulation: the force-invariant contact shape (FabricSlide: depth proportional to the level)
                base = scale[layer, r] * p / (p + p_half[layer]) * rel
                for c in range(3):
                    ch = layer * 9 + r * 3 + c
                    state, z = _irwin_hall(state)  # AR(1) low-pass of unit-variance draws
                    noise[ch] = noise_a * noise[ch] + drive * z
                    v = offset[ch] + gs[ch] * base + noise_sd * noise[ch]  # (gain * sens: numpy's product)
                    v = math.floor(v + 0.5)
                    if v < 0.0:
                        v = 0.0
                    elif v > 1023.0:
                        v = 1023.0
                    out[i, ch] = np.uint16(v)


#: the bounds of :func:`render_seed`'s draw, [1, 2**63), as the 0-d arrays ``Generator.integers`` makes of them (made
#: once: the same draw, without two conversions a call)
_SEED_LOW, _SEED_HIGH = np.asarray(1), np.asarray(2**63)


def render_seed(rng: np.random.Generator) -> int:
    """The noise seed :meth:`SensorModel.render` draws from ``rng`` for one call (a step whose samples are not
    rendered draws it too: the generator's later draws stay the same): uniform in [1, 2**63)."""
    return int(rng.integers(_SEED_LOW, _SEED_HIGH))


def _profile(tex: Texture) -> np.ndarray:
    """Height profile over one period, supersampled (8 x the table size) so rectangular edges are resolved."""
    m = 8
    x = (np.arange(_TABLE_SIZE * m) + 0.5) / (_TABLE_SIZE * m) * tex.period_mm
    return tex.height(x)


def _smooth(h: np.ndarray, period: float, sigma: float, reduce: bool = True) -> np.ndarray:
    """Exact circular convolution of one period of a supersampled profile with a Gaussian of sd ``sigma`` (mm);
    ``reduce``: average down to the table size."""
    spec = np.fft.rfft(h)
    freq = np.fft.rfftfreq(h.size, d=period / h.size)  # cycles per mm
    out = np.fft.irfft(spec * np.exp(-0.5 * (2 * np.pi * freq * sigma) ** 2), n=h.size)
    return out.reshape(_TABLE_SIZE, -1).mean(axis=1) if reduce else out


class SensorModel:
    """The 3x3x2 taxel sensor pressed on a texture (equations in the module docstring).

    Parameters
    ----------
    config : SensorConfig, optional
        Defaults to ``SensorConfig()``.

    Attributes
    ----------
    gain : (18,) float64
        Per-taxel gain (calibration spread, seeded by ``config.calibration_seed``).
    offset : (18,) float64
        Per-taxel offset, ADC counts.
    """

    def __init__(self, config: SensorConfig | None = None):
        self.config = config or SensorConfig()
        c = self.config
        cal = np.random.default_rng(c.calibration_seed)
        self.gain = np.clip(cal.normal(1.0, c.gain_spread, N_TAXELS), 0.25, 2.0)
        self.offset = np.clip(cal.normal(c.offset_mean_counts, c.offset_spread_counts, N_TAXELS), 0.0, 250.0)
        self._row_w = np.asarray(c.row_weights, dtype=np.float64)
        self._p_half = np.array([c.p_half_top_g, c.p_half_bottom_g])
        self._layer_gain = np.array([c.layer_gain_top, c.layer_gain_bottom])
        # AR(1) coefficient of the low-pass sensor noise at the 1 kHz render rate
        self._noise_a = math.exp(-2.0 * math.pi * c.noise_corner_hz / 1000.0) if c.noise_corner_hz > 0 else 0.0
        self._last: tuple | None = None  # (texture, force step, tables, period, eff, depth, gain) of the last render
        self._tables: dict[tuple, tuple] = {}  # height, contact-shape and contact-depth tables by texture (, force)
        self._lock = threading.Lock()

    def height_tables(self, texture: Texture | str) -> tuple[np.ndarray, float, np.ndarray]:
        """Smoothed-height lookup tables of a texture for both layers.

        Returns
        -------
        tables : (2, 2048) float64
            Height (mm) over one period, convolved with the top / bottom receptive field (exact circular convolution).
        period_mm : float
            Length the table covers (1.0 for the smooth texture, whose table is zero).
        mean_mm : (2,) float64
            Mean height of each table (equal to the texture's mean height).
        """
        tex = get_texture(texture)

        def build():
            if tex.kind == "smooth":
                return np.zeros((2, _TABLE_SIZE)), 1.0, np.zeros(2)
            tables = self._layer_tables(_profile(tex), tex.period_mm)
            return tables, float(tex.period_mm), tables.mean(axis=1)

        return self._cached(("h", tex), build)

    def _cached(self, key: tuple, build):
        """``self._tables[key]``, built with ``build()`` (outside the lock) on the first call."""
        with self._lock:
            hit = self._tables.get(key)
        if hit is None:
            hit = build()
            with self._lock:
                self._tables[key] = hit
        return hit

    def _layer_tables(self, profile: np.ndarray, period_mm: float) -> np.ndarray:
        """(2, 2048): a supersampled one-period profile smoothed by the top and the bottom receptive field."""
        c = self.config
        return np.ascontiguousarray(np.stack([_smooth(profile, period_mm, s)
                                              for s in (c.rf_sigma_top_mm, c.rf_sigma_bottom_mm)]))

    def indentation_mm(self, force_g) -> np.ndarray:
        """Nominal pad indentation on a flat plate, mm: ``delta_ref * F / F_ref`` (linear pad spring), float64."""
        c = self.config
        return np.asarray(force_g, dtype=np.float64) * (c.indentation_ref_mm / c.indentation_ref_force_g)

    def tables(self, texture: Texture | str, force_g: float = 500.0) -> tuple[np.ndarray, float, np.ndarray]:
        """Contact-pressure shape tables of a texture at a contact force, for both layers.

        Contact model (Winkler pad): the pad surface, smoothed by its own thickness (``pad_sigma_mm``), is pressed
        onto the plate until its ridges are indented by ``delta0``; the local pressure is proportional to the local
        indentation ``max(0, delta0 - (hmax - h_pad(x)))``. ``delta0`` is solved from the force balance (mean
        indentation over a period = the flat-plate indentation :meth:`indentation_mm` of the force). The pressure
        profile divided by its mean (the *shape*, mean 1) is smoothed by each layer's receptive field. So the
        ridge height sets the depth of the pressure modulation (pad bottoming out in the gaps or not), the spacing
        its period, and the force changes both the level and (through the contact width) the shape, non-linearly.

        Parameters
        ----------
        texture : Texture or str
        force_g : float
            Contact force, g; quantised to 2 % steps (log scale, >= 10 g) for the cache.

        Returns
        -------
        tables : (2, 2048) float64
            Pressure / mean pressure over one period, for the top / bottom layer (1.0 everywhere on the smooth plate).
        period_mm : float
            Length the table covers (1.0 for the smooth texture).
        mean : (2,) float64
            ``[1, 1]``, the mean of each shape table.
        """
        tex = get_texture(texture)
        f = max(float(force_g), 10.0) if math.isfinite(float(force_g)) else 500.0
        fq = round(math.log(f) / math.log(1.02))

        def build():
            if tex.kind == "smooth":
                return np.ones((2, _TABLE_SIZE)), 1.0, np.ones(2)
            depth, delta0_of = self._contact_depth(tex)
            shape = np.maximum(0.0, delta0_of(float(self.indentation_mm(1.02 ** fq))) - depth)
            shape /= shape.mean()
            return self._layer_tables(shape, tex.period_mm), float(tex.period_mm), np.ones(2)

        return self._cached(("p", tex, fq), build)

    def _contact_depth(self, tex: Texture):
        """The pad's depth below its first contact over one period of ``tex`` (mm, supersampled), and the solver of
        the force balance ``mean(max(0, delta0 - depth)) = delta`` for ``delta0`` (exact: the left side is
        piecewise linear and increasing in ``delta0``, so with the depths sorted it is one ``searchsorted``).
        Cached per texture: the tables of every force step of a press share it."""
        def build():
            pad = _smooth(_profile(tex), tex.period_mm, self.config.pad_sigma_mm, reduce=False)
            depth = pad.max() - pad  # >= 0: how far below the pad's first contact each point is
            s = np.sort(depth)
            cs = np.cumsum(s)
            n = s.size
            below = (np.arange(n) * s - np.concatenate(([0.0], cs[:-1]))) / n  # the mean at delta0 = s[k]

            def delta0_of(delta: float) -> float:
                k = int(np.searchsorted(below, delta, side="right"))  # depths <= delta0 (>= 1 for delta > 0)
                return float((delta * n + cs[k - 1]) / k)

            return depth, delta0_of

        return self._cached(("depth", tex), build)

    def render(self, texture: Texture | str, position_mm, force_g, rng: np.random.Generator, *,
               sensitivity: float | np.ndarray = 1.0, out: np.ndarray | None = None, wrap_mm: float | None = None) -> np.ndarray:
        """Render taxel readings.

        Parameters
        ----------
        texture : Texture or str
            The plate on the drum (a Texture, or a label of the paper's A-P set).
        position_mm : (n,) array_like of float
            Drum surface travel under the sensor's row 0 at each sample, mm (unwrapped; phase included).
        force_g : (n,) array_like or float
            Contact force at each sample, g (negative values are treated as 0).
        rng : numpy.random.Generator
            Source of the noise (one 63-bit seed is drawn per call, so a seeded generator reproduces the output).
        sensitivity : float or (18,) array of float
            Sensitivity factor of the fabric (the trial-to-trial drift, and per taxel the contact jitter), 1.0 =
            nominal.
        out : (n, 18) uint16 array, optional
            Written in place if given.
        wrap_mm : float, optional
            Drum circumference, mm: the surface under each taxel row is at plate coordinate
            ``(position - row * pitch) mod wrap_mm`` (the plate is fixed on the drum, so the pattern is the same at
            each pass of the index mark; position 0 = the index mark). None: no wrap (an endless plate).

        Returns
        -------
        (n, 18) uint16
            ADC counts 0-1023, channels 0-8 top layer, 9-17 bottom layer, row-major (docs/wire-protocol.md).

        Raises
        ------
        ValueError
            If ``position_mm`` is not 1-D or ``force_g`` does not broadcast to its length.
        """
        pos = np.ascontiguousarray(position_mm, dtype=np.float64)
        if pos.ndim != 1:
            raise ValueError(f"position_mm must be 1-D, got shape {pos.shape}")
        n = pos.shape[0]
        if isinstance(force_g, np.ndarray) and force_g.dtype == np.float64 and force_g.shape == (n,):
            force = np.ascontiguousarray(force_g)  # the live rig's case, a few ms at a time: no broadcast
        else:
            force = np.ascontiguousarray(np.broadcast_to(np.asarray(force_g, dtype=np.float64), (n,)))
        if out is None:
            out = np.empty((n, N_TAXELS), dtype=np.uint16)
        elif out.shape != (n, N_TAXELS) or out.dtype != np.uint16:
            raise ValueError(f"out must be ({n}, {N_TAXELS}) uint16")
        c = self.config
        # (np.mean's sum and division; np.add.reduce: force.sum()'s own reduction without its Python layer)
        f_mean = float(np.add.reduce(force)) / n if n else c.reference_force_g
        # the contact shape is that of the reference force (force-invariant, FabricSlide); the force sets the
        # level (per sample, saturating), the plate's contact efficiency and the depth (at the chunk's mean force).
        # The live rig renders 1 ms at a time: the last texture and force step's tables are kept at hand.
        fq = round(math.log(max(f_mean if math.isfinite(f_mean) else c.reference_force_g, 10.0)) / math.log(1.02))
        last = self._last
        if last is None or last[0] is not texture or last[1] != fq:
            tables, period, _ = self.tables(texture, c.reference_force_g)
            # both at the force step (2 %), so the output depends on the inputs only, not on earlier calls
            last = (texture, fq, tables, period, self.contact_efficiency(texture, f_mean),
                    float(self.depth_factor(1.02 ** fq)), self.gain * self.plate_pattern(texture))
            self._last = last
        _, _, tables, period, eff, depth, gain = last
        seed = render_seed(rng)
        if isinstance(sensitivity, (int, float)):  # (the live rig's): the kernel multiplies each gain, no array a call
            sens = float(sensitivity)
        else:
            gain, sens = gain * np.asarray(sensitivity, dtype=np.float64), 1.0
        _render_kernel(pos, force, tables, period, depth, eff, float(c.pitch_mm), self._row_w, self._p_half,
                       self._layer_gain, float(c.full_scale_counts), gain, sens,
                       self.offset, float(c.noise_counts), self._noise_a, seed, float(wrap_mm or 0.0), out)
        return out

    def plate_pattern(self, texture: Texture | str) -> np.ndarray:
        """The plate's static per-taxel level factors, (18,) float64, ``exp(N(0, plate_level_spread))`` seeded by
        the plate's label and ``calibration_seed`` (the same plate always loads the taxels the same way)."""
        tex = get_texture(texture)

        def build():
            c = self.config
            if c.plate_level_spread <= 0:
                return np.ones(N_TAXELS)
            key = int.from_bytes(hashlib.sha256(tex.label.encode("utf-8")).digest()[:8], "little")
            rng = np.random.default_rng([c.calibration_seed, key])
            return np.exp(rng.normal(0.0, c.plate_level_spread, N_TAXELS))

        return self._cached(("plate", tex.label), build)

    def depth_factor(self, force_g: float) -> float:
        """Relative modulation depth at ``force_g`` against the reference force: ``(S(F) / S(F_ref)) **
        depth_level_exponent`` with ``S(F) = p / (p + p_half_top)``, ``p = F / 9`` (FabricSlide: amplitude ~
        level^1.37)."""
        c = self.config
        f = max(float(force_g), 1e-3) if math.isfinite(float(force_g)) else c.reference_force_g

        def sat(force):
            p = force / 9.0
            return p / (p + c.p_half_top_g)

        return (sat(f) / sat(c.reference_force_g)) ** c.depth_level_exponent

    def contact_efficiency(self, texture: Texture | str, force_g: float) -> np.ndarray:
        """The plate's mean reading relative to a flat plate's at the same force, per layer and row: (2, 3) float64.

        ``mean_x S(p * shape(x)) / S(p)`` with ``S(p) = p / (p + p_half)`` the saturating response and ``p = F / 9 *
        w_r`` the row's mean pressure: the force concentrated on ridge crests saturates the fabric there, so a
        ridged plate reads lower on average than the flat one, the more so the taller and sparser its ridges and the
        higher the force. 1.0 for the smooth plate. Cached per texture and force (2 % steps).
        """
        tex = get_texture(texture)
        f = max(float(force_g), 10.0) if math.isfinite(float(force_g)) else 500.0
        fq = round(math.log(f) / math.log(1.02))

        def build():
            if tex.kind == "smooth":
                return np.ones((2, N_ROWS))
            tables, _, _ = self.tables(tex, self.config.reference_force_g)
            p = 1.02 ** fq / 9.0 * self._row_w  # (3,)
            eff = np.empty((2, N_ROWS))
            for layer in range(2):
                ph = self._p_half[layer]
                sat = p[:, None] * tables[layer][None, :]
                eff[layer] = (sat / (sat + ph)).mean(axis=1) / (p / (p + ph))
            return eff

        return self._cached(("eff", tex, fq), build)

    def contact_height(self, texture: Texture | str, position_mm, wrap_mm: float | None = None) -> np.ndarray:
        """Smoothed (bottom-layer) texture height under the centre row minus its mean, mm: drives the load-cell ripple.

        ``position_mm``: (n,) plate coordinates, or with ``wrap_mm`` (> 0, the drum's circumference) drum travel,
        taken modulo ``wrap_mm`` first (numpy's ``np.mod``, bit for bit); the wrapped positions must be finite. The
        wrapped case runs in one compiled loop (:func:`_contact_height_kernel`: the dataset renderer's, ~0.12 ms a
        6,000-sample trial in numpy's passes), the same numbers as ``contact_height(texture, np.mod(position_mm,
        wrap_mm))``. Returns (n,) float64."""
        tables, period, hmean = self.height_tables(texture)
        if wrap_mm is not None:
            pos = np.ascontiguousarray(position_mm, dtype=np.float64).reshape(-1)
            out = np.empty_like(pos)
            _contact_height_kernel(pos, float(wrap_mm), float(self.config.pitch_mm), float(period), tables[1],
                                   float(hmean[1]), out)
            return out
        x = (np.asarray(position_mm, dtype=np.float64) - self.config.pitch_mm) / period * tables.shape[1]
        idx = np.floor(x).astype(np.int64) % tables.shape[1]
        return tables[1, idx] - hmean[1]


@numba.njit(cache=True, nogil=True)
def _contact_height_kernel(pos, wrap, pitch, period, table, mean, out):  # pragma: no cover - compiled
    """:meth:`SensorModel.contact_height` of finite drum travel ``pos`` wrapped at ``wrap`` > 0, into ``out``: each
    step numpy's of the same value in the same order (Python's float modulo is numpy's ``np.mod``; the table cell
    ``floor(x)`` as an integer modulo the table's length, as ``astype(np.int64) % n``)."""
    n_table = table.shape[0]
    for i in range(pos.shape[0]):
        x = (pos[i] % wrap - pitch) / period * n_table
        out[i] = table[int(math.floor(x)) % n_table] - mean


# ----------------------------------------------------------------------------------------------------------------
# whole rig mechanics
# ----------------------------------------------------------------------------------------------------------------
class RigModel:
    """Mechanics of the rig, advanced in 1 ms steps by the virtual boards. Thread-safe (one lock).

    Parameters
    ----------
    config : RigConfig, optional
    seed : int
        Seeds the noise, the drum's start angle and runout phase.

    Notes
    -----
    The drum: a commanded microstep rate (Hz, signed) becomes a target surface speed; the actual speed approaches it
    at ``drum.max_accel_mm_s2``. The surface travel integrates the speed; an index pulse (``sync_in``) marks each
    pass of the drum's index mark (angle 0). The actuator integrates a commanded velocity (clipped to its speed
    limit and travel); past ``contact_gap_mm`` a spring of ``contact_stiffness_g_per_mm`` presses drum and sensor
    together; the contact force also carries the drum's runout ripple and a small texture ripple. The load cell
    reads that force with noise. The Mega's control logic is not here.
    """

    def __init__(self, config: RigConfig | None = None, seed: int = 0):
        self.config = config or RigConfig()
        self.sensor = SensorModel(self.config.sensor)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        circ = self.config.drum.circumference_mm
        self._texture = TEXTURES["A"]
        self._position_mm = float(self._rng.uniform(0.0, circ))  # surface travel since angle 0 of revolution 0
        self._start_rev = math.floor(self._position_mm / circ)
        self._speed_mm_s = 0.0
        self._actuator_mm = 0.0
        self._plate_gap_mm = self.config.mechanics.contact_gap_mm  # where the rig's plates' surface is (a swap's)
        self._force_g = 0.0
        self._runout_phase = float(self._rng.uniform(0.0, 2 * np.pi))
        self._sensitivity = 1.0
        self._time_s = 0.0
        self._loadcell_g = 0.0
        self._mass_on_loadcell_g = 0.0  # a calibration mass resting on the load cell (place_mass)
        # HX711: force on the cell, one sample per ms (newest last), and the conversions so far
        self._hx_period_s = self.config.mechanics.hx711_period_s
        self._hx_weights = sinc4_weights(self._hx_period_s * 1000.0)
        self._hx_hist = np.zeros(4 * _HX_HISTORY_MS)
        self._hx_fill = _HX_HISTORY_MS
        self._hx_next_s = self._hx_period_s
        self._hx_conversions = 0
        self._hx_last_s = 0.0
        #: fault-injection hooks (rigctl.simulation.faults): the load cell mounted reversed (-1), the actuator's
        #: motor wired reversed (-1), the drum blocked (True: it turns no further whatever the stepper is told), the
        #: drum slipping (the fraction of the stepper's travel it loses: a loose coupling, 0.2 = 20 %)
        self.loadcell_sign = 1
        self._hx_frozen_raw: int | None = None  # the HX711's output frozen at this raw value (fault injection)
        self.actuator_sign = -1 if self.config.mechanics.actuator_reversed else 1
        self.drum_blocked = False
        self.drum_slip = 0.0
        #: the drum motor's direction: -1 turns it backwards (a swapped coil pair: fault injection)
        self.drum_sign = 1
        #: the load cell's signal against its calibration (cell-gain) and its zero's move, g (cell-offset)
        self.loadcell_gain = 1.0
        self.loadcell_offset_g = 0.0
        #: the home switch: None works (closed at home), True stuck closed (its wire shorted), False never closes
        self.home_switch_stuck: bool | None = None
        #: the actuator's coupling slips this fraction of the motor's travel (wound up, caught up at once when the
        #: motor has held still ACTUATOR_CATCHUP_MS) and the motor loses this fraction of its steps for good
        self.actuator_slip = 0.0
        self.actuator_lost = 0.0
        self._windup_mm = 0.0
        self._still_ms = 0
        #: each bit the controller reads on the HX711's DOUT flips with this probability (hx711-dout-noise)
        self.hx711_dout_noise = 0.0
        self._hx_flip_mask = 0
        #: the drivers' EN input stuck active (they drive whatever EN says): the physics moves as commanded; a
        #: controller's commanded motion is what moves (the model's controller commands none while it disables them)
        self.driver_enable_stuck = False
        self._motor_mm = 0.0  # the stepper's travel since construction, mm of surface (slip not included)
        #: of the last :meth:`advance`, per ms: the stepper's travel at its end (mm of surface, since construction)
        #: and whether a speed mark (``drum.marks_per_rev`` per revolution of the real drum) passed in it
        self.last_stepper_mm = np.zeros(0)
        self.last_marks = np.zeros(0, bool)
        self._step_consts: tuple | None = None  # the config's numbers advance uses (_read_step_consts)
        self._heights: tuple = (None,)  # (texture, its bottom-layer height table, period, mean) for the mechanics
        #: the taxels' analog path into the Uno's ADC (source impedance, anti-alias RC, the mux; ideal until a
        #: source impedance is set: ``--inject taxel-ohm=N``)
        self.front_end = MuxFrontEnd(N_TAXELS, adc_max=ADC_MAX)

    # -- properties ------------------------------------------------------------------------------------------------
    @property
    def contact_stiffness_g_per_mm(self) -> float:
        """Force gained per mm of actuator travel past contact, g/mm (dF/dx of the plant; for tuning a force loop)."""
        return self.config.mechanics.contact_stiffness_g_per_mm

    @property
    def texture(self) -> Texture:
        with self._lock:
            return self._texture

    def set_texture(self, letter: str | Texture, textures: TextureSet | None = None) -> None:
        """Mount a texture plate: a label of ``textures`` (default: the paper's A-P) or a :class:`Texture`
        (:func:`rigctl.simulation.textures.get_texture`). Raises KeyError on a label outside the set."""
        tex = get_texture(letter, textures)
        self.sensor.tables(tex)  # build outside the physics step
        with self._lock:
            self._texture = tex

    @property
    def time_s(self) -> float:
        """Simulated time since construction, s."""
        with self._lock:
            return self._time_s

    @property
    def force_g(self) -> float:
        """Load-cell force (tared), g, with reading noise: the latest HX711 conversion (contact force + any
        calibration mass, sinc^4-filtered over the last four conversion periods; ``MechanicsConfig.hx711_rate_sps``)."""
        with self._lock:
            return self._loadcell_g

    @property
    def hx711_conversions(self) -> int:
        """HX711 conversions (DOUT-ready edges) since construction; :attr:`force_g` changes only with a new one."""
        with self._lock:
            return self._hx_conversions

    @property
    def hx711_last_conversion_s(self) -> float:
        """Simulated time of the latest HX711 conversion, s (what a firmware timing the DOUT edges sees)."""
        with self._lock:
            return self._hx_last_s

    def ms_to_next_conversion(self) -> int:
        """Whole ms until the 1 ms step in which the next HX711 conversion completes (>= 1)."""
        with self._lock:
            return max(1, math.ceil((self._hx_next_s - self._time_s) * 1000.0 - 1e-9))

    def step_start(self) -> tuple[int, float, float, float]:
        """What a controller reads before each :meth:`advance`, under one lock: (:meth:`ms_to_next_conversion`,
        :attr:`time_s` s, :attr:`stepper_travel_mm`, :attr:`actuator_mm`)."""
        with self._lock:
            return (max(1, math.ceil((self._hx_next_s - self._time_s) * 1000.0 - 1e-9)), self._time_s, self._motor_mm,
                    self._actuator_mm)

    @property
    def contact_force_g(self) -> float:
        """True contact force at the end of the last step, g (no load-cell noise)."""
        with self._lock:
            return self._force_g

    @property
    def loadcell_raw(self) -> int:
        """Raw HX711-like counts: ``loadcell_offset_counts + round(force_g * loadcell_counts_per_g)`` (signed 24-bit);
        while frozen (:meth:`freeze_hx711`), the value it froze at."""
        m = self.config.mechanics
        with self._lock:
            if self._hx_frozen_raw is not None:
                return self._hx_frozen_raw
            g = self._loadcell_g * self.loadcell_gain + self.loadcell_offset_g
            raw = m.loadcell_offset_counts + self.loadcell_sign * int(round(g * m.loadcell_counts_per_g))
            raw = max(-(1 << 23), min((1 << 23) - 1, raw))
            if self._hx_flip_mask:  # DOUT bit errors: the 24 bits as read, two's complement
                raw = ((raw & 0xFFFFFF) ^ self._hx_flip_mask)
                raw = raw - (1 << 24) if raw & 0x800000 else raw
        return raw

    @property
    def home_switch_closed(self) -> bool:
        """The home switch as its wire reads: closed at home (actuator <= 0) unless stuck (:attr:`home_switch_stuck`)."""
        with self._lock:
            if self.home_switch_stuck is not None:
                return bool(self.home_switch_stuck)
            return self._actuator_mm <= 1e-6

    def freeze_hx711(self, frozen: bool) -> None:
        """Fault injection (``hx711-frozen``): the HX711's output freezes at its latest conversion's raw value (the
        conversions go on at their rate, the same 24 bits each), or thaws."""
        raw = None
        if frozen:
            self._hx_frozen_raw = None
            raw = self.loadcell_raw
        with self._lock:
            self._hx_frozen_raw = raw

    def set_contact_stiffness(self, g_per_mm: float) -> None:
        """Fault injection (``contact-stiffness=G_PER_MM``): the contact's stiffness becomes ``g_per_mm`` g/mm (> 0)
        from the next step. Off the contact it is a plate swap: the new plate's surface where the rig's own plate's
        is (``contact_gap_mm`` as configured). Under load the force is continuous: a plate cannot be swapped while
        pressed, and what changes a contact's stiffness under load (a soft layer bottoming out, a mount settling)
        changes how the force grows with further travel, not the force where the actuator stands; the spring's
        zero-force point moves so the force there is the same. ValueError."""
        k = float(g_per_mm)
        if not 0 < k <= wire.CONTACT_STIFFNESS_MAX_G_PER_MM:
            raise ValueError(f"contact stiffness must be > 0 and <= {wire.CONTACT_STIFFNESS_MAX_G_PER_MM:g} g/mm (the "
                             f"stiffest contact a rig config accepts), got {g_per_mm}")
        with self._lock:
            m = self.config.mechanics
            own_gap = self._plate_gap_mm
            pressed = self._actuator_mm - m.contact_gap_mm
            gap = self._actuator_mm - pressed * m.contact_stiffness_g_per_mm / k if pressed > 0 else own_gap
            self.config = dataclasses.replace(
                self.config, mechanics=dataclasses.replace(m, contact_stiffness_g_per_mm=k, contact_gap_mm=gap))
            self._step_consts = None  # read again at the next step

    def _slip(self) -> float:
        return 1.0 if self.drum_blocked else min(1.0, max(0.0, float(self.drum_slip)))

    @property
    def drum_speed_mm_s(self) -> float:
        """Actual (real) drum surface speed, mm/s (signed): the stepper's, less any slip."""
        with self._lock:
            return self._speed_mm_s * self.drum_sign * (1.0 - self._slip())

    @property
    def stepper_speed_mm_s(self) -> float:
        """The drum stepper's surface speed, mm/s (signed): its step rate through the acceleration ramp at the
        driver's real microstep setting, what the drum would do without slip."""
        with self._lock:
            return self._speed_mm_s

    @property
    def stepper_travel_mm(self) -> float:
        """The drum stepper's travel since construction, mm of surface (without slip; :attr:`stepper_speed_mm_s`
        integrated)."""
        with self._lock:
            return self._motor_mm

    @property
    def position_mm(self) -> float:
        """Unwrapped drum surface travel, mm."""
        with self._lock:
            return self._position_mm

    @property
    def angle_deg(self) -> float:
        """Drum angle since the index mark, degrees in [0, 360)."""
        circ = self.config.drum.circumference_mm
        with self._lock:
            return (self._position_mm % circ) / circ * 360.0

    @property
    def revolutions(self) -> int:
        """Completed revolutions (index passes) since construction (negative when turned backwards)."""
        circ = self.config.drum.circumference_mm
        with self._lock:
            return math.floor(self._position_mm / circ) - self._start_rev

    @property
    def actuator_mm(self) -> float:
        """Actuator position from home, mm (positive towards the sensor)."""
        with self._lock:
            return self._actuator_mm

    @property
    def actuator_motor_mm(self) -> float:
        """The actuator motor's position as the lead screw travel it turns, mm from home (positive towards the sensor):
        :attr:`actuator_mm` plus the coupling's wind-up (``coupling-slip``: the motor turned, the screw stayed). It
        moves only by the steps the motor really takes (a swapped coil pair's the other way; lost steps, a stall and
        the rear stop move it not); a wound coupling's catch-up moves the screw and not it. The truth log's
        ``motor_mm``: what the controller's own steps moved (the campaign's step-after-latch judge)."""
        with self._lock:
            return self._actuator_mm + self._windup_mm

    def place_mass(self, mass_g: float) -> None:
        """Rest a calibration mass of ``mass_g`` g on the load cell (0 removes it).

        The mass adds to the load-cell reading (``force_g``, ``loadcell_raw``) from the next HX711 conversion on
        (settled after four conversion periods), not to the contact force the taxels feel. Raises ValueError for a negative mass.
        """
        mass = float(mass_g)
        if mass < 0 or not math.isfinite(mass):
            raise ValueError(f"mass_g must be >= 0, got {mass_g}")
        with self._lock:
            self._mass_on_loadcell_g = mass

    def set_hx711_rate(self, rate_sps: float) -> None:
        """The HX711's output rate from now on, samples/s (10 or 80: its RATE pin; fault injection). ValueError."""
        if rate_sps not in (10.0, 80.0):
            raise ValueError(f"the HX711 runs at 10 or 80 samples/s, got {rate_sps}")
        with self._lock:
            self._hx_period_s = 1.0 / (rate_sps * (1.0 + self.config.mechanics.hx711_clock_error))
            self._hx_weights = sinc4_weights(self._hx_period_s * 1000.0)
            self._hx_next_s = self._time_s + self._hx_period_s

    def home_actuator(self) -> None:
        """Place the actuator at home (0 mm) immediately (the end of a HOMING move)."""
        with self._lock:
            self._actuator_mm = 0.0

    # -- dynamics --------------------------------------------------------------------------------------------------
    def _hx711_convert(self, force_g: np.ndarray, mass_g: float) -> None:
        """Feed this step's force on the load cell (one sample per ms: the contact force ``force_g`` plus a resting
        mass ``mass_g``) to the HX711 model; every conversion that completes in the step takes the sinc^4-weighted
        force of the four periods before it (lock held)."""
        n = force_g.size
        t0 = self._time_s
        # the history, newest last, is _hx_hist[:_hx_fill]; the newest _HX_HISTORY_MS move to the front when the
        # step does not fit behind them (no copy of the whole history per ms)
        hist, fill = self._hx_hist, self._hx_fill
        if fill + n > hist.size:
            keep = hist[fill - _HX_HISTORY_MS:fill].copy()
            if _HX_HISTORY_MS + n > hist.size:
                hist = self._hx_hist = np.empty(2 * (_HX_HISTORY_MS + n))
            hist[:_HX_HISTORY_MS] = keep
            fill = _HX_HISTORY_MS
        np.add(force_g, mass_g, out=hist[fill:fill + n])  # (the sum written in place: no array between)
        fill = self._hx_fill = fill + n
        w = self._hx_weights
        noise = self.config.mechanics.loadcell_noise_g
        while self._hx_next_s <= t0 + n * 1e-3 + 1e-12:
            k = min(n, max(1, math.ceil((self._hx_next_s - t0) * 1000.0 - 1e-9)))  # the step it completes in
            end = fill - (n - k)
            window = hist[end - w.size:end][::-1]
            self._loadcell_g = float(np.dot(w, window)) + noise * float(self._rng.standard_normal())
            self._hx_last_s = self._hx_next_s
            self._hx_next_s += self._hx_period_s
            p = self.hx711_dout_noise
            self._hx_flip_mask = 0 if p <= 0 else int(
                np.dot(self._rng.random(24) < p, 1 << np.arange(24, dtype=np.int64)))
            self._hx_conversions += 1

    def _read_step_consts(self) -> tuple:
        """The config's numbers :meth:`advance` uses, in its order (read once per model)."""
        d, m = self.config.drum, self.config.mechanics
        circ = d.circumference_mm
        return (d.true_steps_per_mm, circ, m.actuator_max_speed_mm_s, d.max_accel_mm_s2 * 1e-3, m.actuator_travel_mm,
                m.contact_gap_mm, d.runout_mm, m.contact_stiffness_g_per_mm, m.texture_ripple,
                float(self.sensor.config.pitch_mm), d.marks_per_rev / circ)

    def advance(self, n_ms: int, *, drum_step_rate_hz: float, actuator_velocity_mm_s: float, render: bool = True
                ) -> tuple[np.ndarray | None, np.ndarray]:
        """Advance the physics by ``n_ms`` 1 ms steps under constant commands.

        Parameters
        ----------
        n_ms : int
            Number of 1 ms steps (>= 0).
        drum_step_rate_hz : float
            Commanded stepper rate, microsteps/s (signed; surface speed = rate / ``drum.true_steps_per_mm``: a
            driver at another microstep setting than the firmware assumes turns the drum at another speed).
        actuator_velocity_mm_s : float
            Commanded actuator velocity, mm/s (positive towards the sensor; clipped to the speed limit).
        render : bool
            False: nobody takes this step's taxel samples (a board that does not stream): they are not rendered
            (the noise generator still draws what a render draws, so every later step is the same either way).

        Returns
        -------
        samples : (n_ms, 18) uint16, or None (``render=False``)
            Taxel ADC counts, one row per ms.
        sync_in : (n_ms,) bool
            True in the ms in which the drum's index mark passed.
        """
        n = int(n_ms)
        if n < 0:
            raise ValueError("n_ms must be >= 0")
        dt = 1e-3
        with self._lock:
            if n == 0:
                return np.empty((0, N_TAXELS), np.uint16), np.zeros(0, bool)
            k = self._step_consts
            if k is None:  # the rig's constants, read once (the config does not change while the model runs)
                k = self._step_consts = self._read_step_consts()
            true_steps_per_mm, circ, vmax, accel_step, travel, gap, runout, stiffness, ripple, pitch, marks_per_mm = k
            target = float(drum_step_rate_hz) / true_steps_per_mm  # the driver's real microstep setting
            va = min(max(self.actuator_sign * float(actuator_velocity_mm_s), -vmax), vmax)
            stall_g = self.config.mechanics.actuator_stall_g
            if stall_g > 0 and va > 0:  # the driver's stall current: no further than where the spring carries stall_g
                va = min(va, max(0.0, gap + stall_g / stiffness - self._actuator_mm) / (n * dt))
            self._still_ms = self._still_ms + n if va == 0.0 else 0
            if self._windup_mm and self._still_ms >= ACTUATOR_CATCHUP_MS:  # the coupling catches up: the screw jumps
                to = min(max(self._actuator_mm + self._windup_mm, 0.0), travel)
                if stall_g > 0 and self._windup_mm > 0:  # the motor drives the catch-up: no further than its stall
                    to = min(to, max(self._actuator_mm, gap + stall_g / stiffness))
                self._actuator_mm = to
                self._windup_mm = 0.0
            if self.actuator_lost or self.actuator_slip:  # lost steps never return; a slip winds the coupling up
                va *= 1.0 - min(1.0, max(0.0, self.actuator_lost))
                slip = min(1.0, max(0.0, self.actuator_slip))
                self._windup_mm += va * slip * n * dt
                va *= 1.0 - slip
            # speed ramp, surface travel, index-mark passes, speed marks, actuator travel and contact force with the
            # runout and the texture ripple (SensorModel.contact_height), one ms after another
            # (rigctl.simulation.mechanics)
            tex = self._texture
            if self._heights[0] is not tex:  # the mounted plate's tables, looked up once per plate
                heights, period, mean = self.sensor.height_tables(tex)
                self._heights = (tex, heights[1], period, float(mean[1]))
            _, h_row, period, h_mean = self._heights
            pos, force, motor = np.empty((3, n))  # (rows of one buffer: each C-contiguous)
            sync_in, marks = np.empty((2, n), bool)
            speed, act, pos_last, force_last, motor_last = step_mechanics(
                self._speed_mm_s, target, accel_step, self._position_mm, circ, self._actuator_mm, va * dt,
                travel, gap, runout, self._runout_phase, stiffness, ripple, h_row, period, h_mean, pitch, pos, sync_in,
                force, 1.0 - self.drum_sign * (1.0 - self._slip()), motor,  # the kernel's slip: 2 turns it backwards
                marks_per_mm, marks, self._motor_mm)
            self.last_stepper_mm = motor  # the stepper's travel at the end of each ms of the step
            self._motor_mm = motor_last
            self.last_marks = marks

            # slow sensitivity drift of the fabric: Ornstein-Uhlenbeck, tau 20 s
            c = self.config.sensor
            a = math.exp(-n * dt / 20.0)
            self._sensitivity = 1.0 + a * (self._sensitivity - 1.0) + c.sensitivity_drift * math.sqrt(1 - a * a) * float(
                self._rng.standard_normal())
            samples: np.ndarray | None = None
            if render or self.front_end.carries_state:
                samples = self.front_end.apply(self.sensor.render(tex, pos, force, self._rng,
                                                                  sensitivity=self._sensitivity, wrap_mm=circ))
            else:
                render_seed(self._rng)

            self._speed_mm_s = float(speed)
            self._position_mm = pos_last
            self._actuator_mm = float(act)
            self._force_g = force_last
            self._hx711_convert(force, self._mass_on_loadcell_g)
            self._time_s += n * dt
            return samples, sync_in


_HX_HISTORY_MS = 1024  # 4 conversion periods at 10 SPS with a 20 % slow oscillator fit
#: a slipping coupling (RigModel.actuator_slip) catches up once the motor has held still this long, ms (the simavr
#: harness's ACT_CATCHUP_MS)
ACTUATOR_CATCHUP_MS = 20


def sinc4_weights(period_ms: float) -> np.ndarray:
    """Weights of the HX711's settling as a sinc^4 filter on 1 ms force samples, newest first.

    Four cascaded moving averages of one conversion period (``period_ms``): the cubic B-spline over four periods,
    sampled at the sample centres and normalised to sum 1 (group delay two periods; a step settles after four, the
    Avia HX711 datasheet's figure). Returns ``(ceil(4 * period_ms),)`` float64.
    """
    n = int(math.ceil(4.0 * period_ms))
    u = (np.arange(n) + 0.5) / period_ms
    u = np.where(u >= 2.0, 4.0 - u, u)
    v = u - 1.0
    w = np.where(u < 1.0, u ** 3 / 6.0, (1.0 + 3.0 * v + 3.0 * v * v - 3.0 * v ** 3) / 6.0)
    w = np.clip(w, 0.0, None)
    return w / w.sum()
