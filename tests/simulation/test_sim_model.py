"""Physical invariants of the rig model: speed dilates time, force scales amplitude non-linearly, the bottom layer is
smoother and weaker, 10-bit range, seeded reproducibility; drum, actuator, load cell and a PI force loop."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rigctl.simulation.model import (
    MechanicsConfig,
    RigConfig,
    RigModel,
    SensorConfig,
    SensorModel,
)
from rigctl.simulation.textures import TEXTURES

TOP_CENTRE, BOTTOM_CENTRE = 4, 13


def _trace(sensor, letter, speed, force, seed=0, travel=240.0):
    n = int(round(travel / speed * 1000))
    pos = 3.0 + np.arange(1, n + 1) * speed / 1000
    return sensor.render(letter, pos, force, np.random.default_rng(seed))


def _dominant_hz(x):
    x = x.astype(float) - x.mean()
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    freq = np.fft.rfftfreq(x.size, d=1e-3)
    spec[freq < 1.0] = 0
    return freq[np.argmax(spec)]


def test_range_dtype_and_seeded_reproducibility():
    sensor = SensorModel()
    a = _trace(sensor, "M", 80, 1000, seed=1)
    b = _trace(sensor, "M", 80, 1000, seed=1)
    c = _trace(sensor, "M", 80, 1000, seed=2)
    assert a.dtype == np.uint16 and a.shape == (3000, 18)
    assert a.max() <= 1023
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    # another sensor built from the same config has the same calibration spread
    np.testing.assert_array_equal(SensorModel().gain, sensor.gain)


@pytest.mark.parametrize("letter", ["B", "H", "L"])
def test_speed_dilates_time_spatial_period_unchanged(letter):
    sensor = SensorModel()
    period = TEXTURES[letter].period_mm
    f40 = _dominant_hz(_trace(sensor, letter, 40, 500)[:, TOP_CENTRE])
    f120 = _dominant_hz(_trace(sensor, letter, 120, 500)[:, TOP_CENTRE])
    assert f120 / f40 == pytest.approx(3.0, rel=0.05)  # temporal frequency scales with speed
    assert 40 / f40 == pytest.approx(period, rel=0.05)  # the spatial period is the texture's, at both speeds
    assert 120 / f120 == pytest.approx(period, rel=0.05)


def test_force_changes_amplitude_non_linearly():
    sensor = SensorModel()
    off = sensor.offset[:9]
    levels = {f: (_trace(sensor, "A", 80, f)[:, :9].mean(axis=0) - off).mean() for f in (250, 500, 1000)}
    assert levels[250] < levels[500] < levels[1000]
    # doubling the force does not double the signal (saturating piezoresistive response)
    assert 1.1 < levels[500] / levels[250] < 1.85
    assert 1.1 < levels[1000] / levels[500] < 1.85
    # the texture modulation grows with force, sub-linearly
    amp = {f: _trace(sensor, "H", 80, f)[:, TOP_CENTRE].astype(float).std() for f in (250, 500, 1000)}
    assert amp[250] < amp[500] < amp[1000] < 2 * amp[500]


def test_bottom_layer_smoother_and_weaker():
    cfg = SensorConfig(noise_counts=0.0, gain_spread=0.0, offset_spread_counts=0.0)
    sensor = SensorModel(cfg)
    x = _trace(sensor, "G", 80, 500).astype(float)  # sharp-edged rectangular ridges
    top, bottom = x[:, :9] - cfg.offset_mean_counts, x[:, 9:] - cfg.offset_mean_counts
    assert bottom.mean() < 0.8 * top.mean()  # weaker
    rel_mod_top = top.std(axis=0) / top.mean(axis=0)
    rel_mod_bottom = bottom.std(axis=0) / bottom.mean(axis=0)
    assert np.all(rel_mod_bottom < 0.8 * rel_mod_top)  # larger receptive field: the ridges are smoothed
    # the more so the finer the spacing (half-space rectangular ridges, K)
    xk = _trace(sensor, "K", 80, 500).astype(float) - cfg.offset_mean_counts
    rel_k_top = xk[:, :9].std(axis=0) / xk[:, :9].mean(axis=0)
    rel_k_bottom = xk[:, 9:].std(axis=0) / xk[:, 9:].mean(axis=0)
    assert np.all(rel_k_bottom < 0.5 * rel_k_top)
    assert np.all(rel_k_bottom / rel_k_top < rel_mod_bottom / rel_mod_top)
    # edges: the largest sample-to-sample step is much smaller on the bottom layer
    assert np.abs(np.diff(bottom, axis=0)).max() < 0.5 * np.abs(np.diff(top, axis=0)).max()


def test_rows_see_the_same_surface_one_pitch_apart():
    cfg = SensorConfig(noise_counts=0.0, gain_spread=0.0, offset_spread_counts=0.0, plate_level_spread=0.0,
                       row_weights=(1.0, 1.0, 1.0))
    sensor = SensorModel(cfg)
    speed = 50.0
    x = _trace(sensor, "L", speed, 500).astype(int)
    lag = int(round(cfg.pitch_mm / speed * 1000))  # row 1 sees what row 0 saw pitch/speed earlier
    np.testing.assert_allclose(x[lag:, 3], x[:-lag, 0], atol=1)
    np.testing.assert_array_equal(x[:, 0], x[:, 2])  # ridges run across the drum: columns agree


def test_config_json_round_trip():
    cfg = RigConfig()
    cfg.sensor.noise_counts = 1.25
    again = RigConfig.from_json(json.dumps(cfg.to_dict()))
    assert again == cfg
    with pytest.raises(TypeError, match="nope"):
        RigConfig.from_dict({"drum": {"nope": 1}})


def test_drum_acceleration_limit_and_index_pulse():
    rig = RigModel(seed=3)
    d = rig.config.drum
    rate = 120 * d.steps_per_mm
    rig.advance(100, drum_step_rate_hz=rate, actuator_velocity_mm_s=0)
    assert rig.drum_speed_mm_s == pytest.approx(d.max_accel_mm_s2 * 0.1, rel=1e-6)
    rig.advance(200, drum_step_rate_hz=rate, actuator_velocity_mm_s=0)
    assert rig.drum_speed_mm_s == pytest.approx(120.0)
    rev0, pos0 = rig.revolutions, rig.position_mm
    total_sync = 0
    for _ in range(10):
        _, sync = rig.advance(1000, drum_step_rate_hz=rate, actuator_velocity_mm_s=0)
        total_sync += int(sync.sum())
    assert rig.position_mm - pos0 == pytest.approx(1200.0, rel=1e-9)
    assert total_sync == rig.revolutions - rev0 == math.floor(rig.position_mm / d.circumference_mm) - math.floor(
        pos0 / d.circumference_mm)
    assert 0 <= rig.angle_deg < 360
    assert rig.angle_deg == pytest.approx((rig.position_mm % d.circumference_mm) / d.circumference_mm * 360)


def test_steps_whose_samples_nobody_takes_leave_every_later_sample_as_it_was():
    """``advance(render=False)`` (a board that does not stream) renders nothing but draws what a render draws: the
    steps rendered around skipped ones are those of a run that rendered every step, bit for bit."""
    runs = []
    for render in (lambda i: True, lambda i: i % 3 == 0):
        rig = RigModel(seed=5)
        rate = 80 * rig.config.drum.steps_per_mm
        runs.append([rig.advance(3, drum_step_rate_hz=rate, actuator_velocity_mm_s=1.5, render=render(i))
                     for i in range(1500)])  # the drum turning, the actuator pressing into contact
    skipped = 0
    for (every, sync), (some, sync_some) in zip(*runs):
        assert np.array_equal(sync, sync_some)
        if some is None:
            skipped += 1
        else:
            assert np.array_equal(every, some)
    assert skipped == 1000 and runs[0][-1][0].std() > 0


def test_actuator_spring_and_load_cell():
    rig = RigModel(seed=5)
    m = rig.config.mechanics
    samples, _ = rig.advance(200, drum_step_rate_hz=0, actuator_velocity_mm_s=2.0)  # 0.4 mm: no contact yet
    assert rig.actuator_mm == pytest.approx(0.4)
    assert abs(rig.force_g) < 5 and samples[:, :9].mean() < 100
    rig.advance(2000, drum_step_rate_hz=0, actuator_velocity_mm_s=2.0)  # 4.4 mm: 1.4 mm past contact
    expected = m.contact_stiffness_g_per_mm * (4.4 - m.contact_gap_mm)
    assert rig.contact_force_g == pytest.approx(expected, abs=m.contact_stiffness_g_per_mm * 0.03)
    # the HX711 lags a moving force (sinc^4 over 4 conversion periods: ~2 periods at 500 g/s = 12.5 g, plus the
    # time since the last conversion); 4 periods after the actuator stops it reads the contact force
    lag_g = rig.contact_force_g - rig.force_g
    assert 500 * 2 * m.hx711_period_s - 5 * m.loadcell_noise_g < lag_g < 500 * 3 * m.hx711_period_s + 5 * m.loadcell_noise_g
    rig.advance(int(4 * m.hx711_period_s * 1000) + 1, drum_step_rate_hz=0, actuator_velocity_mm_s=0)
    assert rig.force_g == pytest.approx(rig.contact_force_g, abs=5 * m.loadcell_noise_g)
    raw_g = (rig.loadcell_raw - m.loadcell_offset_counts) / m.loadcell_counts_per_g
    assert raw_g == pytest.approx(rig.force_g, abs=0.01)
    pressed, _ = rig.advance(50, drum_step_rate_hz=0, actuator_velocity_mm_s=0)
    assert pressed[:, :9].mean() > samples[:, :9].mean() + 150
    rig.place_mass(200)
    assert rig.force_g == pytest.approx(rig.contact_force_g, abs=5 * m.loadcell_noise_g)  # no conversion yet
    rig.advance(int(4 * m.hx711_period_s * 1000) + 1, drum_step_rate_hz=0, actuator_velocity_mm_s=0)
    assert rig.force_g == pytest.approx(rig.contact_force_g + 200, abs=5 * m.loadcell_noise_g)


@pytest.mark.parametrize("sps", [10.0, 80.0])
def test_hx711_converts_once_per_period_and_settles_in_four(sps):
    """Avia HX711 datasheet: one reading per conversion period, settled 4 periods after a step (sinc^4)."""
    rig = RigModel(RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=sps, hx711_clock_error=0.05, loadcell_noise_g=0)))
    period = rig.config.mechanics.hx711_period_s
    assert period == pytest.approx(1 / (sps * 1.05))
    rig.advance(1000, drum_step_rate_hz=0, actuator_velocity_mm_s=0)
    assert rig.hx711_conversions == int(1.0 / period)
    n0, readings = rig.hx711_conversions, []
    rig.place_mass(300)  # a force step
    while rig.hx711_conversions < n0 + 6:
        rig.advance(rig.ms_to_next_conversion(), drum_step_rate_hz=0, actuator_velocity_mm_s=0)
        readings.append(rig.force_g)
    assert 0 < readings[0] < 300 and 0 < readings[2] < 300  # still moving after 3 periods
    assert readings[3] == pytest.approx(300, abs=1.0) and readings[5] == pytest.approx(300, abs=1e-6)


@pytest.mark.parametrize("setpoint", [250.0, 500.0, 1000.0])
def test_pi_force_loop_settles_in_a_realistic_time(setpoint):
    """The virtual Mega's force loop (the firmware's algorithm and default gains) on the model with the HX711's delay,
    default stiffness (250 g/mm), pressing from home: settles within FORCE_TOLERANCE_G in 1-4 s, small overshoot."""
    from rigctl.core.drum import DrumState
    from rigctl.devices.wire import Command, HoldingRegister as HR
    from rigctl.simulation.controller import MegaController

    ctl = MegaController(RigModel(seed=1), factory_calibrated=True)  # calibrated: defaults refuse PRESS (spec 2.11)
    # a controller out of reset is NOT_HOMED and refuses PRESS until HOME succeeds (docs/wire-protocol.md 2.6)
    assert ctl.write_registers(6, HR.COMMAND, [int(Command.PRESS)]) is not None
    assert ctl.write_registers(6, HR.COMMAND, [int(Command.HOME)]) is None
    for _ in range(1000):  # 10 s at most
        ctl.note_request()
        ctl.step(10)
        if ctl.state == DrumState.IDLE:
            break
    assert ctl.state == DrumState.IDLE
    assert ctl.write_registers(6, HR.FORCE_SETPOINT_G, [int(setpoint)]) is None
    assert ctl.write_registers(6, HR.COMMAND, [int(Command.PRESS)]) is None
    t, forces = [], []
    for i in range(600):  # 6 s in 10 ms steps
        ctl.note_request()
        ctl.step(10)
        t.append((i + 1) * 0.01)
        forces.append(ctl.model.contact_force_g)
    f = np.array(forces)
    outside = np.flatnonzero(np.abs(f - setpoint) > 15)
    settle = t[outside[-1] + 1] if outside.size else t[0]
    assert outside.size == 0 or outside[-1] < len(f) - 1, "did not settle"
    assert 1.0 <= settle <= 4.0
    assert abs(f[-100:].mean() - setpoint) < 5
    assert f.max() - setpoint < 0.1 * setpoint


def test_texture_setter_and_threaded_advance():
    import threading

    rig = RigModel(seed=9)
    rig.set_texture("n")
    assert rig.texture.letter == "N"
    with pytest.raises(KeyError):
        rig.set_texture("Z")
    from rigctl.core import TextureSet

    rig.set_texture("Z", TextureSet(["Z", "Velvet-7"]))  # any label of a set (geometry derived from the label)
    assert rig.texture.label == "Z"
    rig.set_texture("Velvet-7", TextureSet(["Z", "Velvet-7"]))
    assert rig.texture.label == "Velvet-7"
    rig.set_texture("N")
    errors = []

    def run():
        try:
            for _ in range(50):
                rig.advance(3, drum_step_rate_hz=500, actuator_velocity_mm_s=1.0)
        except Exception as exc:  # pragma: no cover - a failure is reported below
            errors.append(exc)

    threads = [threading.Thread(target=run) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert rig.time_s == pytest.approx(3 * 50 * 3 * 1e-3)
    assert rig.actuator_mm == pytest.approx(0.45)


def test_ridges_modulate_the_reading_deeply_and_force_keeps_the_shape():
    """Contact model: the pad rests on the crests, so a ridged plate's reading swings by more than its mean (the
    paper's Fig. 2C raster of texture L is strongly modulated), the smooth plate's not at all; the plate sets the
    mean level at a given force (crest saturation); the force scales the modulation with the level and keeps its
    shape (FabricSlide: amplitude ~ level^1.37, no spectral tilt), and the tabulated contact shape keeps its mean."""
    cfg = SensorConfig(noise_counts=0.0, gain_spread=0.0, offset_spread_counts=0.0)
    sensor = SensorModel(cfg)

    def top(letter, force):
        return _trace(sensor, letter, 80, force)[:, TOP_CENTRE].astype(float) - cfg.offset_mean_counts

    flat = top("A", 500)
    assert np.ptp(flat) < 0.05 * flat.mean()
    means = {}
    for letter in "BGL":
        x = top(letter, 500)
        assert np.ptp(x) > x.mean(), letter
        means[letter] = x.mean()
    assert all(abs(m - flat.mean()) > 0.1 * flat.mean() for m in means.values())
    e = {f: top("E", f) for f in (250, 1000)}  # half-height circular ridges: no clipping at either force
    assert e[1000].mean() > 1.2 * e[250].mean()
    rel = {f: x.std() / x.mean() for f, x in e.items()}
    grow = sensor.depth_factor(1000) / sensor.depth_factor(250)  # FabricSlide: depth ~ level^0.37
    assert 1.1 < grow < 1.5
    assert rel[1000] / rel[250] == pytest.approx(grow, rel=0.05)
    # same shape: the deviations from the mean, divided by the depth, coincide
    np.testing.assert_allclose((e[1000] / e[1000].mean() - 1) / rel[1000], (e[250] / e[250].mean() - 1) / rel[250],
                               atol=0.1)
    for letter in "BHMK":
        for force in (250.0, 1000.0):
            tables, _, mean = sensor.tables(letter, force)
            np.testing.assert_allclose(tables.mean(axis=1), 1.0, rtol=1e-6)
            np.testing.assert_allclose(mean, 1.0)


@pytest.mark.parametrize("letter", ["C", "H", "M", "K"])
def test_contact_force_balance_is_solved_exactly(letter):
    """The pad indentation delta0 of a texture's contact tables satisfies the force balance of the module docstring,
    mean(max(0, delta0 - depth)) = flat-plate indentation, to rounding, and agrees with a 60-step bisection."""
    from rigctl.simulation.textures import get_texture

    model = SensorModel()
    depth, delta0_of = model._contact_depth(get_texture(letter))
    for force in (10.0, 250.0, 500.0, 1000.0, 5000.0):
        delta = float(model.indentation_mm(force))
        d0 = delta0_of(delta)
        assert abs(np.maximum(0.0, d0 - depth).mean() - delta) <= 1e-9 * delta
        lo, hi = 0.0, delta + float(depth.max())
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.maximum(0.0, mid - depth).mean() < delta else (lo, mid)
        assert d0 == pytest.approx(0.5 * (lo + hi), rel=1e-9, abs=1e-12)


def test_plate_pattern_is_static_per_plate_and_contact_efficiency_below_one():
    """Each plate loads the taxels in its own static pattern (FabricSlide: sd 0.026 between fabrics), the same in
    every sensor model built from the same config; ridged plates read lower on average than the flat one (crest
    saturation), the more so at higher force for sparse ridges."""
    a, b = SensorModel(), SensorModel()
    np.testing.assert_array_equal(a.plate_pattern("B"), b.plate_pattern("B"))
    pats = np.log(np.array([a.plate_pattern(t) for t in TEXTURES]))
    assert pats.shape == (16, 18)
    assert 0.015 < pats.std() < 0.04
    assert np.abs(np.corrcoef(pats)[np.triu_indices(16, 1)]).mean() < 0.4  # plates differ
    assert not np.allclose(a.plate_pattern("A"), SensorModel(SensorConfig(calibration_seed=1)).plate_pattern("A"))
    assert np.all(SensorModel(SensorConfig(plate_level_spread=0.0)).plate_pattern("C") == 1.0)
    np.testing.assert_allclose(a.contact_efficiency("A", 500), 1.0)
    for letter in "BDGL":
        e250, e1000 = a.contact_efficiency(letter, 250), a.contact_efficiency(letter, 1000)
        assert np.all(e250 < 1.0) and np.all(e1000 <= e250 + 1e-9), letter


def test_a_starved_clock_keeps_the_actuator_count_on_the_true_position():
    """The controller counts the actuator's steps as the firmware does; a starved clock hands the model long chunks
    (here 37 ms, stepped 10 ms at a time), and each STOP's retract ending at the home switch used to count steps past
    it: over 12 presses the count and the true position parted by 0.012 mm (0.06 mm in a loaded CI run, enough for a
    'home' actuator to stand off its switch). They stay together now."""
    from rigctl.devices.wire import Command, HoldingRegister as HR
    from rigctl.simulation.controller import MegaController

    model = RigModel(seed=1)
    ctl = MegaController(model, factory_calibrated=True)

    def write(reg, value):
        assert ctl.write_registers(6, reg, [int(value)]) is None, (reg, value)

    def run(ms, chunk=37):
        for _ in range(ms // chunk):
            write(HR.WATCHDOG_MS, 10000)  # the host's requests, fed between chunks
            ctl.step(chunk)

    write(HR.WATCHDOG_MS, 10000)
    write(HR.COMMAND, Command.HOME)
    run(8000, 10)
    for _ in range(12):
        write(HR.FORCE_SETPOINT_G, 200)
        write(HR.COMMAND, Command.PRESS)
        run(4000)
        assert model.actuator_mm > 1.0  # it pressed
        write(HR.COMMAND, Command.STOP)
        run(3000)
    assert model.actuator_mm <= 1e-6 and abs(ctl.actuator_position_mm()) <= 1e-3, (model.actuator_mm,
                                                                                  ctl.actuator_position_mm())


def test_the_kernels_plate_coordinate_is_pythons_modulo_bit_for_bit():
    """Issue 57 item 6: the render kernel takes the plate coordinate without a division on the first two turns
    (model._plate_x); every value must be the bits of Python's float ``%`` (the dataset's numbers unchanged): the
    turns' edges and their neighbours, zeros, negatives, NaN, far turns, other circumferences."""
    from rigctl.simulation.model import _plate_x

    rng = np.random.default_rng(5)
    for wrap in (math.pi * 100.0, 3.0, 50.0, 0.1, 1e-300):
        edges = [0.0, -0.0, wrap, 2 * wrap, 3 * wrap, -wrap, wrap / 2, float("nan"), float("inf"), -1e-320, 1e300]
        near = [np.nextafter(e, d) for e in (0.0, wrap, 2 * wrap) for d in (-np.inf, np.inf)]
        xs = np.concatenate([edges, near, rng.uniform(-3 * wrap, 5 * wrap, 2000)])
        got = np.array([_plate_x(float(x), wrap) for x in xs])
        want = np.array([float(x) % wrap for x in xs])
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64)), (wrap, xs[got.view(np.uint64) != want.view(np.uint64)])


