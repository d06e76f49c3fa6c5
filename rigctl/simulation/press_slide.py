"""Another lab's continuous press-and-slide recordings, generated with a known answer (tests, docs, trying
``rigctl import --segment cycles`` without one's own files).

Not a model of this rig (that is :mod:`rigctl.simulation.model`): a stand-in for what issue 23 met in a lab's
files, one continuous recording per texture and session, 9 channels at 100 Hz in counts, where each cycle is a press
(a 0.15 s raised-cosine ramp onto the texture), a slide (the texture's vibration on top of the press level), a
release (0.15 s) and a rest. What the import must cope with is planted on purpose and returned as truth:

* each file its own period (cycle to cycle +-3 % around it) and its own press level (levels 5x apart),
* a start-up transient before the first press (an offset decaying with a 0.5 s time constant),
* NaN runs (samples 1-2, as a logger writes them, and one run inside the file),
* optionally alternating strong and weak presses (the autocorrelation then peaks higher at twice the period),
* optionally a slow drift of the press level across the file (what a recording-grouped evaluation must not
  learn as texture).

:func:`press_slide_recording` makes one file's samples and its press onsets; :func:`write_press_slide_set` writes a
set of ``.npy`` files (``TEXTURE__R<recording>.npy``) and returns each file's truth.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RATE_HZ", "N_CHANNELS", "PressSlideTruth", "press_slide_recording", "write_press_slide_set",
           "DEFAULT_SET", "LabFile", "lab_set", "write_lab_set"]

RATE_HZ = 100.0
N_CHANNELS = 9
#: ramp onto and off the texture, s
RAMP_S = 0.15
#: the press (ramp, slide, release) lasts this fraction of each cycle; the rest of it is rest
PRESS_FRACTION = 0.55

#: the default set: (texture, period_s, level_counts, n_cycles, alternating presses); 6 files, 3 textures, periods
#: 3.8-7.2 s, levels 40-200 counts (5x), the last file a short one (an outlier in trial count)
DEFAULT_SET = (("felt", 3.8, 40.0, 24, False), ("silk", 4.5, 200.0, 24, True), ("cork", 5.2, 80.0, 24, False),
               ("felt", 5.9, 120.0, 24, False), ("silk", 6.5, 60.0, 24, False), ("cork", 7.2, 160.0, 8, False))

#: the seed of the one sensor every file was recorded with
SENSOR_SEED = 23
#: texture -> vibration frequency during the slide, Hz
TEXTURE_HZ = {"felt": 9.0, "silk": 17.0, "cork": 13.0}


@dataclass
class PressSlideTruth:
    """One generated file: its ``path`` (when written), ``texture``, ``period_s``, ``level_counts``, the press
    ``onsets`` (samples where each press ramp starts), ``n_samples`` and the ``nan_samples`` planted."""

    path: Path | None
    texture: str
    period_s: float
    level_counts: float
    onsets: list[int]
    n_samples: int
    nan_samples: int


def _ramp(n: int) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n, endpoint=False))


def press_slide_recording(period_s: float, level_counts: float, n_cycles: int, *, texture_hz: float = 12.0,
                          seed: int = 0, startup_s: float = 3.0, alternating: bool = False, drift: float = 0.0,
                          nan: bool = True, vibration: float = 1.0, press_fraction: float = PRESS_FRACTION
                          ) -> tuple[np.ndarray, list[int]]:
    """One continuous recording: ``(n, 9)`` float64 counts (NaN where planted) at :data:`RATE_HZ` and the press
    onsets (samples).

    period_s : the file's mean cycle period, s (each cycle +-3 %); level_counts : the press level, counts;
    n_cycles : presses; texture_hz : the slide's vibration, Hz; startup_s : rest with a decaying offset before the
    first press, s; alternating : every other press at 60 % of the level; drift : the press level grows linearly by
    this fraction over the file; nan : plant NaN at samples 1-2 and a 6-sample run in the middle; vibration : the
    slide's vibration relative to the default (0: a static press); press_fraction : the share of each cycle pressed.
    """
    sensor = np.random.default_rng(SENSOR_SEED)  # one sensor for every file: its channel gains and rest levels
    gains = sensor.uniform(0.5, 1.0, N_CHANNELS) * sensor.choice([-1.0, 1.0], N_CHANNELS)
    vib_gains = sensor.uniform(0.1, 0.2, N_CHANNELS)
    base = 450.0 + sensor.uniform(-60, 60, N_CHANNELS)
    rng = np.random.default_rng(seed)
    ramp = int(round(RAMP_S * RATE_HZ))
    n0 = int(round(startup_s * RATE_HZ))
    periods = np.rint(period_s * RATE_HZ * (1 + rng.uniform(-0.03, 0.03, n_cycles))).astype(int)
    n = n0 + int(periods.sum()) + int(0.5 * RATE_HZ)
    env = np.zeros(n)
    vib = np.zeros(n)
    onsets = []
    pos = n0
    for i, p in enumerate(periods):
        press = int(round(press_fraction * p))
        shape = np.ones(press)
        shape[:ramp] = _ramp(ramp)
        shape[press - ramp:] = _ramp(ramp)[::-1]
        strength = (0.6 if alternating and i % 2 else 1.0) * (1 + drift * pos / n)
        env[pos:pos + press] = strength * shape
        t = np.arange(press) / RATE_HZ
        vib[pos:pos + press] = shape * np.sin(2 * np.pi * texture_hz * t + rng.uniform(0, 2 * np.pi))
        onsets.append(pos)
        pos += int(p)
    t = np.arange(n) / RATE_HZ
    startup = 0.6 * np.exp(-t / 0.5) * (t < startup_s)
    x = (base + level_counts * (env[:, None] * gains + vibration * vib[:, None] * vib_gains
                                + startup[:, None] * np.abs(gains))
         + rng.normal(0, 1.5, (n, N_CHANNELS)))
    x = np.clip(np.rint(x), 0, 1023)
    if nan:
        x[1:3, rng.integers(0, N_CHANNELS)] = np.nan
        mid = n // 2 + int(rng.integers(0, int(RATE_HZ)))
        x[mid:mid + 6, rng.integers(0, N_CHANNELS)] = np.nan
    return x, onsets


def write_press_slide_set(folder: str | os.PathLike[str], files: tuple[tuple[str, float, float, int, bool], ...]
                          = DEFAULT_SET, *, seed: int = 0, drift: float = 0.0, nan: bool = True
                          ) -> list[PressSlideTruth]:
    """Write ``files`` (texture, period_s, level_counts, n_cycles, alternating) as ``TEXTURE__R<i>.npy`` in
    ``folder`` (created); returns each file's truth. A file that exists is not overwritten (FileExistsError)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, (texture, period_s, level, n_cycles, alternating) in enumerate(files):
        x, onsets = press_slide_recording(period_s, level, n_cycles, texture_hz=TEXTURE_HZ.get(texture, 12.0),
                                          seed=seed + i, alternating=alternating, drift=drift, nan=nan)
        path = folder / f"{texture}__R{i}.npy"
        if path.exists():
            raise FileExistsError(f"{path} exists")
        np.save(path, x)
        out.append(PressSlideTruth(path, texture, period_s, level, onsets, x.shape[0], int(np.isnan(x).sum())))
    return out


