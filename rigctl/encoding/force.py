"""Force invariance: input scaling coefficients found by bisection (paper eq. 1; Results and Methods, force
invariance module).

For texture T, taxel i, speed j and force k, find ``C`` such that::

    | SR(Phi_SA(C R_ijk^T)) - SR(Phi_SA(R_ij,500^T)) | < eps         (1)

with ``SR`` the mean spike rate (spikes / trial duration, averaged over the condition's trials) of the SA encoding
``Phi_SA`` (eqs. 3-5, k = 100). The SA encoding is monotone in its input, so bisection applies; eps = 0.1 spikes/s;
coefficients are capped at 5 (the paper: 62 of 4320 did not converge, all very low-activity trains, and were limited
to 5). The 500 g reference conditions have C = 1 by definition.

Bisection is vectorised: every coefficient keeps its own bracket ``[lo, hi]`` (start ``[0, c_max]``), and each step
encodes the trials of *all* still-open coefficients in **one** kernel call with per-(trial, taxel) gains.

Two groupings:

- per texture (the paper's): one coefficient per (texture, taxel, speed, force);
- label-free: one per (taxel, speed, force), pooled over textures, because the per-texture coefficients use the very
  label the classifier is asked to predict (a deployable system does not know the texture).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Self

import numpy as np

from rigctl.encoding.fused import run_fused
from rigctl.encoding.izhikevich import FS_HZ, K_SA, TONIC_SPIKING, IzhikevichParams, Ragged, as_ragged

__all__ = ["ForceFit", "fit_force_coefficients", "fit_force_groupings", "fit_scalers", "ForceCoefficients",
           "REFERENCE_FORCE_G", "EPSILON", "C_MAX"]

REFERENCE_FORCE_G = 500.0  #: the force whose SA rate is the target (Methods)
EPSILON = 0.1  #: spikes/s tolerance of eq. (1)
C_MAX = 5.0  #: the cap on a coefficient (Methods)


@dataclass
class ForceFit:
    """Result of :func:`fit_force_coefficients`.

    Attributes
    ----------
    coeffs : (n_groups, n_taxels) float64, C of eq. (1) (1 for reference groups).
    converged : (n_groups, n_taxels) bool, |rate - target| < eps reached.
    target_rate, rate : (n_groups, n_taxels) float64 spikes/s: the reference rate and the rate at ``coeffs``.
    n_iter : bisection steps run (each one kernel call).
    """

    coeffs: np.ndarray
    converged: np.ndarray
    target_rate: np.ndarray
    rate: np.ndarray
    n_iter: int

    @property
    def n_not_converged(self) -> int:
        return int((~self.converged).sum())

    @property
    def n_coefficients(self) -> int:
        return int(self.converged.size)


def _group_rates(counts, durations, group, n_groups, trial_mask=None):
    """Mean over a group's trials of count / duration -> (n_groups, n_ch)."""
    rates = counts / durations[:, None]
    if trial_mask is not None:
        rates = np.where(trial_mask[:, None], rates, 0.0)
        w = trial_mask.astype(np.float64)
    else:
        w = np.ones(group.size)
    n_ch = counts.shape[1]
    sums = np.zeros((n_groups, n_ch))
    np.add.at(sums, group, rates)
    n = np.bincount(group, weights=w, minlength=n_groups)
    return np.divide(sums, n[:, None], out=np.zeros_like(sums), where=n[:, None] > 0)


