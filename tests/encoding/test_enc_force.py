"""Force invariance (eq. 1): vectorised bisection on inputs with known answers, the cap, non-convergence."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.encoding.force import fit_force_coefficients
from rigctl.encoding.izhikevich import encode_sa


def test_constant_inputs_converge_to_the_known_ratio():
    # reference group 0 at level 0.3; group 1 at 0.15 (answer C = 2), group 2 at 0.6 (answer C = 0.5)
    n = 1000
    levels = np.array([0.3, 0.15, 0.6])
    x = np.stack([np.full((n, 4), lv) for lv in levels for _ in range(2)])  # 2 trials per group
    group = np.repeat([0, 1, 2], 2)
    fit = fit_force_coefficients(x, group, reference=[0, 0, 0])
    assert fit.converged.all()
    assert fit.n_not_converged == 0
    np.testing.assert_allclose(fit.coeffs[0], 1.0)
    # the scaled rate matches the target within eps (checked independently with the plain encoder given C as the
    # input scale of eq. 1; constant inputs are the model's most rounding-sensitive case: C x rounded apart from
    # k C can move a count by several spikes, tests/encoding/test_enc_fused.py) ...
    for g in (1, 2):
        r = (encode_sa(x[group == g][:1], coeff=fit.coeffs[g]).counts() / (n / 1000.0)).ravel()
        assert np.all(np.abs(r - fit.target_rate[g]) < 0.1)
    # ... and the coefficient is the known ratio up to the width of the spike-count step it landed on (a 1 s
    # trial counts whole spikes, so eps = 0.1 spikes/s means the same count: a flat step of the rate curve)
    assert np.all(np.abs(fit.coeffs[1] - 2.0) < 0.2)
    assert np.all(np.abs(fit.coeffs[2] - 0.5) < 0.05)


def test_unreachable_target_hits_the_cap_and_is_reported():
    n = 1000
    ref = np.full((n, 3), 0.9)
    weak = np.full((n, 3), 0.05)
    weak[:, 0] = 0.45  # taxel 0 reachable (C = 2); taxels 1, 2 need C = 18 > 5
    fit = fit_force_coefficients(np.stack([ref, weak]), [0, 1], reference=[0, 0], c_max=5.0)
    assert fit.converged[1, 0]
    assert not fit.converged[1, 1] and not fit.converged[1, 2]
    assert fit.n_not_converged == 2
    assert np.all(fit.coeffs <= 5.0)
    assert np.all(fit.coeffs[1, 1:] > 4.99)


def test_each_step_is_one_kernel_call_for_all_coefficients():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.1, 0.9, size=(12, 600, 5))
    group = np.repeat(np.arange(6), 2)
    fit = fit_force_coefficients(x, group, reference=[0, 0, 0, 3, 3, 3], max_iter=40)
    # 20 open coefficients solved together: far fewer steps than solving them one by one
    assert fit.n_iter <= 40
    assert fit.coeffs.shape == (6, 5)
    assert fit.converged[[0, 3]].all()


def test_force_scaler_per_texture_and_label_free():
    from rigctl.encoding.estimators import ForceScaler

    n = 800
    tex, spd, frc, data = [], [], [], []
    for t, gain in (("A", 1.0), ("B", 0.5)):
        for f, fg in ((250, 0.5), (500, 1.0), (1000, 1.6)):
            for _ in range(2):
                tex.append(t)
                spd.append(80)
                frc.append(f)
                data.append(np.full((n, 2), 0.4 * gain * fg))
    x = np.stack(data)
    per_tex = ForceScaler().fit_labels(x, tex, spd, frc)
    assert per_tex.coeffs_.shape == (6, 2)
    c = per_tex.coefficients_for(["A", "B", "A"], [80, 80, 80], [250, 250, 500])
    assert np.all(np.abs(c[0] - 2.0) < 0.2) and np.all(np.abs(c[1] - 2.0) < 0.2)
    np.testing.assert_allclose(c[2], 1.0)
    lf = ForceScaler(label_free=True).fit_labels(x, tex, spd, frc)
    assert lf.coeffs_.shape == (3, 2)  # (taxel, speed, force) only
    c_lf = lf.coefficients_for(["Z"], [80], [1000])
    assert np.all(c_lf < 1.0)
    table = per_tex.table()
    assert table.size == 12 and set(table["texture"]) == {"A", "B"}


def test_unknown_speed_is_one_condition_and_labels_are_kept_whole():
    """A NaN speed (imported recordings) groups with the other NaN-speed trials of its texture and force and finds
    its 500 g reference among them; long labels survive into the coefficient table."""
    from rigctl.encoding.estimators import ForceScaler

    n = 800
    tex, spd, frc, data = [], [], [], []
    for speed in (np.nan, 50.0):
        for f, fg in ((250, 0.5), (500, 1.0)):
            for _ in range(2):
                tex.append("Herringbone-3")
                spd.append(speed)
                frc.append(f)
                data.append(np.full((n, 2), 0.4 * fg * (1.0 if np.isnan(speed) else 0.8)))
    sc = ForceScaler().fit_labels(np.stack(data), tex, spd, frc)
    assert sc.coeffs_.shape == (4, 2)  # (NaN, 250), (NaN, 500), (50, 250), (50, 500)
    c = sc.coefficients_for(["Herringbone-3", "Herringbone-3"], [np.nan, np.nan], [250, 500])
    assert np.all(np.abs(c[0] - 2.0) < 0.2)
    np.testing.assert_allclose(c[1], 1.0)
    table = sc.table()
    assert set(table["texture"]) == {"Herringbone-3"}
    assert np.isnan(table["speed_mm_s"]).sum() == 4 and (table["speed_mm_s"] == 50).sum() == 4


def test_missing_reference_force_is_an_error():
    from rigctl.encoding.estimators import ForceScaler

    x = np.full((2, 100, 2), 0.3)
    with pytest.raises(ValueError, match="reference force"):
        ForceScaler().fit_labels(x, ["A", "A"], [80, 80], [250, 1000])