@dataclass(frozen=True)
class LabFile:
    """One file of :func:`lab_set`: its texture, period (s), press level (counts), cycles, and what is wrong with it:
    ``"nan"`` (NaN runs: refused unless ``--nan`` says what to do), ``"flat"`` (no presses: refused),
    ``"doubled"`` (a period twice the others': its row must be flagged), or ``""``."""

    texture: str
    period_s: float
    level_counts: float
    n_cycles: int
    fault: str = ""


def lab_set(n_files: int = 38, *, seed: int = 0) -> list[LabFile]:
    """A lab's 38 continuous recordings (issue 38): 6 textures, 9 channels at 100 Hz, 40-42 press cycles each at
    periods 4.2-5.8 s and press levels 40-200 counts; 4 files with NaN runs, 2 flat (the sensor unplugged), 2 at twice
    the usual period (a slower operator: 10.4 and 11.2 s, beyond twice the set's median), the rest clean."""
    rng = np.random.default_rng(seed)
    textures = ("felt", "silk", "cork", "wool", "denim", "linen")
    faults = ["nan"] * 4 + ["flat"] * 2 + ["doubled"] * 2
    faults += [""] * (n_files - len(faults))
    order = rng.permutation(n_files)
    out = []
    for i in range(n_files):
        fault = faults[order[i]]
        period = float(rng.uniform(4.2, 5.8)) if fault != "doubled" else (10.4, 11.2)[i % 2]
        out.append(LabFile(textures[i % len(textures)], round(period, 2), float(rng.uniform(40, 200)),
                           int(rng.integers(40, 43)), fault))
    return out


def write_lab_set(folder: str | os.PathLike[str], files: list[LabFile] | None = None, *, seed: int = 0
                  ) -> list[tuple[Path, LabFile]]:
    """Write :func:`lab_set` (or ``files``) as ``TEXTURE__R<i>.npy`` in ``folder``; returns each path with its
    truth. A flat file is rest and noise only; the others are :func:`press_slide_recording` (NaN only where the
    fault says so)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, f in enumerate(files if files is not None else lab_set(seed=seed)):
        x, _ = press_slide_recording(f.period_s, f.level_counts, f.n_cycles, texture_hz=TEXTURE_HZ.get(f.texture, 12.0),
                                     seed=seed + 100 + i, nan=f.fault == "nan")
        if f.fault == "flat":
            x = np.rint(np.median(x, axis=0) + np.random.default_rng(seed + i).normal(0, 1.5, x.shape))
        path = folder / f"{f.texture}__R{i}.npy"
        np.save(path, x)
        out.append((path, f))
    return out