def fit_force_coefficients(readings, group, reference, *, offset=0.0, scale=1.0, eps: float = EPSILON,
                           c_max: float = C_MAX, k: float = K_SA, fs: float = FS_HZ, max_iter: int = 40,
                           params: IzhikevichParams = TONIC_SPIKING, dtype=np.float32) -> ForceFit:
    """Solve eq. (1) for every (group, taxel) at once by vectorised bisection.

    Parameters
    ----------
    readings : :class:`~rigctl.encoding.izhikevich.Ragged`, (n_trials, n_samples, n_taxels) array or list of
        (n_i, n_taxels) trials: normalised 0-1 readings, or raw ones with ``offset``/``scale``
        (``(x - offset) * scale`` in [0, 1]).
    group : (n_trials,) int, the coefficient group of each trial (e.g. the index of its (texture, speed, force)).
    reference : (n_groups,) int, the reference group of each group (the same texture/speed at 500 g);
        ``reference[g] == g`` marks a reference group (coefficient 1).
    eps : spikes/s tolerance. c_max : the cap (bracket is [0, c_max]). k : SA scale (100). fs : Hz.
    max_iter : bisection steps at most (c_max / 2**40 is far below any meaningful precision).
    dtype : the SA kernel's state (:mod:`rigctl.encoding.fused`; float32 default).

    Returns
    -------
    ForceFit

    Raises
    ------
    ValueError
        on mismatched sizes, a group without trials used as a reference, or a reference group that is itself
        referred to another group.
    """
    return fit_force_groupings(readings, [(group, reference)], offset=offset, scale=scale, eps=eps, c_max=c_max,
                               k=k, fs=fs, max_iter=max_iter, params=params, dtype=dtype)[0]


def _check_grouping(group, reference, n_trials: int) -> tuple[np.ndarray, np.ndarray]:
    group = np.asarray(group, dtype=np.int64)
    reference = np.asarray(reference, dtype=np.int64)
    n_groups = reference.size
    if group.shape != (n_trials,):
        raise ValueError(f"group must be ({n_trials},), got {group.shape}")
    if group.size and (group.min() < 0 or group.max() >= n_groups):
        raise ValueError("group indices out of range of reference")
    if np.any(reference[reference] != reference):
        raise ValueError("a reference group must be its own reference")
    n_per_group = np.bincount(group, minlength=n_groups)
    is_ref = reference == np.arange(n_groups)
    if np.any(n_per_group[reference[~is_ref]] == 0):
        raise ValueError("some groups refer to a reference group without trials")
    return group, reference


