"""One normalisation, as the paper (issue 56 item 3): the training block's per-taxel range serves the calibration
and real-time blocks (``rigctl encode --range-from TRAINING.enc.h5``), so a scan's offline features are its live
features (the live classifier encodes every scan with the training block's range)."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.rigs import open_rig
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import open_session

from ..conftest import small_handheld_protocol

VARIANTS = ["--variant", "realtime_original", "--variant", "realtime_speed_scaled"]


def test_a_block_encoded_with_the_training_range_gives_the_live_features(tmp_path):
    from rigctl.cli import main
    from rigctl.operations import ScanClassifier

    proto = parse_protocol(small_handheld_protocol("B", "L"))
    for name, seed in (("train", 4), ("live", 9)):
        with open_rig("handheld", seed=seed, host_config_path=tmp_path / "rig.json") as rig:
            assert run_protocol(proto, tmp_path / f"{name}.h5", rig=rig).ok
    runner = CliRunner()
    res = runner.invoke(main, ["encode", str(tmp_path / "train.h5"), "--out", str(tmp_path / "train.enc.h5"), *VARIANTS])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["encode", str(tmp_path / "live.h5"), "--out", str(tmp_path / "live.enc.h5"),
                               "--range-from", str(tmp_path / "train.enc.h5"), *VARIANTS])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["encode", str(tmp_path / "live.h5"), "--out", str(tmp_path / "own.enc.h5"), *VARIANTS])
    assert res.exit_code == 0, res.output
    with open_encoded(tmp_path / "train.enc.h5") as t, open_encoded(tmp_path / "live.enc.h5") as e, \
            open_encoded(tmp_path / "own.enc.h5") as o:
        for k in ("taxel_min", "taxel_max"):
            assert np.array_equal(e.normalisation[k], t.normalisation[k])
        assert not np.array_equal(o.normalisation["taxel_max"], t.normalisation["taxel_max"])
        assert e.attrs["range_from"] == str(tmp_path / "train.enc.h5")
        offline = {v: e.features(v) for v in ("realtime_original", "realtime_speed_scaled")}
        own = o.features("realtime_speed_scaled")
        ids = [int(i) for i in e.trials["trial_id"]]
    diffs = {}
    with open_session(tmp_path / "live.h5") as s:
        for variant, x in offline.items():
            clf = ScanClassifier(tmp_path / "train.enc.h5", variant=variant, n_pcs=2)
            live = np.array([clf.features(s.trial(tid)) for tid in ids])
            diffs[variant] = float(np.max(np.abs(live - x)))
            if variant == "realtime_speed_scaled":
                assert np.max(np.abs(live - own)) > 1.0  # the block's own range: other features
    print("max abs difference, offline vs live (spikes/s):", diffs)
    # equal to float32 rounding of the spike rates (max abs difference, spikes/s)
    assert max(diffs.values()) <= 1e-3, diffs
    # a calibration block normalised with its own range is named (the live scans use the training block's)
    clf = ScanClassifier(tmp_path / "train.enc.h5", calibration=tmp_path / "own.enc.h5", n_pcs=2)
    assert "--range-from" in clf.calibration_note
    assert ScanClassifier(tmp_path / "train.enc.h5", calibration=tmp_path / "live.enc.h5", n_pcs=2).calibration_note == ""
    res = runner.invoke(main, ["encode", str(tmp_path / "live.h5"), "--out", str(tmp_path / "x.enc.h5"),
                               "--range-from", str(tmp_path / "live.h5")])
    assert res.exit_code != 0 and "Traceback" not in res.output
