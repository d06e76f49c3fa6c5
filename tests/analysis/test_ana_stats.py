"""Welch + Cohen's d and the two-proportion z-test + Cohen's h against scipy and hand values."""

import math

import numpy as np
import pytest


def test_welch_matches_scipy():
    from scipy import stats as st

    from rigctl.analysis.stats import welch_test

    rng = np.random.default_rng(0)
    a, b = rng.normal(0.9, 0.01, 20), rng.normal(0.95, 0.03, 20)
    t, p = welch_test(a, b)
    ref = st.ttest_ind(a, b, equal_var=False)
    assert t == pytest.approx(ref.statistic) and p == pytest.approx(ref.pvalue)
    # hand value of the Welch statistic
    se = math.sqrt(a.var(ddof=1) / 20 + b.var(ddof=1) / 20)
    assert t == pytest.approx((a.mean() - b.mean()) / se)


def test_cohens_d_hand_value():
    from rigctl.analysis.stats import cohens_d

    assert cohens_d([1, 2, 3, 4], [2, 3, 4, 5]) == pytest.approx(-1 / math.sqrt(5 / 3))
    assert cohens_d([1, 1, 1], [1, 1, 1]) == 0.0
    assert cohens_d([2, 2], [1, 1]) == math.inf


def test_cohens_h_and_z_hand_values():
    from scipy import stats as st

    from rigctl.analysis.stats import cohens_h, two_proportion_z

    assert cohens_h(0.5, 0.25) == pytest.approx(math.pi / 6)
    z, p = two_proportion_z(60, 100, 40, 100)
    assert z == pytest.approx(0.2 / math.sqrt(0.25 * 0.02))
    assert p == pytest.approx(2 * st.norm.sf(z))
    assert p == pytest.approx(0.004677, abs=2e-6)
    assert two_proportion_z(10, 10, 5, 5) == (0.0, 1.0)
    with pytest.raises(ValueError):
        two_proportion_z(11, 10, 0, 5)
    with pytest.raises(ValueError):
        cohens_h(1.2, 0.5)


def test_stars_follow_the_paper_thresholds():
    from rigctl.analysis.stats import stars_d, stars_h

    assert stars_d(0.001, 1.5) == "**" and stars_d(0.001, 0.7) == "*" and stars_d(0.03, 2) == "*"
    assert stars_d(0.2, 3) == "" and stars_d(0.001, 0.3) == ""
    assert stars_h(0.001, 0.6) == "**" and stars_h(0.04, 0.3) == "*" and stars_h(0.04, 0.1) == ""


def test_comparison_of_repeated_accuracies():
    from rigctl.analysis.stats import Comparison, two_proportion_z

    a = np.full(20, 0.50) + np.linspace(-0.01, 0.01, 20)
    b = np.full(20, 0.80) + np.linspace(-0.01, 0.01, 20)
    c = Comparison.of("speed_scaled", 50, a, b, 400, 400)
    assert c.mean_b - c.mean_a == pytest.approx(0.3)
    assert c.t > 0 and c.p_t < 1e-10 and c.stars_d == "**" and c.stars_h == "**"
    k_a, k_b = round(a.sum() * 400), round(b.sum() * 400)
    assert (c.z, c.p_z) == pytest.approx(two_proportion_z(k_b, 8000, k_a, 8000))


@pytest.mark.parametrize("seed", range(5))
def test_welch_and_z_equal_scipy_stats_on_many_samples(seed):
    """Computed without scipy.stats (its import is ~1.5 CPU-s of every ``rigctl analyze``): the same t, p and z."""
    from scipy import stats as st

    from rigctl.analysis.stats import two_proportion_z, welch_test

    rng = np.random.default_rng(seed)
    na, nb = (int(n) for n in rng.integers(2, 40, 2))
    a, b = rng.normal(0.8, rng.uniform(1e-4, 0.1), na), rng.normal(0.8 + rng.normal(0, 0.02), 0.05, nb)
    for x, y in ((a, b), (b, a), (a, a + 1e-3), (a, np.full(nb, 0.8))):
        ref = st.ttest_ind(x, y, equal_var=False)
        t, p = welch_test(x, y)
        assert t == pytest.approx(ref.statistic, rel=1e-12) and p == pytest.approx(ref.pvalue, rel=1e-9, abs=1e-300)
    k1, k2 = (int(k) for k in rng.integers(0, 100, 2))
    z, p = two_proportion_z(k1, 100, k2, 120)
    assert p == pytest.approx(2 * st.norm.sf(abs(z)), rel=1e-12, abs=1e-300)