def fit_force_groupings(readings, groupings, *, offset=0.0, scale=1.0, eps: float = EPSILON, c_max: float = C_MAX,
                        k: float = K_SA, fs: float = FS_HZ, max_iter: int = 40,
                        params: IzhikevichParams = TONIC_SPIKING, dtype=np.float32) -> list[ForceFit]:
    """:func:`fit_force_coefficients` for several groupings of the same trials at once (e.g. per texture and
    label-free): each bisection step is **one** pass of the fused SA kernel over the trials still open in any
    grouping, one SA population per grouping, so the readings are read once per step for all coefficients.

    Parameters
    ----------
    readings : Ragged, array or list
        As in :func:`fit_force_coefficients`, or a list of :class:`~rigctl.encoding.izhikevich.Ragged` blocks
        (trials in block order, as the pipeline reads them; no concatenated copy is made).
    groupings : list of (group, reference) pairs
        Each as in :func:`fit_force_coefficients`. The other parameters are those of :func:`fit_force_coefficients`.

    Returns
    -------
    list of ForceFit, one per grouping.
    """
    if isinstance(readings, (list, tuple)) and readings and all(isinstance(r, Ragged) for r in readings):
        blocks = list(readings)  # trials read in blocks (the pipeline's batches): used where they are
    else:
        blocks = [as_ragged(readings)]
    n_ch = blocks[0].n_channels
    if any(b.n_channels != n_ch for b in blocks):
        raise ValueError("every block of trials must have the same channels")
    lengths = np.concatenate([b.lengths for b in blocks])
    bounds = np.cumsum([0] + [b.n_trials for b in blocks])
    groups = [_check_grouping(g, r, lengths.size) for g, r in groupings]
    durations = lengths / fs
    if np.any(durations <= 0):
        raise ValueError("empty trial")
    izh = (params.a, params.b, params.c, params.d, params.v_peak)

    def rates_at(coeff_groups: list[np.ndarray], masks: list[np.ndarray], groups: list[Any],
                 one_gain: bool = False) -> list[np.ndarray]:
        """The groups' rates at these coefficients; ``one_gain``: every grouping's gains are the same (the
        targets: C = 1), so one SA population serves them all (the same counts, half the kernel's work)."""
        active = np.logical_or.reduce(masks)
        gains = [cg[g] for cg, (g, _) in zip(coeff_groups, groups)][:1 if one_gain else None]  # (n_trials, n_ch)
        counts = np.concatenate([
            run_fused(b.data, b.starts, offset=offset, scale=scale, sa_gains=[g[t0:t1] for g in gains], k_sa=k,
                      ra=False, fs=fs, izhikevich=izh, dtype=dtype, want_times=False, active=active[t0:t1]).counts
            for b, t0, t1 in zip(blocks, bounds[:-1], bounds[1:])], axis=1)
        return [_group_rates(counts[0 if one_gain else i], durations, g, r.size, m)
                for i, ((g, r), m) in enumerate(zip(groups, masks))]

    is_ref = [r == np.arange(r.size) for _, r in groups]
    targets = rates_at([np.ones((r.size, n_ch)) for _, r in groups], [ir[g] for ir, (g, _) in zip(is_ref, groups)],
                       groups, one_gain=True)
    state = []
    for (g, r), ir, tr in zip(groups, is_ref, targets):
        n_per_group = np.bincount(g, minlength=r.size)
        done = np.repeat(ir[:, None], n_ch, axis=1) | (n_per_group[:, None] == 0)
        target = tr[r]
        state.append({"n_iter": 0, "coeffs": np.ones((r.size, n_ch)), "rate": target.copy(), "target": target,
                      "done": done,
                      "converged": done.copy(), "lo": np.zeros((r.size, n_ch)),
                      "hi": np.full((r.size, n_ch), float(c_max))})
    n_iter = 0
    while not all(st["done"].all() for st in state) and n_iter < max_iter:
        run = [i for i, st in enumerate(state) if not st["done"].all()]  # groupings still open: one population each
        mids = [0.5 * (state[i]["lo"] + state[i]["hi"]) for i in run]
        masks = [~state[i]["done"].all(axis=1)[groups[i][0]] for i in run]
        rs = rates_at([np.where(state[i]["done"], state[i]["coeffs"], mid) for i, mid in zip(run, mids)], masks,
                      [groups[i] for i in run])
        n_iter += 1
        for i, mid, r in zip(run, mids, rs):
            st = state[i]
            st["n_iter"] += 1
            open_ = ~st["done"]
            ok = open_ & (np.abs(r - st["target"]) < eps)
            st["coeffs"][open_] = mid[open_]
            st["rate"][open_] = r[open_]
            st["converged"] |= ok
            st["done"] |= ok
            low = open_ & ~ok & (r < st["target"])
            st["lo"][low] = mid[low]
            high = open_ & ~ok & (r >= st["target"])
            st["hi"][high] = mid[high]
            # once the kernel's gains at lo and hi (k C in its dtype) are equal or adjacent numbers, every further
            # midpoint rounds to one of them: an input already run, so the rate can no longer come within eps
            # (a jump of the rate): stop the coefficient, not converged, as max_iter would leave it
            g_lo, g_hi = (k * st["lo"]).astype(dtype), (k * st["hi"]).astype(dtype)
            st["done"] |= open_ & ~ok & (np.nextafter(g_lo, np.inf) >= g_hi)
    # not converged: the bracket closed on a jump of the rate (or the target is out of reach below c_max).
    return [ForceFit(st["coeffs"], st["converged"], st["target"], st["rate"], st["n_iter"]) for st in state]


def _condition(values) -> np.ndarray:
    """A speed or force as a grouping key: rounded to 1e-3; unknown (NaN) values become -inf, one condition of
    their own (NaN would not equal itself, so every such trial would be a group without a reference)."""
    v = np.round(np.asarray(values, float), 3)
    return np.where(np.isnan(v), -np.inf, v)


def _key_index(keys: np.ndarray):
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)


