"""Where on the plate a handheld session's scans sit: the real-time features' windows shifted along the plate, and a
session's shift found from the taxels themselves (issue 78 item 2).

The real-time features (:func:`rigctl.encoding.features.realtime_features`) are ``n_trains`` x 20 windows of 100 ms of
scaled time from the cut at the tracked 50 mm mark; at the reference speed (100 mm/s) a scaled window is 10 mm of
plate (:data:`WINDOW_MM`). A session whose plate axis reads the finger ``d`` mm off (a calibration touch off, the
tracker re-strapped, the wrist's velocity bias: :class:`rigctl.simulation.operator.OperatorConfig`) cuts every scan
``d`` mm early or late, and its windows hold the texture ``d / 10`` windows away from where the training block's did.
:func:`session_shift` finds that shift from a block of the session's scans (the calibration block the paper records
before the real-time block): the shift, in steps of :data:`SHIFT_STEP_WINDOWS`, whose shifted block mean correlates
best with the training block's mean, window by window on each train (the texture's pattern along the plate, not its
level); :func:`shift_windows` moves a scan's windows by it (linear interpolation between neighbouring windows; the
end windows held). Neither needs the texture's label.
"""

from __future__ import annotations

import numpy as np

from rigctl.encoding.speed import REALTIME_REFERENCE_SPEED_MM_S, WINDOW_S

__all__ = ["WINDOW_MM", "SHIFT_STEP_WINDOWS", "ALIGNMENT_TOLERANCE_MM", "augment_shifts", "session_shift", "shift_windows",
           "window_spectrum"]

#: the plate length of one scaled window at the reference speed, mm (10)
WINDOW_MM = REALTIME_REFERENCE_SPEED_MM_S * WINDOW_S
#: the shifts :func:`session_shift` tries, windows apart (1 mm)
SHIFT_STEP_WINDOWS = 0.1
#: a session whose scans sit farther than this from the training block's alignment is warned about, mm
ALIGNMENT_TOLERANCE_MM = 2.0


def shift_windows(features: np.ndarray, n_trains: int, shift: float) -> np.ndarray:
    """Each train's windows moved ``shift`` windows earlier (positive: window k takes what window k + shift held):
    linear interpolation between neighbouring windows, the first and last windows held past the ends.

    Parameters
    ----------
    features : (n, n_trains * n_windows) or (n_trains * n_windows,), train-major (the real-time features' order).
    n_trains : trains per scan.
    shift : windows (fractional; 0 returns a copy).

    Returns
    -------
    The same shape, float64.

    Raises
    ------
    ValueError
        The feature count is not a multiple of ``n_trains``.
    """
    x = np.asarray(features, np.float64)
    flat = x.ndim == 1
    x2 = np.atleast_2d(x)
    if x2.shape[1] % n_trains:
        raise ValueError(f"{x2.shape[1]} features are not {n_trains} trains of equal windows")
    w = x2.shape[1] // n_trains
    cube = x2.reshape(x2.shape[0], n_trains, w)
    pos = np.clip(np.arange(w) + float(shift), 0.0, w - 1.0)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, w - 1)
    f = pos - lo
    out = (cube[:, :, lo] * (1.0 - f) + cube[:, :, hi] * f).reshape(x2.shape)
    return out[0] if flat else out


def _pattern(x: np.ndarray, n_trains: int) -> np.ndarray:
    """(n, n_trains * w): each train's windows minus their mean, over their norm (the pattern, not the level)."""
    cube = np.atleast_2d(x).reshape(np.atleast_2d(x).shape[0], n_trains, -1)
    cube = cube - cube.mean(axis=2, keepdims=True)
    norm = np.linalg.norm(cube, axis=2, keepdims=True)
    return (cube / np.where(norm > 0, norm, 1.0)).reshape(cube.shape[0], -1)


def session_shift(template: np.ndarray, block: np.ndarray, n_trains: int, *, max_shift: float = 1.5,
                  step: float = SHIFT_STEP_WINDOWS) -> tuple[float, float]:
    """The shift (windows) that best aligns a block of a session's scans with the training block (module
    docstring): the one in ``[-max_shift, max_shift]`` (steps of ``step``) whose shifted block mean correlates best
    with ``template`` on each train's pattern of windows.

    Parameters
    ----------
    template : (n_trains * n_windows,) the training block's mean features.
    block : (m, n_trains * n_windows) the session's scans (m >= 1; e.g. its calibration block).
    n_trains : trains per scan.

    Returns
    -------
    (shift, correlation): windows (:func:`shift_windows`'s sign; times :data:`WINDOW_MM` is mm of plate), and the
    mean correlation over trains at it (1: the same pattern).

    Raises
    ------
    ValueError
        Shapes that do not match, or an empty block.
    """
    t = np.asarray(template, np.float64).ravel()
    b = np.atleast_2d(np.asarray(block, np.float64))
    if b.shape[0] == 0 or b.shape[1] != t.size:
        raise ValueError(f"block must be (m >= 1, {t.size}), got {b.shape}")
    mean = b.mean(axis=0)
    ref = _pattern(t, n_trains)[0]
    shifts = np.round(np.arange(-max_shift, max_shift + step / 2, step), 6)
    scores = [float(_pattern(shift_windows(mean, n_trains, s), n_trains)[0] @ ref) / n_trains for s in shifts]
    k = int(np.argmax(scores))
    return float(shifts[k]), scores[k]


def window_spectrum(features: np.ndarray, n_trains: int) -> np.ndarray:
    """A place-free feature: the magnitude of each train's Fourier transform over its windows (a shift of the
    windows changes only the phases). (n, n_trains * w) -> (n, n_trains * (w // 2 + 1)) float64."""
    x = np.atleast_2d(np.asarray(features, np.float64))
    cube = x.reshape(x.shape[0], n_trains, -1)
    return np.abs(np.fft.rfft(cube, axis=2)).reshape(x.shape[0], -1)


def augment_shifts(features: np.ndarray, labels: np.ndarray, n_trains: int, *, max_shift: float = 0.8,
                   step: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Training with shifted copies: each scan at every shift in ``[-max_shift, max_shift]`` (steps of ``step``,
    windows; :func:`shift_windows`), with its label. Returns ((n * k, f) features, (n * k,) labels)."""
    x = np.atleast_2d(np.asarray(features, np.float64))
    y = np.asarray(labels)
    shifts = np.round(np.arange(-max_shift, max_shift + step / 2, step), 6)
    return (np.concatenate([shift_windows(x, n_trains, s) for s in shifts]), np.tile(y, shifts.size))
