"""Trial lengths by label: a label hidden in the trial length.

When one texture's trials are shorter than another's (6 s against 8 s), features sized to the longest trial give the
short ones empty last windows, and a classifier reads the texture off the padding (100 % on that texture, whatever
the encoding). :func:`length_imbalance` names it; ``rigctl encode --crop-s S`` cuts every trial to its first S seconds
(:func:`rigctl.encoding.pipeline.encode_session` with ``EncodeParams.crop_s``), a common length, so the length says nothing.

A handheld scan's length is not the protocol's but the operator's (issue 79 item 7): every scan covers the same
stretch of plate (its boundaries are positions), at the speed the operator's hand went, so scans of the same cue differ
in length by design, and a crop to the shortest would cut the slow scans' plate short. For such sessions
(``operator_paced``) a texture's lengths are compared with the other textures' scans of the same cue only where each
has scans enough to show its own spread (an analysis of variance across textures), and the line names the operator's speed, not a
crop.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LENGTH_TOLERANCE", "length_imbalance", "crop_samples"]

#: textures whose median trial durations differ by more than this fraction of the longest are named
LENGTH_TOLERANCE = 0.05


def length_imbalance(texture: np.ndarray, duration_s: np.ndarray, *, tolerance: float = LENGTH_TOLERANCE,
                     speed_mm_s: np.ndarray | None = None, force_g: np.ndarray | None = None,
                     profile: np.ndarray | None = None, operator_paced: bool = False) -> str | None:
    """One line naming the textures whose median trial duration (s) differs from the others' by more than
    ``tolerance`` of the longest **at the same speed, force and profile** (like with like: durations that differ
    only with the mix of conditions each texture was recorded at, as FabricSlide's do, are no label in the length),
    with the crop that removes it (``--crop-s``: the shortest trial of that condition) and what the crop costs, or
    None.

    ``operator_paced`` (a handheld session: each scan's length is the operator's speed over the same stretch of
    plate): a condition counts only where every texture in it has at least two scans and the textures' lengths differ
    beyond their own spread (a one-way ANOVA of the log durations, p < 0.01, besides the ``tolerance``); the line then names the operator's
    speed and no crop.

    texture : (n_trials,) labels; duration_s : (n_trials,) s (NaN entries ignored); speed_mm_s, force_g : (n_trials,)
    each trial's condition, profile : (n_trials,) its speed profile (None: one condition for all)."""
    tex = np.asarray(texture).astype(str)
    dur = np.asarray(duration_s, np.float64)
    n = tex.size
    prof = np.asarray(profile).astype(str) if profile is not None else np.full(n, "")
    # each trial's condition (an unlabelled speed or force, NaN, is a condition of its own: -1)
    cond_v = np.nan_to_num(np.round(np.asarray(speed_mm_s, np.float64), 3), nan=-1.0) if speed_mm_s is not None \
        else np.zeros(n)
    cond_f = np.nan_to_num(np.round(np.asarray(force_g, np.float64), 3), nan=-1.0) if force_g is not None \
        else np.zeros(n)
    ok = np.isfinite(dur) & (dur > 0)
    worst: tuple[float, dict[str, float], np.ndarray, str] | None = None
    for v, f, pr in sorted({(float(a), float(b), str(c)) for a, b, c in zip(cond_v[ok], cond_f[ok], prof[ok])}):
        cell = ok & (cond_v == v) & (cond_f == f) & (prof == pr)
        labels = np.unique(tex[cell])
        if labels.size < 2 or operator_paced and not _beyond_own_spread([dur[cell & (tex == t)] for t in labels]):
            continue
        med = {str(t): float(np.median(dur[cell & (tex == t)])) for t in labels}
        lo, hi = min(med.values()), max(med.values())
        spread = (hi - lo) / hi
        if hi - lo > tolerance * hi and (worst is None or spread > worst[0]):
            shaped = pr not in ("", "constant")  # a speed profile (a ramp, a handheld block's) is named
            named = "speed, force and profile" if shaped else "speed and force"
            values = f"{v:g} mm/s, {f:g} g" + (f", {pr}" if shaped else "")
            where = "" if speed_mm_s is None and force_g is None else f" at the same {named} ({values})"
            worst = (spread, med, cell, where)
    if worst is None:
        return None
    _, med, cell, where = worst
    order = sorted(med, key=lambda t: med[t])
    shown = ", ".join(f"{t} {med[t]:.2f} s" for t in (order[:3] + ["..."] + order[-2:] if len(order) > 5 else order)
                      if t != "...") + (" ..." if len(order) > 5 else "")
    if operator_paced:
        return (f"scan durations differ by texture (median: {shown}){where}: the scans cover the same stretch of "
                "plate, so the operator scanned these textures at different speeds; features in real time "
                "(original, realtime_original) can read the label off that speed, the speed-scaled ones "
                "(speed_scaled, realtime_speed_scaled) use each scan's measured speed")
    crop = math.floor(float(dur[cell].min()) * 100) / 100
    return (f"trial durations differ by texture (median: {shown}){where}: features sized to the longest trial leave "
            "the shorter ones' last windows empty, a label a classifier can read off the padding; rigctl encode "
            f"--crop-s {crop:g} cuts every trial to a common length but drops what the longer ones hold after it: "
            "compare the analysis with and without the crop before choosing")


def _beyond_own_spread(groups: list[np.ndarray]) -> bool:
    """Whether the groups' values (durations, s) differ beyond their own spread: every group has two or more, and a
    one-way ANOVA of their logarithms (an operator's speed scales a scan's length) gives p < 0.01; with no spread
    within the groups, whether they differ at all."""
    if any(g.size < 2 for g in groups):
        return False
    logs = [np.log(g) for g in groups]
    if all(np.all(g == g[0]) for g in logs):
        return len({float(g[0]) for g in logs}) > 1
    from scipy.stats import f_oneway

    return bool(f_oneway(*logs).pvalue < 0.01)


def crop_samples(crop_s: float | None, rate_hz: float) -> int | None:
    """Samples of ``crop_s`` seconds at ``rate_hz`` (None: no crop)."""
    if crop_s is None:
        return None
    return max(1, int(round(float(crop_s) * float(rate_hz))))
