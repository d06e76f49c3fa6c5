"""Where on the plate a handheld session's scans sit: the real-time features' windows shifted along the plate, and a
session's shift found from the taxels themselves (issue 78 item 2).

The real-time features (:func:`rigctl.encoding.features.realtime_features`) are ``n_trains`` x 20 windows of 100 ms of
scaled time from the cut at the tracked 50 mm mark; at the reference speed (100 mm/s) a scaled window is 10 mm of
plate (:data:`WINDOW_MM`). A session whose plate axis reads the finger ``d`` mm off (a calibration touch off, the
tracker re-strapped, the wrist's velocity bias: :class:`rigctl.simulation.operator.OperatorConfig`) cuts every scan
``d`` mm early or late, and its windows hold the texture ``d / 10`` windows away from where the training block's did.
:func:`session_shift` finds that shift from a block of the session's scans whose textures are known (the calibration
block the paper records before the real-time block, cued plate by plate): the shift, in steps of
:data:`SHIFT_STEP_WINDOWS`, whose shifted per-texture means are nearest the training block's;
:func:`shift_windows` moves a scan's windows by it (linear interpolation between neighbouring windows; the end
windows held). Measured (docs/results.md 3b): axis offsets of 0/2/4/6/8 mm read 0/2/5/7/9 mm; the block's mean
over textures instead (no labels) read +10 mm at 2 mm and -15 mm at 4 mm (the textures' patterns average out).

:func:`window_statistics` is a feature that does not depend on the place: per train, the windows' mean, spread and
mean change (the live classifier's default: it kept 84-90 % where the windows' own features fell from 88 % to 6 %).
"""

from __future__ import annotations

import numpy as np

from rigctl.encoding.speed import REALTIME_REFERENCE_SPEED_MM_S, WINDOW_S

__all__ = ["WINDOW_MM", "SHIFT_STEP_WINDOWS", "ALIGNMENT_TOLERANCE_MM", "session_shift", "shift_windows",
           "window_statistics"]

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


def session_shift(templates: dict[str, np.ndarray], block: np.ndarray, labels: np.ndarray, n_trains: int, *,
                  max_shift: float = 1.5, step: float = SHIFT_STEP_WINDOWS, edge_windows: int = 2) -> float:
    """The shift (windows) that best aligns a block of a session's scans with the training block (module
    docstring): the one in ``[-max_shift, max_shift]`` (steps of ``step``) whose shifted per-texture block means
    are nearest the training block's per-texture means (least squares over every train's windows but the
    ``edge_windows`` at each end, which a shift fills by holding).

    Parameters
    ----------
    templates : texture -> (n_trains * n_windows,) the training block's mean features of that texture.
    block : (m, n_trains * n_windows) the session's scans (e.g. its calibration block: the cued textures).
    labels : (m,) their textures (those without a template are ignored).
    n_trains : trains per scan.

    Returns
    -------
    The shift, windows (:func:`shift_windows`'s sign: times :data:`WINDOW_MM` is mm of plate; positive: the
    session's scans start earlier on the plate than the training block's).

    Raises
    ------
    ValueError
        Shapes that do not match, or no scan of a texture with a template.
    """
    b = np.atleast_2d(np.asarray(block, np.float64))
    y = np.asarray(labels).astype(str)
    known = [c for c in np.unique(y) if c in templates]
    if b.shape[0] != y.size or not known:
        raise ValueError(f"need (m, f) scans with m labels, some of a trained texture; got {b.shape}, {y.size} labels")
    pairs = []
    for c in known:
        t = np.asarray(templates[c], np.float64).ravel()
        if t.size != b.shape[1]:
            raise ValueError(f"block must be (m, {t.size}), got {b.shape}")
        pairs.append((t.reshape(n_trains, -1), b[y == c].mean(axis=0)))
    w = pairs[0][0].shape[1]
    inner = slice(edge_windows, max(edge_windows + 1, w - edge_windows))
    shifts = np.round(np.arange(-max_shift, max_shift + step / 2, step), 6)
    err = [sum(float(np.sum((t[:, inner] - shift_windows(m, n_trains, s).reshape(n_trains, -1)[:, inner]) ** 2))
               for t, m in pairs) for s in shifts]
    return float(shifts[int(np.argmin(err))])


def window_statistics(features: np.ndarray, n_trains: int) -> np.ndarray:
    """A place-free feature (issue 78 item 2): per train, the mean rate over its windows, their standard deviation
    and the mean absolute change between neighbouring windows (how the texture's rate varies, not where).

    Parameters
    ----------
    features : (n, n_trains * n_windows) or (n_trains * n_windows,), train-major, spikes/s.
    n_trains : trains per scan.

    Returns
    -------
    (n, 3 * n_trains) float64 (or (3 * n_trains,)): ``[means..., sds..., mean |change|...]``, spikes/s.

    Raises
    ------
    ValueError
        The feature count is not a multiple of ``n_trains``, or fewer than 2 windows.
    """
    x = np.asarray(features, np.float64)
    x2 = np.atleast_2d(x)
    if x2.shape[1] % n_trains or x2.shape[1] // n_trains < 2:
        raise ValueError(f"{x2.shape[1]} features are not {n_trains} trains of >= 2 equal windows")
    cube = x2.reshape(x2.shape[0], n_trains, -1)
    out = np.concatenate([cube.mean(axis=2), cube.std(axis=2), np.abs(np.diff(cube, axis=2)).mean(axis=2)], axis=1)
    return out[0] if x.ndim == 1 else out
