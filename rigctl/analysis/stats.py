"""Significance and effect size, as in the paper's Statistical Analysis sections.

* Accuracies of repeated classifications (n = 20 per PC count): two-tailed two-population **Welch's t-test** with
  **Cohen's d** (pooled standard deviation). Asterisks: ``*`` p < 0.05 and d > 0.5; ``**`` p < 0.01 and d > 1
  (Methods, "Tactile Texture Dataset - Statistical Analysis").
* Counts of correct classifications (the real-time demonstration, Fig. S5): two-tailed **two-proportion z-test**
  with **Cohen's h**. Asterisks: ``*`` p < 0.05 and h > 0.2; ``**`` p < 0.01 and h > 0.5.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import ndtr, stdtr

__all__ = ["cohens_d", "welch_test", "cohens_h", "two_proportion_z", "Comparison", "stars_d", "stars_h"]


def cohens_d(a, b) -> float:
    """Cohen's d = (mean(a) - mean(b)) / pooled sd (sample sd, ``ddof=1``).

    Parameters
    ----------
    a, b : array_like (n,), (m,)
        Samples (e.g. 20 accuracies each), n, m >= 2.

    Returns
    -------
    float
        ``inf``/``-inf`` when both samples have zero spread and different means, ``0.0`` when identical constants.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    na, nb = len(a), len(b)
    if na < 2 or nb < 2:
        raise ValueError("Cohen's d needs at least 2 values per sample")
    pooled = np.sqrt(((na - 1) * a.var(ddof=1) + (nb - 1) * b.var(ddof=1)) / (na + nb - 2))
    diff = a.mean() - b.mean()
    if pooled == 0:
        return 0.0 if diff == 0 else float(np.copysign(np.inf, diff))
    return float(diff / pooled)


def welch_test(a, b):
    """Two-tailed Welch's t-test (unequal variances), as :func:`scipy.stats.ttest_ind` ``(equal_var=False)``.

    Returns
    -------
    (t, p) : tuple of float
        ``p = 1.0`` (``t = 0``) when both samples are the same constant; ``p = 0.0`` when two zero-spread samples
        differ (scipy returns nan there).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.var() == 0 and b.var() == 0:
        return (0.0, 1.0) if a.mean() == b.mean() else (float(np.copysign(np.inf, a.mean() - b.mean())), 0.0)
    # scipy.stats.ttest_ind(a, b, equal_var=False)'s statistic, Welch-Satterthwaite degrees of freedom and
    # two-sided p from the t distribution's CDF (scipy.special.stdtr, what its t.sf computes): scipy.stats itself is
    # ~1.5 CPU-s of imports at every `rigctl analyze` (tests/analysis/test_ana_stats.py holds the two equal)
    with np.errstate(all="ignore"):
        va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
        se2 = va + vb
        t = (a.mean() - b.mean()) / np.sqrt(se2)
        df = se2**2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
        p = 2 * stdtr(df, -abs(t))
    return float(t), float(min(p, 1.0))


def cohens_h(p1, p2) -> float:
    """Cohen's h = 2 asin(sqrt(p1)) - 2 asin(sqrt(p2)) for proportions in [0, 1]."""
    for p in (p1, p2):
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"proportion {p} outside [0, 1]")
    return float(2 * np.arcsin(np.sqrt(p1)) - 2 * np.arcsin(np.sqrt(p2)))


def two_proportion_z(k1, n1, k2, n2):
    """Two-tailed two-proportion z-test with pooled proportion.

    Parameters
    ----------
    k1, n1, k2, n2 : int
        Successes and trials of the two samples (n > 0, 0 <= k <= n).

    Returns
    -------
    (z, p) : tuple of float
        ``z = (p1 - p2) / sqrt(P (1 - P) (1/n1 + 1/n2))``, ``P = (k1 + k2) / (n1 + n2)``; ``p = 2 sf(|z|)``.
        ``(0.0, 1.0)`` when the pooled proportion is 0 or 1.
    """
    if min(n1, n2) <= 0 or not (0 <= k1 <= n1 and 0 <= k2 <= n2):
        raise ValueError(f"bad counts k1={k1} n1={n1} k2={k2} n2={n2}")
    p1, p2 = k1 / n1, k2 / n2
    pooled = (k1 + k2) / (n1 + n2)
    se = np.sqrt(pooled * (1 - pooled) * (1 / n1 + 1 / n2))
    if se == 0:
        return 0.0, 1.0
    z = (p1 - p2) / se
    return float(z), float(2 * ndtr(-abs(z)))  # scipy.stats.norm.sf(|z|)


def stars_d(p, d) -> str:
    """The paper's asterisks for Welch + Cohen's d: ``**`` p<0.01 and |d|>1, ``*`` p<0.05 and |d|>0.5, else ``""``."""
    if p < 0.01 and abs(d) > 1:
        return "**"
    if p < 0.05 and abs(d) > 0.5:
        return "*"
    return ""


def stars_h(p, h) -> str:
    """Asterisks for the z-test + Cohen's h: ``**`` p<0.01 and |h|>0.5, ``*`` p<0.05 and |h|>0.2, else ``""``."""
    if p < 0.01 and abs(h) > 0.5:
        return "**"
    if p < 0.05 and abs(h) > 0.2:
        return "*"
    return ""


@dataclass
class Comparison:
    """Original vs one scaled variant at one PC count (accuracies as fractions).

    Attributes: ``variant``, ``n_pcs``, ``mean_a``/``mean_b`` (Original / scaled), Welch ``t``, ``p_t``, ``d``,
    ``stars_d``; pooled-count z-test ``z``, ``p_z``, ``h``, ``stars_h`` (correct counts over all repetitions).
    """

    variant: str
    n_pcs: int
    mean_a: float
    mean_b: float
    t: float
    p_t: float
    d: float
    stars_d: str
    z: float
    p_z: float
    h: float
    stars_h: str

    @classmethod
    def of(cls, variant, n_pcs, acc_a, acc_b, n_tested_a, n_tested_b):
        """Compare repeated accuracies ``acc_a`` (Original) with ``acc_b`` (scaled); ``n_tested_*`` trials per repeat.

        The z-test uses the pooled counts ``round(sum(acc) * n_tested)`` over all repetitions.
        """
        acc_a = np.asarray(acc_a, dtype=np.float64)
        acc_b = np.asarray(acc_b, dtype=np.float64)
        t, pt = welch_test(acc_b, acc_a)
        d = cohens_d(acc_b, acc_a)
        na, nb = n_tested_a * len(acc_a), n_tested_b * len(acc_b)
        ka, kb = int(round(acc_a.sum() * n_tested_a)), int(round(acc_b.sum() * n_tested_b))
        z, pz = two_proportion_z(kb, nb, ka, na)
        h = cohens_h(kb / nb, ka / na)
        return cls(variant, int(n_pcs), float(acc_a.mean()), float(acc_b.mean()), t, pt, d, stars_d(pt, d), z, pz, h,
                   stars_h(pz, h))

    def to_dict(self):
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}