def test_the_render_kernels_numbers_are_those_before_its_per_sample_work_was_hoisted():
    """Issue 57 item 6: the render kernel takes each row's plate cell and pressure once a sample (not once per layer)
    and each channel's gain times the sensitivity once a call; the same roundings in the same order, so every
    rendered trial keeps its bits. The SHA-256 of five trials (every array and attribute of render_trial: three
    constant speeds, a ramp, a start at any drum angle) as main rendered them before (d6da9ac)."""
    import hashlib

    from rigctl.simulation.dataset import RampProfile, render_trial
    from rigctl.simulation.model import RigConfig as Config

    def digest(t):
        h = hashlib.sha256()
        for name in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s", "speed_time_s"):
            h.update(np.ascontiguousarray(getattr(t, name)).tobytes())
        h.update(repr(sorted(t.attrs.items())).encode())
        return h.hexdigest()[:16]

    any_angle = Config()
    any_angle.drum.start_at_index = False
    cases = [("A", 40, 250, None, None, 1), ("L", 120, 1000, None, None, 2), ("P", 80, 500, None, None, 3),
             ("G", 60, 500, RampProfile(40.0, 120.0), None, 4), ("D", 100, 750, None, any_angle, 5)]
    got = [digest(render_trial(tex, v, f, rng=np.random.default_rng(s), profile=prof, config=cfg))
           for tex, v, f, prof, cfg, s in cases]
    assert got == ["bc65dff87175a3f2", "2c81f51ec336a81f", "1c622c066fb67e50", "76320e0ab12afb4b", "7b8c6225c4999026"]


def test_the_wrapped_contact_height_is_numpys_modulo_then_lookup_bit_for_bit():
    """Issue 57 item 6: contact_height(..., wrap_mm=c) in one compiled loop gives the bits of contact_height(...,
    np.mod(pos, c)) (numpy's passes): drum travel over several turns, the turns' edges, negatives, every texture."""
    model = SensorModel(RigConfig().sensor)
    rng = np.random.default_rng(11)
    for wrap in (RigConfig().drum.circumference_mm, 3.0, 77.7):
        edges = np.array([0.0, -0.0, wrap, 2 * wrap, -wrap, wrap / 2, 1e-300, -1e-300])
        near = np.array([np.nextafter(e, d) for e in (0.0, wrap, 2 * wrap) for d in (-np.inf, np.inf)])
        pos = np.concatenate([edges, near, rng.uniform(-3 * wrap, 6 * wrap, 5000), np.cumsum(rng.uniform(0, 0.2, 3000))])
        for label in TEXTURES:
            got = model.contact_height(label, pos, wrap_mm=wrap)
            want = model.contact_height(label, np.mod(pos, wrap))
            assert np.array_equal(got.view(np.uint64), want.view(np.uint64)), (wrap, label)