class ForceCoefficients:
    """Eq. (1)'s coefficients of labelled trials: :meth:`fit_labels` finds them (per texture or label-free),
    :meth:`coefficients_for` gives each trial its coefficients (the SA input gains), :meth:`table` lists them. The
    encoder's (:func:`rigctl.encoding.pipeline.encode_session`); :class:`rigctl.encoding.estimators.ForceScaler` is
    the same as a scikit-learn transformer (this module does not import scikit-learn: the encoder starts without it).

    Parameters
    ----------
    label_free : False -> one coefficient per (texture, taxel, speed, force) (the paper); True -> per
        (taxel, speed, force), pooled over textures.
    reference_force_g, eps, c_max, k, max_iter, fs : see :func:`fit_force_coefficients`.

    Attributes (after fitting)
    --------------------------
    keys_ : (n_groups, 3) float64 rows (texture code, speed mm/s, force g); texture code = index into
        ``textures_`` (-1 for label-free).
    textures_ : list of texture labels seen.
    coeffs_, converged_ : (n_groups, n_taxels).
    fit_ : the :class:`ForceFit`.
    n_not_converged_ : int.
    """

    def __init__(self, *, label_free: bool = False, reference_force_g: float = REFERENCE_FORCE_G,
                 eps: float = EPSILON, c_max: float = C_MAX, k: float = K_SA, max_iter: int = 40, fs: float = FS_HZ):
        self.label_free = label_free
        self.reference_force_g = reference_force_g
        self.eps = eps
        self.c_max = c_max
        self.k = k
        self.max_iter = max_iter
        self.fs = fs

    def _keys(self, texture, speed_mm_s, force_g):
        speed = np.asarray(speed_mm_s, float).reshape(-1)
        if self.label_free or texture is None:
            tcode = np.full(speed.size, -1.0 if self.label_free else -2.0)
        else:
            texture = np.asarray(texture).astype(str)
            lookup = {t: i for i, t in enumerate(self.textures_)}
            tcode = np.array([lookup.get(t, -2) for t in texture], dtype=np.float64)
        return np.column_stack([tcode, _condition(speed), _condition(force_g)])

    def fit_labels(self, readings, texture, speed_mm_s, force_g, *, offset=0.0, scale=1.0) -> Self:
        """Fit on readings and one label per trial (texture, speed mm/s, force g): what
        :meth:`rigctl.encoding.estimators.ForceScaler.fit` and :func:`rigctl.encoding.pipeline.encode_session`
        call.

        Raises
        ------
        ValueError
            if a (texture, speed) has no trial at the reference force.
        """
        group, reference = self._grouping(texture, speed_mm_s, force_g)
        fit = fit_force_coefficients(readings, group, reference, offset=offset, scale=scale, eps=self.eps,
                                     c_max=self.c_max, k=self.k, fs=self.fs, max_iter=self.max_iter)
        return self._adopt(fit)

    def _grouping(self, texture, speed_mm_s, force_g) -> tuple[np.ndarray, np.ndarray]:
        """(group (n_trials,), reference (n_groups,)) of labelled trials; sets ``textures_`` and ``keys_``.
        Raises ValueError as :meth:`fit`."""
        self.textures_ = sorted(set(np.asarray(texture).astype(str).tolist()))
        keys = self._keys(texture, speed_mm_s, force_g)
        uniq, group = _key_index(keys)
        ref_key = uniq.copy()
        ref_key[:, 2] = round(self.reference_force_g, 3)
        index = {tuple(r): i for i, r in enumerate(uniq)}
        missing = [tuple(r) for r in ref_key if tuple(r) not in index]
        if missing:
            def name(m):
                tex = "all textures" if m[0] < 0 else self.textures_[int(m[0])]
                return f"{tex} at {'unknown speed' if np.isinf(m[1]) else f'{m[1]:g} mm/s'}"

            conds = [name(m) for m in sorted({m[:2] for m in missing})]
            shown = ", ".join(conds[:6]) + (f" (+{len(conds) - 6} more)" if len(conds) > 6 else "")
            raise ValueError(f"no trials at the reference force {self.reference_force_g:g} g for {len(conds)} "
                             f"(texture, speed) conditions: {shown}")
        self.keys_ = uniq
        return group, np.array([index[tuple(r)] for r in ref_key], dtype=np.int64)

    def _adopt(self, fit: ForceFit) -> Self:
        self.fit_ = fit
        self.coeffs_ = fit.coeffs
        self.converged_ = fit.converged
        self.n_not_converged_ = fit.n_not_converged
        return self

    def coefficients_for(self, texture, speed_mm_s, force_g) -> np.ndarray:
        """(n_trials, n_taxels) float64 coefficients for labelled trials; conditions not seen in ``fit`` (and, per
        texture, trials whose ``texture`` is None) get 1.0."""
        keys = self._keys(texture, speed_mm_s, force_g)
        index = {tuple(r): i for i, r in enumerate(self.keys_)}
        rows = np.array([index.get(tuple(r), -1) for r in keys], dtype=np.int64)
        out = np.ones((rows.size, self.coeffs_.shape[1]))
        out[rows >= 0] = self.coeffs_[rows[rows >= 0]]
        return out

    def table(self) -> np.ndarray:
        """Structured array, one row per coefficient: texture (str, ``"*"`` for label-free), speed_mm_s, force_g
        (NaN: unknown), taxel, coeff, converged, target_rate, rate (spikes/s)."""
        n_g, n_ch = self.coeffs_.shape
        tex = ["*" if c < 0 else self.textures_[int(c)] for c in self.keys_[:, 0]]
        dt = np.dtype([("texture", f"U{max([1] + [len(t) for t in tex])}"), ("speed_mm_s", "f4"), ("force_g", "f4"),
                       ("taxel", "u2"), ("coeff", "f8"), ("converged", "?"), ("target_rate", "f8"), ("rate", "f8")])
        out = np.zeros(n_g * n_ch, dtype=dt)
        out["texture"] = np.repeat(np.array(tex, dtype=str), n_ch)
        out["speed_mm_s"] = np.repeat(np.where(np.isinf(self.keys_[:, 1]), np.nan, self.keys_[:, 1]), n_ch)
        out["force_g"] = np.repeat(np.where(np.isinf(self.keys_[:, 2]), np.nan, self.keys_[:, 2]), n_ch)
        out["taxel"] = np.tile(np.arange(n_ch), n_g)
        out["coeff"] = self.coeffs_.ravel()
        out["converged"] = self.converged_.ravel()
        out["target_rate"] = self.fit_.target_rate.ravel()
        out["rate"] = self.fit_.rate.ravel()
        return out


