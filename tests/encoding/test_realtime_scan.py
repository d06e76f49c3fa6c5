"""The live encoding of a scan (rigctl.encoding.realtime.ScanEncoder) equals the offline encoding of the recorded
session (``rigctl encode``'s realtime_original / realtime_speed_scaled), chunk by chunk with the velocity arriving
late; and its incremental scaling is the paper's (eq. 2 per 100 ms window)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core.normalisation import TaxelRange
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.pipeline import encode_session
from rigctl.encoding.realtime import ScanEncoder
from rigctl.rigs import open_rig
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import open_session

VARIANTS = ["realtime_original", "realtime_speed_scaled"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("handheld")
    proto = load_protocol(find_protocol("handheld_calibration"))
    proto = type(proto)(**{**proto.__dict__, "textures": ("B", "L"), "trials_per_condition": 1})
    out = tmp / "cal.h5"
    with open_rig("handheld", seed=4, host_config_path=tmp / "rig.json") as rig:
        assert run_protocol(proto, out, rig=rig).ok
    enc = encode_session(out, tmp / "cal.enc.h5", variants=VARIANTS)
    return out, enc


def _live(session, enc, tid, chunk=37, lag_s=0.15):
    """Feed trial ``tid`` as a live scan: readings in chunks, each velocity sample ``lag_s`` after its time."""
    with open_encoded(enc) as f:
        norm = f.normalisation
        params = EncodeParams.from_dict(f.parameters)
    se = ScanEncoder(TaxelRange(norm["taxel_min"], norm["taxel_max"]), params)
    d = session.trial(tid)
    t, v = d.speed_time_s, d.speed_mm_s
    sent = 0
    scaled_while_scanning = 0
    for a in range(0, d.n_samples, chunk):
        se.feed(d.taxels[a:a + chunk])
        now = (a + chunk) / d.rate_hz
        n = int(np.searchsorted(t, now - lag_s, side="right"))
        if n > sent:
            se.feed_speed(t[sent:n], v[sent:n])
            sent = n
        scaled_while_scanning = se.windows_scaled
    se.feed_speed(t[sent:], v[sent:])
    return se.features(), scaled_while_scanning


def test_live_scan_features_equal_the_offline_encoding(recorded):
    path, enc = recorded
    with open_encoded(enc) as f:
        offline = {v: f.features(v) for v in VARIANTS}
        ids = list(f.trials["trial_id"])
    assert offline["realtime_speed_scaled"].shape == (len(ids), 180)
    with open_session(path) as s:
        for row, tid in enumerate(ids):
            live, during = _live(s, enc, int(tid))
            assert during >= 10  # the windows were scaled while the scan went on, not at its end
            for v in VARIANTS:
                np.testing.assert_allclose(live[v], offline[v][row], rtol=1e-6, atol=1e-6, err_msg=f"{v} trial {tid}")


def test_speed_scaled_features_cover_the_plates_middle_in_20_windows(recorded):
    """200 mm at the 100 mm/s reference is 2 s of scaled time: every scan fills about the 20 windows, whatever its
    speed; the original features of a slow scan are its last 2 s of about 5 (no padding)."""
    _, enc = recorded
    with open_encoded(enc) as f:
        ss = f.features("realtime_speed_scaled").reshape(-1, 9, 20)
        orig = f.features("realtime_original").reshape(-1, 9, 20)
        prof = f.trials["profile"]
    active = (ss.sum(axis=1) > 0).sum(axis=1)
    assert np.all(active >= 18)
    slow = np.asarray([str(p) == "slow" for p in prof])
    assert slow.any() and np.all((orig[slow].sum(axis=1) > 0).sum(axis=1) == 20)


def test_scan_classifier_predicts_each_scan_and_says_so(recorded):
    from rigctl.operations import ScanClassifier

    path, enc = recorded
    lines = []
    clf = ScanClassifier(enc, calibration=enc, n_pcs=5, on_prediction=lambda p: lines.append(p.line()))
    with open_session(path) as s:
        for tid in s.completed_ids():
            row = s.plan[tid]
            clf.classify(tid, str(row["texture"]), str(row["profile"]), s.trial(tid))
    assert len(lines) == 10 and lines[0].startswith("scan 0 (plate B, slow): predicted ")
    assert clf.accuracy() >= 0.8  # its own training scans, two plates
    with pytest.raises(ValueError, match="no force_scaled"):
        ScanClassifier(enc, variant="force_scaled")
