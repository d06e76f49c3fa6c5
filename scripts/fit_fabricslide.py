"""Fit the simulated sensor's force, speed, noise and per-taxel responses to the real FabricSlide recordings.

Usage (from the repository root; prints the fitted figures, writes the comparison figure)::

    python scripts/fit_fabricslide.py [--data ../shared/data/fabricslide] [--figure docs/figures/sensor_fit.png]

What it measures, per recording (720 fabric trials: 4 fabrics x 5 force setpoints x 6 speeds 10-150 mm/s x 2
directions x 3 repeats; 16 taxels; raw samples at ~35.7 Hz, repeated timestamps dropped, the first and last 15 %
trimmed as the FabricSlide README advises):

- ``level``: each taxel's mean reading (counts);
- the Welch power spectrum (64-sample segments, 0.56 Hz bins) of each taxel's linearly detrended reading;
- ``noise floor``: the spectral density in the 8-16 Hz band of the least textured cell (BrownCotton at the lowest
  force), speed-independent, i.e. sensor noise (counts^2/Hz, and as a fraction of the taxel's level);
- ``texture amplitude``: the power in 4-16 Hz above the noise floor (the 1-3 Hz band holds a ~2.2 Hz peak at every
  fabric and speed that grows with the force setpoint: the arm's force loop, not texture, so it is left out).

Fits (printed):

1. per-taxel spread: ``level_i = a_i + b_i * F`` (least squares over all recordings); gain spread = sd(b)/mean(b),
   offset spread = sd(a) in units of mean(b) * F_mid;
2. force response: ``log A = c(fabric, speed, taxel) + beta * log level`` over the force setpoints (beta = 1:
   modulation depth proportional to the level; > 1: the relative modulation depth grows with force);
3. spectral shape versus force: ``log P(f) = c(fabric, speed, taxel, f) + beta_f * log level + delta * log level *
   log(f / 8 Hz)``; ``delta`` is how much the force tilts the spectrum (0: the shape is force-invariant);
4. speed response: ``log A = c(fabric, force, taxel) + alpha * log speed`` (0: pure time dilation, no sensor
   low-pass in 10-150 mm/s);
5. across taxels within a recording: ``log A`` vs ``log level`` (a per-taxel gain scales level and modulation
   alike when the slope is ~1);
6. each fabric's per-taxel level pattern (log level minus its mean over the taxels): its spread between fabrics
   (within each speed x force condition), its stability across conditions, and its trial-to-trial spread.

The figure compares these measured responses with the simulated sensor's (:class:`rigctl.simulation.model.
SensorModel`, rendered on the base wave texture L at the paper's forces and speeds): level and relative modulation
depth versus force (normalised at the middle force), modulation amplitude versus speed (normalised at the middle
speed), and the normalised spectra at three forces.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.signal import detrend, welch

from rigctl.storage.fabricslide import load_fabricslide

TRIM = 0.15  #: fraction dropped at each end of a recording (acceleration ramps)
NPERSEG = 64  #: Welch segment, samples (~1.8 s at 35.7 Hz)
BAND_HZ = (4.0, 16.0)  #: texture band (above the force loop's ~2.2 Hz oscillation, below Nyquist's roll-off)
NOISE_BAND_HZ = (8.0, 16.0)
#: highest force setpoint without the arm's force-loop oscillation (a ~2.2 Hz peak, the same at every fabric and
#: speed, whose power jumps ~10x from setpoint 180 to 210 and whose harmonics reach the texture band)
CLEAN_MAX_SETPOINT = 180.0
#: relative texture depth (amplitude / level) above which a fabric counts as clearly textured
TEXTURED_MIN_DEPTH = 0.008


def measure(directory: Path) -> dict:
    """Per-recording levels and spectra of the fabric recordings.

    Returns a dict of arrays: ``fabric`` (n,) str, ``force`` (n,), ``speed`` (n,) |mm/s|, ``level`` (n, 16) counts,
    ``freq`` (m,) Hz, ``psd`` (n, m, 16) counts^2/Hz, ``fs`` (n,) Hz; and the Board10mm recordings' dominant
    frequency per speed (``board_speed``, ``board_peak_hz``).
    """
    recs = load_fabricslide(directory, include_board=True)
    fabric, force, speed, level, psd, fs = [], [], [], [], [], []
    board_speed, board_peak, board_amp = [], [], []
    freq = None
    for r in recs:
        ts = np.asarray(r.timestamp_ms, dtype=np.float64)
        x = np.asarray(r.readings, dtype=np.float64)
        keep = np.concatenate(([True], np.diff(ts) > 0))
        ts, x = ts[keep], x[keep]
        k = int(TRIM * ts.size)
        ts, x = ts[k:ts.size - k], x[k:x.shape[0] - k]
        rate = 1000.0 / float(np.median(np.diff(ts)))
        f, p = welch(detrend(x, axis=0), fs=rate, nperseg=NPERSEG, axis=0)
        if r.kind == "board" or r.label.startswith("Board"):
            fb, pb = welch(detrend(x, axis=0), fs=rate, nperseg=min(256, x.shape[0]), axis=0)
            pm = pb.mean(axis=1)
            pm[fb < 0.1] = 0
            k = int(np.argmax(pm))
            board_speed.append(abs(r.velocity_mm_s))
            board_peak.append(float(fb[k]))
            # amplitude of the board's fundamental (power within +-1 bin of the peak), relative to the level
            board_amp.append(float(np.sqrt(pm[max(0, k - 1):k + 2].sum() * (fb[1] - fb[0])) / x.mean()))
            continue
        freq = f
        fabric.append(r.label)
        force.append(r.force_setpoint)
        speed.append(abs(r.velocity_mm_s))
        level.append(x.mean(axis=0))
        psd.append(p)
        fs.append(rate)
    return {"fabric": np.array(fabric), "force": np.array(force), "speed": np.array(speed),
            "level": np.array(level), "freq": freq, "psd": np.array(psd), "fs": np.array(fs),
            "board_speed": np.array(board_speed), "board_peak_hz": np.array(board_peak),
            "board_amp": np.array(board_amp)}


def _within(groups: list[np.ndarray], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y with each group's mean removed (the group = the cell whose own constant the fit absorbs)."""
    key = np.unique(np.stack(groups, axis=1), axis=0, return_inverse=True)[1].ravel()
    xs, ys = x.copy(), y.copy()
    for g in np.unique(key):
        m = key == g
        xs[m] -= xs[m].mean()
        ys[m] -= ys[m].mean()
    return xs, ys


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y on x (both already centred) and its standard error."""
    b = float((x * y).sum() / (x * x).sum())
    resid = y - b * x
    se = float(np.sqrt((resid ** 2).sum() / max(1, x.size - 1) / (x * x).sum()))
    return b, se


def fit(meas: dict) -> dict:
    """All fitted figures (see the module docstring); returns a dict, also printed by :func:`main`."""
    f, psd, level = meas["freq"], meas["psd"], meas["level"]
    fab, force, speed = meas["fabric"], meas["force"], meas["speed"]
    df = float(f[1] - f[0])
    nb = (f >= NOISE_BAND_HZ[0]) & (f <= NOISE_BAND_HZ[1])
    tb = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1])
    out: dict = {}

    # 1. per-taxel spread: level_i = a_i + b_i F
    A = np.c_[np.ones_like(force), force]
    coef, *_ = np.linalg.lstsq(A, level, rcond=None)
    a, b = coef
    f_mid = float(np.median(np.unique(force)))
    out["taxel_gain_cv"] = float(b.std() / b.mean())
    out["taxel_offset_sd_rel"] = float(a.std() / (b.mean() * f_mid))
    out["taxel_level_r2"] = float(1 - ((level - A @ coef) ** 2).sum() / ((level - level.mean(0)) ** 2).sum())
    out["level_per_setpoint"] = {float(F): float(level[force == F].mean()) for F in np.unique(force)}

    # noise floor: least textured cell (lowest total band power), per taxel
    cells = {(lab, F) for lab, F in zip(fab, force)}
    quiet = min(cells, key=lambda c: psd[(fab == c[0]) & (force == c[1])][:, tb].mean())
    qm = (fab == quiet[0]) & (force == quiet[1])
    floor = psd[qm][:, nb].mean(axis=(0, 1))  # (16,) counts^2/Hz
    out["noise_cell"] = f"{quiet[0]} F{quiet[1]:g}"
    out["noise_density"] = float(np.median(floor))
    out["noise_density_rel"] = float(np.median(floor / level[qm].mean(axis=0) ** 2))  # per Hz, relative to level^2
    # speed-independence of that floor (noise, not texture)
    out["noise_speed_slope"] = _slope(*_within([speed[qm] * 0], np.log(speed[qm]),
                                               np.log(psd[qm][:, nb].mean(axis=(1, 2)))))[0]
    # flatness of the noise floor: ratio of density at 4-8 Hz to 8-16 Hz
    lb = (f >= 4) & (f < 8)
    out["noise_flatness"] = float(psd[qm][:, lb].mean() / psd[qm][:, nb].mean())

    # texture amplitude above the floor, band 4-16 Hz
    excess = np.clip(psd[:, tb, :] - floor[None, None, :], 0, None).sum(axis=1) * df  # (n, 16) counts^2
    amp = np.sqrt(excess)
    with np.errstate(divide="ignore"):
        log_rel = np.log(amp / level)  # -inf where nothing is above the floor (masked out below)
    ok = excess > 0.5 * floor[None, :] * tb.sum() * df  # clearly above the noise
    out["amp_valid_fraction"] = float(ok.mean())
    n, nt = level.shape
    tax = np.broadcast_to(np.arange(nt), (n, nt))
    rep = lambda v: np.broadcast_to(v[:, None], (n, nt))  # noqa: E731
    sel = ok
    g = [rep(fab)[sel], rep(speed)[sel], tax[sel]]
    beta, beta_se = _slope(*_within(g, np.log(level[sel]), np.log(amp[sel])))
    out["force_beta_all"], out["force_beta_all_se"] = beta, beta_se
    # the same over the clean setpoints only (<= CLEAN_MAX_SETPOINT: no force-loop oscillation)
    clean = sel & (rep(force) <= CLEAN_MAX_SETPOINT)
    gc = [rep(fab)[clean], rep(speed)[clean], tax[clean]]
    out["force_beta"], out["force_beta_se"] = _slope(*_within(gc, np.log(level[clean]), np.log(amp[clean])))
    # the arm's force-loop oscillation: power in 1.5-3 Hz (speed-independent peak) per setpoint, counts^2
    lb2 = (f >= 1.5) & (f <= 3.0)
    out["loop_power_per_setpoint"] = {float(F): float(psd[force == F][:, lb2].sum(axis=1).mean() * df)
                                      for F in np.unique(force)}
    # relative depth per force setpoint (amp / level), normalised at the middle setpoint, per cell then averaged
    rel = {}
    for F in np.unique(force):
        m = (force == F)[:, None] & ok
        rel[float(F)] = float(np.exp(np.mean(log_rel[m])))
    out["rel_depth_per_setpoint"] = rel

    # 3. spectral tilt with force
    fb = f[tb]
    lp = np.log(np.clip(psd[:, tb, :] - floor[None, None, :], 1e-6, None))  # (n, nb, 16)
    okb = (psd[:, tb, :] > 2 * floor[None, None, :]) & (force[:, None, None] <= CLEAN_MAX_SETPOINT)
    L3 = np.broadcast_to(np.log(level)[:, None, :], lp.shape)
    lf = np.broadcast_to(np.log(fb / 8.0)[None, :, None], lp.shape)
    rep3 = lambda v: np.broadcast_to(v[:, None, None], lp.shape)  # noqa: E731
    g3 = [rep3(fab)[okb], rep3(speed)[okb], np.broadcast_to(np.arange(nt)[None, None, :], lp.shape)[okb],
          np.broadcast_to(np.arange(fb.size)[None, :, None], lp.shape)[okb]]
    key = np.unique(np.stack(g3, axis=1), axis=0, return_inverse=True)[1].ravel()
    X = np.c_[L3[okb], L3[okb] * lf[okb]]
    y = lp[okb].copy()
    Xc, yc = X.copy(), y.copy()
    for k in np.unique(key):
        m = key == k
        Xc[m] -= Xc[m].mean(axis=0)
        yc[m] -= yc[m].mean()
    sol, *_ = np.linalg.lstsq(Xc, yc, rcond=None)
    resid = yc - Xc @ sol
    cov = np.linalg.inv(Xc.T @ Xc) * (resid ** 2).sum() / max(1, yc.size - 2)
    out["spectrum_beta"], out["spectrum_tilt"] = float(sol[0]) / 2, float(sol[1]) / 2  # amplitude units
    out["spectrum_tilt_se"] = float(np.sqrt(cov[1, 1])) / 2
    # 4. speed response
    g4 = [rep(fab)[clean], rep(force)[clean], tax[clean]]
    alpha, alpha_se = _slope(*_within(g4, np.log(rep(speed)[clean].astype(float)), np.log(amp[clean])))
    out["speed_alpha"], out["speed_alpha_se"] = alpha, alpha_se
    out["amp_per_speed"] = {}
    for v in np.unique(speed):
        m = ((speed == v) & (force <= CLEAN_MAX_SETPOINT))[:, None] & ok
        out["amp_per_speed"][float(v)] = float(np.exp(np.mean(log_rel[m])))
    # 6. each fabric's per-taxel level pattern (log level minus its mean over the taxels): spread between fabrics
    # (per condition, around the mean over fabrics) and within a fabric (trial to trial), stability across conditions
    patt = np.log(level) - np.log(level).mean(axis=1, keepdims=True)
    between, within, effects = [], [], []
    fabrics = np.unique(fab)
    for F in np.unique(force):
        for v in np.unique(speed):
            m = (force == F) & (speed == v)
            means = np.array([patt[m & (fab == a)].mean(axis=0) for a in fabrics])
            effects.append(means - means.mean(axis=0))
            for a in fabrics:
                q = patt[m & (fab == a)]
                within.append(q - q.mean(axis=0))
    eff = np.array(effects)
    out["plate_level_spread"] = float(eff.std())
    out["contact_level_spread"] = float(np.concatenate(within).std())
    cc = [np.corrcoef(eff[i].ravel(), eff[j].ravel())[0, 1] for i in range(len(eff)) for j in range(i + 1, len(eff))]
    out["pattern_stability"] = float(np.mean(cc))
    # 5. across taxels within a recording
    g5 = [np.broadcast_to(np.arange(n)[:, None], (n, nt))[sel]]
    out["taxel_beta"] = _slope(*_within(g5, np.log(level[sel]), np.log(amp[sel])))[0]
    # board: dominant frequency vs speed
    if meas["board_speed"].size:
        sp, pk = meas["board_speed"], meas["board_peak_hz"]
        out["board_period_mm"] = {float(v): float(v / p) for v, p in zip(sp, pk)}
        out["board_amp"] = {float(v): float(a) for v, a in zip(sp, meas["board_amp"])}
        ls, la = np.log(sp), np.log(meas["board_amp"])
        out["board_alpha"] = _slope(ls - ls.mean(), la - la.mean())
    # force response without per-recording thresholds: mean excess power per (fabric, setpoint), pooled over
    # speeds, taxels and repeats (unbiased: the floor is subtracted, negative estimates kept)
    pex = (psd[:, tb, :] - floor[None, None, :]).sum(axis=1) * df  # (n, 16)
    out["force_beta_fabric"] = {}
    out["rel_depth_fabric"] = {}
    for lab in np.unique(fab):
        Fs_ = np.array([F for F in np.unique(force) if F <= CLEAN_MAX_SETPOINT])
        lv = np.array([level[(fab == lab) & (force == F)].mean() for F in Fs_])
        am = np.sqrt(np.clip([pex[(fab == lab) & (force == F)].mean() for F in Fs_], 1e-9, None))
        out["force_beta_fabric"][str(lab)] = float(np.polyfit(np.log(lv), np.log(am), 1)[0])
        out["rel_depth_fabric"][str(lab)] = [float(a / v) for a, v in zip(am, lv)]
    out["force_beta_pooled"] = float(np.mean(list(out["force_beta_fabric"].values())))
    # the fabrics whose texture stands well above the noise (relative depth > TEXTURED_MIN_DEPTH at every clean
    # setpoint); on the others the force loop's harmonics dominate the band
    textured = [k for k, v in out["rel_depth_fabric"].items() if min(v) > TEXTURED_MIN_DEPTH]
    out["textured_fabrics"] = textured
    out["force_beta_textured"] = float(np.mean([out["force_beta_fabric"][k] for k in textured]))
    return out


def model_parameters(res: dict) -> dict:
    """The simulated sensor's parameters that follow from the fit (what :class:`rigctl.simulation.model.SensorConfig`
    should hold): gain spread, noise corner and sd (the floor scaled by the ratio of mid-force levels), depth
    exponent."""
    from rigctl.simulation.model import SensorConfig, SensorModel

    cfg = SensorConfig()
    w = np.asarray(cfg.row_weights, dtype=np.float64)
    row_cv = float(np.repeat(w, 3).std() / np.repeat(w, 3).mean())
    # first-order noise spectrum 1 / (1 + (f / fc)^2): density ratio 4-8 Hz / 8-16 Hz (band centres 6, 12 Hz)
    r = res["noise_flatness"]
    fc = float(np.sqrt((144.0 - 36.0 * r) / (r - 1.0))) if r > 1.0 else float("inf")
    # this sensor's mean reading above offset on the flat plate at the middle force (500 g), unit gain
    sensor = SensorModel(cfg)
    p = 500.0 / 9.0 * w
    level = float(np.mean(np.concatenate([cfg.full_scale_counts * g * p / (p + ph) for g, ph in
                                          ((cfg.layer_gain_top, cfg.p_half_top_g),
                                           (cfg.layer_gain_bottom, cfg.p_half_bottom_g))])))
    del sensor
    mid = res["level_per_setpoint"][float(np.median(list(res["level_per_setpoint"])))]
    s0 = res["noise_density"] * (level / mid) ** 2
    sd = float(np.sqrt(s0 * np.pi * fc / 2.0))
    return {"gain_spread": float(np.sqrt(max(0.0, res["taxel_gain_cv"] ** 2 - row_cv ** 2))), "row_cv": row_cv,
            "noise_corner_hz": fc, "model_mid_level": level, "noise_density_model": s0, "noise_counts": sd,
            "depth_level_exponent": res["force_beta_textured"] - 1.0}


def _print(res: dict) -> None:
    print("FabricSlide fit (720 fabric recordings, 16 taxels, 35.7 Hz)")
    print(f"  level per force setpoint (counts): " + ", ".join(f"F{k:g}: {v:.1f}" for k, v in
                                                          res["level_per_setpoint"].items()))
    print(f"  per-taxel spread: level_i = a_i + b_i F, R^2 {res['taxel_level_r2']:.3f}; gain CV {res['taxel_gain_cv']:.3f}; "
          f"offset sd {res['taxel_offset_sd_rel']:.3f} of the mid-force level")
    print(f"  noise floor ({res['noise_cell']}, 8-16 Hz): {res['noise_density']:.3f} counts^2/Hz "
          f"= {res['noise_density_rel']:.2e} x level^2 per Hz; speed slope {res['noise_speed_slope']:+.3f} "
          f"(log-log); 4-8 Hz / 8-16 Hz density ratio {res['noise_flatness']:.2f} (1 = white)")
    print(f"  texture amplitude (4-16 Hz above the floor) clearly above noise in {100 * res['amp_valid_fraction']:.0f} % "
          f"of recording x taxel")
    print(f"  force response: amplitude ~ level^beta, beta = {res['force_beta']:.2f} +- {res['force_beta_se']:.2f} "
          f"over setpoints <= {CLEAN_MAX_SETPOINT:g} (1 = depth proportional to the level); over all setpoints "
          f"{res['force_beta_all']:.2f} +- {res['force_beta_all_se']:.2f}")
    print("    force-loop oscillation power, 1.5-3 Hz (counts^2): " + ", ".join(
        f"F{k:g}: {v:.1f}" for k, v in res["loop_power_per_setpoint"].items()))
    print("    relative depth (amplitude / level) per setpoint: " + ", ".join(
        f"F{k:g}: {v:.4f}" for k, v in res["rel_depth_per_setpoint"].items()))
    print(f"  spectral shape vs force: per-frequency beta {res['spectrum_beta']:.2f}, tilt delta "
          f"{res['spectrum_tilt']:+.3f} +- {res['spectrum_tilt_se']:.3f} per log(level) per log(f) "
          f"over setpoints <= {CLEAN_MAX_SETPOINT:g} (0 = force-invariant shape)")
    print(f"  speed response: amplitude ~ speed^alpha, alpha = {res['speed_alpha']:+.3f} +- {res['speed_alpha_se']:.3f}")
    print("    relative depth per speed: " + ", ".join(f"{k:g}: {v:.4f}" for k, v in res["amp_per_speed"].items()))
    print(f"  across taxels of one recording: amplitude ~ level^{res['taxel_beta']:.2f}")
    print(f"  per-taxel level pattern (log level minus its taxel mean): between fabrics sd "
          f"{res['plate_level_spread']:.3f}, stable across the speed x force conditions (mean correlation "
          f"{res['pattern_stability']:.2f}); trial to trial within a fabric and condition sd "
          f"{res['contact_level_spread']:.3f}")
    print("  force response per fabric (mean excess power, setpoints <= %g): beta " % CLEAN_MAX_SETPOINT + ", ".join(
        f"{k} {v:.2f}" for k, v in res["force_beta_fabric"].items()) + f"; mean {res['force_beta_pooled']:.2f}; textured fabrics ({', '.join(res['textured_fabrics'])}): "
          f"{res['force_beta_textured']:.2f} -> model depth_level_exponent = beta - 1 = "
          f"{res['force_beta_textured'] - 1:.2f}")
    for k, v in res["rel_depth_fabric"].items():
        print(f"    {k}: relative depth " + ", ".join(f"{d:.4f}" for d in v))
    if "board_amp" in res:
        print("  Board10mm fundamental amplitude / level vs speed: " + ", ".join(
            f"{k:g} mm/s: {v:.4f}" for k, v in sorted(res["board_amp"].items())) +
            f"; alpha {res['board_alpha'][0]:+.3f} +- {res['board_alpha'][1]:.3f}")
    if "board_period_mm" in res:
        print("  Board10mm dominant spatial period (speed / peak frequency): " + ", ".join(
            f"{k:g} mm/s: {v:.1f} mm" for k, v in res["board_period_mm"].items()))


def model_responses(forces=(250.0, 500.0, 1000.0), speeds=(40.0, 60.0, 80.0, 100.0, 120.0), letter: str = "L"):
    """The simulated sensor's level, modulation amplitude and spectrum on texture ``letter`` (mean over the 18
    taxels, 240 mm of travel, no noise): dict of ``level[F]``, ``amp[F]`` at 80 mm/s, ``amp_speed[v]`` at 500 g,
    ``spectrum[F]`` (freq Hz, normalised PSD) at 80 mm/s."""
    import dataclasses

    from rigctl.simulation.model import SensorConfig, SensorModel

    sensor = SensorModel(dataclasses.replace(SensorConfig(), noise_counts=0.0))
    rng = np.random.default_rng(0)
    out = {"level": {}, "amp": {}, "amp_speed": {}, "spectrum": {}}

    def render(F, v):
        n = int(240.0 / v * 1000)
        pos = np.arange(n) * v / 1000.0
        x = sensor.render(letter, pos, F, rng).astype(np.float64) - sensor.offset
        return x

    for F in forces:
        x = render(F, 80.0)
        out["level"][F] = float(x.mean())
        out["amp"][F] = float(x.std(axis=0).mean())
        fr, p = welch(x - x.mean(0), fs=1000.0, nperseg=2048, axis=0)
        out["spectrum"][F] = (fr, p.mean(axis=1))
    for v in speeds:
        out["amp_speed"][v] = float(render(500.0, v).std(axis=0).mean())
    return out


def figure(res: dict, meas: dict, path: Path) -> None:
    """Three panels: force response (level and relative depth), speed response, spectral shape versus force."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mod = model_responses()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    # (a) level and relative depth vs force, normalised at the middle force
    Fm = np.array(sorted(res["level_per_setpoint"]))
    lm = np.array([res["level_per_setpoint"][F] for F in Fm])
    mid = int(np.argmin(np.abs(Fm - CLEAN_MAX_SETPOINT)))
    ax[0].plot(Fm / Fm[mid], lm / lm[mid], "o-", color="C0", label="FabricSlide level (all fabrics)")
    Fc = Fm[Fm <= CLEAN_MAX_SETPOINT]
    for i, lab in enumerate(res["textured_fabrics"]):
        d = np.array(res["rel_depth_fabric"][lab])
        ax[0].plot(Fc / Fm[mid], d / d[-1], "s-", color=f"C{i + 1}", label=f"FabricSlide relative depth, {lab}")
    dm = np.array([res["rel_depth_per_setpoint"][F] for F in Fm])
    ax[0].plot(Fm / Fm[mid], dm / dm[mid], "x:", color="grey",
               label="FabricSlide relative depth, pooled\n(setpoints > 180: force-loop oscillation)")
    Fs = np.array(sorted(mod["level"]))
    ls = np.array([mod["level"][F] for F in Fs])
    ds = np.array([mod["amp"][F] / mod["level"][F] for F in Fs])
    ax[0].plot(Fs / 500.0, ls / mod["level"][500.0], "o--", color="C0", alpha=0.6, label="model level (texture L)")
    ax[0].plot(Fs / 500.0, ds / (mod["amp"][500.0] / mod["level"][500.0]), "s--", color="C3", alpha=0.8,
               label="model relative depth (texture L)")
    ax[0].set_xscale("log", base=2)
    ax[0].set_yscale("log", base=2)
    ax[0].set_xlabel("force / middle force (FabricSlide: setpoint / 180; model: F / 500 g)")
    ax[0].set_ylabel("relative to the middle force")
    ax[0].set_title(f"force response: amplitude ~ level^{res['force_beta_textured']:.2f} (Canvas, Linen)",
                    fontsize=10)
    ax[0].legend(fontsize=6.5)
    # (b) relative modulation vs speed: the ridged board (clean: one 20 mm period) and the model
    if "board_amp" in res:
        vb = np.array(sorted(res["board_amp"]))
        ab = np.array([res["board_amp"][v] for v in vb])
        ax[1].plot(vb, ab / np.exp(np.mean(np.log(ab))), "o-", label="FabricSlide Board10mm (20 mm ridges)")
    vm = np.array(sorted(res["amp_per_speed"]))
    am = np.array([res["amp_per_speed"][v] for v in vm])
    ax[1].plot(vm, am / np.exp(np.mean(np.log(am))), "x:", color="grey",
               label="FabricSlide fabrics, 4-16 Hz band\n(the fabric's spatial spectrum moves through the band)")
    vs = np.array(sorted(mod["amp_speed"]))
    asim = np.array([mod["amp_speed"][v] for v in vs])
    ax[1].plot(vs, asim / np.exp(np.mean(np.log(asim))), "s--", color="C3", label="model (texture L, 500 g)")
    ax[1].set_xscale("log")
    ax[1].set_ylim(0.5, 1.5)
    ax[1].set_xlabel("speed, mm/s")
    ax[1].set_ylabel("modulation amplitude / level, over its geometric mean")
    ax[1].set_title(f"speed response: board alpha = {res['board_alpha'][0]:+.3f} +- {res['board_alpha'][1]:.3f}",
                    fontsize=10)
    ax[1].legend(fontsize=6.5)
    # (c) spectral shape vs force: power at each frequency at the high force over the low force, normalised
    f = meas["freq"]
    band = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1])
    Flo, Fhi = Fm[0], Fc[-1]
    for i, lab in enumerate(res["textured_fabrics"]):
        for v, style in ((10.0, "-"), (150.0, "--")):
            lo = meas["psd"][(meas["fabric"] == lab) & (meas["force"] == Flo) & (meas["speed"] == v)].mean(axis=(0, 2))
            hi = meas["psd"][(meas["fabric"] == lab) & (meas["force"] == Fhi) & (meas["speed"] == v)].mean(axis=(0, 2))
            r = hi[band] / lo[band]
            ax[2].plot(f[band], r / np.exp(np.mean(np.log(r))), style, color=f"C{i + 1}",
                       label=f"FabricSlide {lab} {v:g} mm/s: F{Fhi:g} / F{Flo:g}")
    fr, plo = mod["spectrum"][250.0]
    _, phi = mod["spectrum"][1000.0]
    sig = plo > 1e-3 * plo.max()  # the texture's harmonics
    r = phi[sig] / plo[sig]
    ax[2].plot(fr[sig], r / np.exp(np.mean(np.log(r))), "s", color="C3",
               label="model L 80 mm/s: 1000 g / 250 g (harmonics)")
    ax[2].set_xlim(0, 40)
    ax[2].set_yscale("log", base=2)
    ax[2].set_ylim(0.25, 4)
    ax[2].axhline(1.0, color="k", lw=0.5)
    ax[2].set_xlabel("frequency, Hz")
    ax[2].set_ylabel("power ratio high / low force (normalised)")
    ax[2].set_title(f"spectral shape vs force: tilt {res['spectrum_tilt']:+.2f} (flat = same shape)", fontsize=10)
    ax[2].legend(fontsize=6.5)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"figure -> {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "fabricslide"))
    ap.add_argument("--figure", default="docs/figures/sensor_fit.png")
    ap.add_argument("--no-figure", action="store_true")
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not (data / "fabric").is_dir():
        print(f"error: {data} holds no FabricSlide fabric/ folder (give --data)", file=sys.stderr)
        return 2
    meas = measure(data)
    res = fit(meas)
    _print(res)
    mp = model_parameters(res)
    print("model parameters from the fit (rigctl.simulation.model.SensorConfig):")
    print(f"  gain_spread = sqrt({res['taxel_gain_cv']:.3f}^2 - row-weight CV {mp['row_cv']:.3f}^2) = "
          f"{mp['gain_spread']:.2f}")
    print(f"  noise_corner_hz = {mp['noise_corner_hz']:.0f} (first-order spectrum with the measured flatness)")
    print(f"  noise_counts = sqrt(S0 * pi * fc / 2) = {mp['noise_counts']:.1f} (S0 = floor x (model mid level "
          f"{mp['model_mid_level']:.0f} / FabricSlide mid level)^2 = {mp['noise_density_model']:.3f} counts^2/Hz)")
    print(f"  depth_level_exponent = {mp['depth_level_exponent']:.2f}")
    print(f"  plate_level_spread = {res['plate_level_spread']:.3f}, contact_level_spread = "
          f"{res['contact_level_spread']:.3f}")
    if not args.no_figure:
        figure(res, meas, Path(args.figure))
    return 0


if __name__ == "__main__":
    sys.exit(main())
