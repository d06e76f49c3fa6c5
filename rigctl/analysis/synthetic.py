"""Synthetic spiking-feature sets with a known answer (tests, benchmarks, docs).

Not a model of the rig (that is :mod:`rigctl.simulation`): a small generative stand-in for the *encoded* features
with the speed and force confounds planted explicitly, so the analyses can be checked where the right answer is
known. Each texture has, per spike train, a spatial pattern ``a (1 + sin(2 pi x / period + phase))``:

* ``original``: sampled in 100 ms windows at the trial's speed (windows cover ``speed * 0.1`` mm; the trial lasts
  ``distance / speed``, zero-padded to 60 windows) and scaled by the force gain ``(force / 500 g) ** force_exponent``;
* ``speed_scaled``: sampled at the reference speed (20 windows) - speed no longer matters;
* ``force_scaled``: like ``original`` with force gain 1;
* ``speed_force_scaled``: both.

Noise is Gaussian with sd ``noise`` (relative to the pattern amplitude). Shapes follow the sensor layout: SA and RA
per taxel, so the paper's 3x3x2 sensor gives 36 spike trains x 60 windows = 2160 features (unscaled) and 36 x 20 =
720 (speed scaled); a 3x3 single-layer sensor gives 18 trains.
"""

from __future__ import annotations

import numpy as np

from rigctl.analysis.data import FeatureSet
from rigctl.core import PAPER_SENSOR, SensorLayout

__all__ = ["synthetic_features", "random_features"]

PAPER_SPEEDS = (40.0, 60.0, 80.0, 100.0, 120.0)
PAPER_FORCES = (250.0, 500.0, 1000.0)


