"""Issue 78 item 2: where on the plate a session's scans sit. The place-free window statistics, the session's shift
measured from a labelled calibration block, and the classifier's warning past the tolerance (synthetic features: 9
trains x 20 windows, each texture a fixed pattern along the plate sampled at a shift)."""

import numpy as np
import pytest

from rigctl.analysis.realtime_model import RealtimeClassifier
from rigctl.encoding.alignment import session_shift, shift_windows, window_statistics
from rigctl.simulation.operator import OperatorConfig, SimulatedOperator

N_TRAINS, N_WIN = 9, 20


def _block(rng, shift_mm, n_per=10, textures="ABDLN"):
    """Scans whose rates follow each texture's own pattern along the plate (1 mm grid), cut ``shift_mm`` early."""
    x_mm = np.arange(-30, 260)
    pats = {c: 50 + 30 * np.sin(x_mm[None, :] / (3 + i) + np.arange(N_TRAINS)[:, None]) for i, c in enumerate(textures)}
    rows, labels = [], []
    for c in textures:
        for _ in range(n_per):
            start = 30 - int(shift_mm)  # index of the cut on the grid
            w = pats[c][:, start:start + 10 * N_WIN].reshape(N_TRAINS, N_WIN, 10).mean(axis=2)
            rows.append((w + rng.normal(0, 2, w.shape)).ravel())
            labels.append(c)
    return np.array(rows), np.array(labels)


def test_shift_windows_moves_and_holds_the_ends():
    x = np.tile(np.arange(N_WIN, dtype=float), N_TRAINS)
    y = shift_windows(x, N_TRAINS, 1.5).reshape(N_TRAINS, N_WIN)
    assert y[0, 0] == 1.5 and y[0, -1] == N_WIN - 1  # window 0 takes what 1.5 held; the last held
    assert np.array_equal(shift_windows(x, N_TRAINS, 0.0), x)
    with pytest.raises(ValueError):
        shift_windows(np.zeros(7), N_TRAINS, 1.0)


def test_session_shift_finds_the_offset_from_the_labelled_block():
    rng = np.random.default_rng(0)
    tr, y = _block(rng, 0)
    templates = {c: tr[y == c].mean(axis=0) for c in np.unique(y)}
    for mm in (0, 3, 6, -5):
        cal, yc = _block(rng, mm)
        assert abs(10 * session_shift(templates, cal, yc, N_TRAINS) - mm) <= 1.0, mm


def test_window_statistics_do_not_depend_on_the_place_and_the_classifier_warns():
    rng = np.random.default_rng(1)
    tr, y = _block(rng, 0)
    cal, yc = _block(rng, 8)
    rt, yr = _block(rng, 8)
    s = window_statistics(tr, N_TRAINS)
    assert s.shape == (tr.shape[0], 3 * N_TRAINS)
    assert np.allclose(window_statistics(tr[0], N_TRAINS), s[0])
    for alignment in ("none", "statistics"):
        clf = RealtimeClassifier(tr, y, n_pcs=10, alignment=alignment)
        clf.calibrate(cal, yc)
        assert clf.shift_mm == pytest.approx(8, abs=1.0)
        assert "+8" in clf.alignment_note or "+7" in clf.alignment_note or "+9" in clf.alignment_note
    good = RealtimeClassifier(tr, y, n_pcs=10, alignment="statistics")
    good.calibrate(cal, yc)
    assert np.mean(good.predict(rt) == yr) >= 0.9
    exact = RealtimeClassifier(tr, y, n_pcs=10)
    exact.calibrate(_block(rng, 0)[0], _block(rng, 0)[1])
    assert exact.alignment_note == "" and abs(exact.shift_mm) <= 1.0
    with pytest.raises(ValueError, match="textures"):
        RealtimeClassifier(tr, y, alignment="session").calibrate(cal)
    with pytest.raises(ValueError, match="alignment"):
        RealtimeClassifier(tr, y, alignment="bogus")


def test_a_session_carries_its_errors_by_default_and_none_when_exact():
    a, b = SimulatedOperator(seed=7), SimulatedOperator(seed=0, session_seed=7)
    assert a.session_errors()["plate_offset_mm"] == b.session_errors()["plate_offset_mm"] != 0.0
    assert SimulatedOperator(seed=1).session_errors()["plate_offset_mm"] != a.session_errors()["plate_offset_mm"]
    exact = SimulatedOperator(OperatorConfig(touch_error_mm=0, strap_offset_mm=0, strap_rotation_deg=0,
                                             session_speed_error=0), seed=7)
    assert exact.session_offset_mm == pytest.approx(0.0, abs=1e-9)
    assert exact.tracker_rate_hz == a.tracker_rate_hz  # the session's draws leave the others as they were


def test_analyze_realtime_classifies_the_window_statistics_of_a_shifted_session():
    """The offline path (rigctl analyze --task realtime --realtime-features statistics): the same transform as the
    live classifier's, on the new session too; the paper's windows stay the default."""
    from rigctl.analysis.data import FeatureSet
    from rigctl.analysis.tasks import run_realtime

    rng = np.random.default_rng(2)

    def fs_of(shift_mm):
        x, y = _block(rng, shift_mm, n_per=16)
        n = y.size
        prof = np.array(["slow", "medium", "fast", "slow-to-fast"] * (n // 4))
        return FeatureSet(features={"realtime_speed_scaled": x.astype(np.float32)}, texture=y,
                          speed_mm_s=np.full(n, 80.0), force_g=np.full(n, 500.0), profile=prof)

    fs, other = fs_of(0), fs_of(8)
    got = {}
    for feats in ("windows", "statistics"):
        res = run_realtime(fs, new_session=other, n_pcs=10, repeats=2, seed=1, features=feats)
        got[feats] = res.curves["rt_new_session"]["realtime_speed_scaled"].at(10)[0]
    assert got["statistics"] >= 0.9 and got["statistics"] > got["windows"]
    with pytest.raises(ValueError, match="real-time features"):
        run_realtime(fs, n_pcs=5, repeats=1, features="bogus")
