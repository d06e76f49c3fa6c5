"""The nested LDA's predictions for every input count in one pass (compiled): :meth:`NestedLDA.predict_all
<rigctl.analysis.classify.NestedLDA.predict_all>`'s inner loop.

For each trial, the discriminants of every class are running sums over the whitened inputs; after each input the
largest is the prediction with that many inputs. NumPy needed a ``(n_inputs, n_trials, n_classes)`` temporary and
five passes over it (~17 ms a Table 1 split of 2000 trials, 50 inputs, 16 classes: ~14 % of a repetition); this
loop keeps the sums in registers. The same sums in the same order as :meth:`NestedLDA.decision_all
<rigctl.analysis.classify.NestedLDA.decision_all>` (no fast-math: no reassociation, no fused multiply-adds), so the
same predictions; ties go to the first class, as ``argmax``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["nested_argmax", "nested_argmax_numpy"]


def _compiled():
    """The compiled loop (numba imported on first use: ~1-2 CPU-s with its first dispatch)."""
    global _KERNEL
    if _KERNEL is None:
        import numba

        _KERNEL = numba.njit(cache=True, nogil=True)(_nested_argmax)
    return _KERNEL


_KERNEL = None


def _nested_argmax(zw, mw, half_norm, log_prior, out):  # pragma: no cover - compiled by numba
    n_trials, n_max = zw.shape
    k = mw.shape[0]
    acc = np.empty(k)
    for t in range(n_trials):
        acc[:] = 0.0
        for j in range(n_max):
            z = zw[t, j]
            best = -np.inf
            win = 0
            for c in range(k):
                acc[c] += z * mw[c, j]
                v = acc[c] - half_norm[c, j]
                v += log_prior[c]
                if v > best or c == 0:
                    best = v
                    win = c
            out[j, t] = win


def nested_argmax(zw, means_w, half_norm, log_prior):
    """The class with the largest discriminant for each trial and input count.

    Parameters
    ----------
    zw : ndarray (n_trials, n_max) float64
        Whitened inputs.
    means_w : ndarray (n_classes, >= n_max) float64
        Whitened class means.
    half_norm : ndarray (n_classes, >= n_max) float64
        Half the cumulative squared norms of ``means_w``.
    log_prior : ndarray (n_classes,) float64

    Returns
    -------
    ndarray (n_max, n_trials) intp
        ``out[n - 1, t]``: the class index predicted for trial ``t`` from its first ``n`` inputs.
    """
    zw = np.ascontiguousarray(zw, dtype=np.float64)
    out = np.empty((zw.shape[1], zw.shape[0]), np.intp)
    _compiled()(zw, np.ascontiguousarray(means_w, dtype=np.float64),
                   np.ascontiguousarray(half_norm, dtype=np.float64),
                   np.ascontiguousarray(log_prior, dtype=np.float64), out)
    return out


def nested_argmax_numpy(zw, means_w, half_norm, log_prior):
    """:func:`nested_argmax` by NumPy (the same sums in the same order, the same result): a ``(n_trials, n_max,
    n_classes)`` temporary, for calls too small to be worth loading numba."""
    n_max = zw.shape[1]
    d = zw[:, :, None] * means_w[:, :n_max].T[None, :, :]
    np.cumsum(d, axis=1, out=d)
    d -= half_norm[:, :n_max].T[None, :, :]
    d += log_prior[None, None, :]
    return d.argmax(axis=2).T