def synthetic_features(
    trials_per_condition=10,
    *,
    n_textures=16,
    n_channels=None,
    layout: SensorLayout | None = None,
    speeds=PAPER_SPEEDS,
    forces=PAPER_FORCES,
    reference_speed=120.0,
    distance_mm=240.0,
    noise=0.3,
    force_exponent=0.7,
    start_jitter_mm=0.3,
    seed=0,
) -> FeatureSet:
    """A FeatureSet of the four variants with planted speed and force confounds.

    Parameters
    ----------
    trials_per_condition : int
        Trials per (texture, speed, force) cell (the paper: 100).
    n_textures : int
        Textures, lettered from "A" (groups follow the paper's lettering when 16).
    n_channels : int, optional
        Spike trains per trial (even: SA and RA per taxel). Default ``2 * layout.n_channels``.
    layout : SensorLayout, optional
        The sensor (default: the paper's 3x3x2, or ``SensorLayout.for_channels(n_channels // 2)`` when only
        ``n_channels`` is given); stored on the FeatureSet.
    speeds : sequence of float
        mm/s. forces : sequence of float, g.
    reference_speed : float
        mm/s; speed-scaled trials last ``distance_mm / reference_speed`` s.
    distance_mm : float
        Drum travel per trial (240 mm: 6 s at 40 mm/s, 2 s at 120 mm/s, as in the paper).
    noise : float
        Noise sd relative to the pattern amplitude.
    force_exponent : float
        Force gain exponent of the unscaled variants.
    start_jitter_mm : float
        sd of the trial's start position on the drum (mm).
    seed : int

    Returns
    -------
    FeatureSet
        float32 features; ``original``/``force_scaled`` have ``n_channels * 60`` columns (for the paper's speeds),
        the speed-scaled ones ``n_channels * 20``.
    """
    if layout is None:
        layout = PAPER_SENSOR if n_channels in (None, 2 * PAPER_SENSOR.n_channels) else \
            SensorLayout.for_channels(max(1, int(n_channels) // 2))
    if n_channels is None:
        n_channels = 2 * layout.n_channels
    if n_channels != 2 * layout.n_channels:
        raise ValueError(f"n_channels={n_channels} spike trains do not match the {layout.shape_text} sensor "
                         f"(2 x {layout.n_channels} SA/RA trains)")
    rng = np.random.default_rng(seed)
    letters = [chr(ord("A") + i) for i in range(n_textures)]
    # texture amplitude = a common per-channel profile x a texture height: force gain moves one texture's amplitude
    # onto another's (the force confound); the period sets the temporal frequency at a given speed (speed confound)
    height = rng.permutation(np.geomspace(0.5, 2.0, n_textures))
    amp = height[:, None] * rng.uniform(0.8, 1.2, n_channels)[None, :]
    period = rng.permutation(np.geomspace(3.0, 12.0, n_textures))  # mm
    phase = rng.uniform(0, 2 * np.pi, (n_textures, n_channels))
    tex, spd, frc = np.meshgrid(np.arange(n_textures), np.asarray(speeds, float), np.asarray(forces, float),
                                indexing="ij")
    tex = np.repeat(tex.ravel(), trials_per_condition)
    spd = np.repeat(spd.ravel(), trials_per_condition)
    frc = np.repeat(frc.ravel(), trials_per_condition)
    n = len(tex)
    w_max = int(np.ceil(distance_mm / min(speeds) / 0.1 - 1e-9))
    w_ref = int(round(distance_mm / reference_speed / 0.1))
    start = rng.normal(0.0, start_jitter_mm, n)  # start position on the drum, mm (trials start at the same place)

    def render(speed_eff, n_windows, gain, valid_windows):
        t = (np.arange(n_windows) + 0.5) * 0.1  # s
        x = start[:, None] + speed_eff[:, None] * t[None, :]  # (n, W) mm
        arg = 2 * np.pi * x[:, None, :] / period[tex][:, None, None] + phase[tex][:, :, None]
        f = amp[tex][:, :, None] * gain[:, None, None] * (1 + np.sin(arg))
        f += noise * rng.standard_normal(f.shape)
        f *= (np.arange(n_windows)[None, None, :] < valid_windows[:, None, None])
        return f.reshape(n, -1).astype(np.float32)

    gain = (frc / 500.0) ** force_exponent
    ones = np.ones(n)
    n_valid = np.round(distance_mm / spd / 0.1).astype(int)
    ref = np.full(n, float(reference_speed))
    full = np.full(n, w_ref)
    feats = {
        "original": render(spd, w_max, gain, n_valid),
        "speed_scaled": render(ref, w_ref, gain, full),
        "force_scaled": render(spd, w_max, ones, n_valid),
        "speed_force_scaled": render(ref, w_ref, ones, full),
    }
    return FeatureSet(feats, np.array(letters)[tex], spd, frc, source="synthetic",
                      attrs={"trials_per_condition": trials_per_condition}, layout=layout)


def random_features(n_trials=24_000, n_features=(2160, 720, 2160, 720), *, n_textures=16, seed=0,
                    zero_pad=False) -> FeatureSet:
    """Paper-sized random feature matrices with the paper's label layout (benchmarks).

    Parameters
    ----------
    n_trials : int
        Multiple of ``n_textures * 15`` (the paper: 24,000 = 16 x 15 x 100).
    n_features : tuple of 4 int
        Columns of original, speed_scaled, force_scaled, speed_force_scaled.
    zero_pad : bool
        Pad the unscaled variants (original, force_scaled) as the encoder does: a trial at speed ``v`` lasts
        ``240 mm / v`` (6-2 s), so its 36 trains fill ``2400 / v`` of their 60 windows (columns train-major)
        and the rest are zero.

    Returns
    -------
    FeatureSet
        float32 Gaussian features with a weak class signal in a few hundred columns (so LDA has work to do).
    """
    rng = np.random.default_rng(seed)
    per = n_trials // (n_textures * 15)
    tex, spd, frc = np.meshgrid(np.arange(n_textures), np.asarray(PAPER_SPEEDS), np.asarray(PAPER_FORCES),
                                indexing="ij")
    tex = np.repeat(tex.ravel(), per)
    feats = {}
    for name, d in zip(("original", "speed_scaled", "force_scaled", "speed_force_scaled"), n_features):
        x = rng.standard_normal((len(tex), d), dtype=np.float32)
        centres = rng.standard_normal((n_textures, min(d, 200)), dtype=np.float32) * 0.3
        x[:, : centres.shape[1]] += centres[tex]
        x *= np.linspace(3, 0.3, d, dtype=np.float32)
        if zero_pad and name in ("original", "force_scaled") and d % 60 == 0:
            filled = np.ceil(2400.0 / np.repeat(spd.ravel(), per)).astype(int)  # 100 ms windows of 240 mm / v
            x.reshape(len(tex), d // 60, 60)[...] *= (np.arange(60)[None, :] < filled[:, None])[:, None, :]
        feats[name] = x
    letters = np.array([chr(ord("A") + i) for i in range(n_textures)])
    return FeatureSet(feats, letters[tex], np.repeat(spd.ravel(), per), np.repeat(frc.ravel(), per),
                      source="random", layout=PAPER_SENSOR)