def fit_from_ragged(ragged: Ragged, texture, speed_mm_s, force_g, *, offset=0.0, scale=1.0,
                    label_free: bool = False, **kw) -> ForceCoefficients:
    """Convenience: ``ForceCoefficients(label_free=...).fit_labels(...)``."""
    return ForceCoefficients(label_free=label_free, **kw).fit_labels(ragged, texture, speed_mm_s, force_g, offset=offset,
                                                               scale=scale)


def fit_scalers(scalers: list[ForceCoefficients], readings, texture, speed_mm_s, force_g, *, offset=0.0,
                scale=1.0) -> list[str]:
    """Fit several :class:`ForceCoefficients` (e.g. per texture and label-free) on the same trials at once: one kernel
    pass per bisection step for all of them (:func:`fit_force_groupings`). Each scaler must share ``eps``, ``c_max``,
    ``k``, ``fs`` and ``max_iter`` with the first.

    Returns
    -------
    list of str, one per scaler: "" if fitted, else why not (the ValueError of :meth:`ForceCoefficients.fit_labels`: no trials
    at the reference force); such a scaler is left unfitted.
    """
    errors, groupings, fitted = [], [], []
    for sc in scalers:
        try:
            groupings.append(sc._grouping(texture, speed_mm_s, force_g))
            fitted.append(sc)
            errors.append("")
        except ValueError as exc:
            errors.append(str(exc))
    if fitted:
        s0 = fitted[0]
        fits = fit_force_groupings(readings, groupings, offset=offset, scale=scale, eps=s0.eps, c_max=s0.c_max,
                                   k=s0.k, fs=s0.fs, max_iter=s0.max_iter)
        for sc, fit in zip(fitted, fits):
            sc._adopt(fit)
    return errors

