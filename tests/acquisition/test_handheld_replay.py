"""``--replay`` of a recorded handheld session (issue 37): the recorded scans (taxels, tracker samples, boundaries) go
through the same live path (cut by position, encoded live, classified) and give the live run's predictions exactly;
the replay says so by comparing them with the predictions the recording logged."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.encoding.pipeline import encode_session
from rigctl.rigs import open_rig
from rigctl.storage.session import SessionWriter, open_session

from ..conftest import small_handheld_protocol

SMALL = small_handheld_protocol("B", "L")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A calibration block of plates B and L (10 scans) on the simulated operator, encoded: the classifier's
    training block."""
    tmp = tmp_path_factory.mktemp("hh_replay")
    proto = load_protocol(find_protocol("handheld_calibration"))
    proto = type(proto)(**{**proto.__dict__, "textures": ("B", "L"), "trials_per_condition": 1})
    with open_rig("handheld", seed=4, host_config_path=tmp / "rig.json") as rig:
        assert run_protocol(proto, tmp / "cal.h5", rig=rig).ok
    enc = encode_session(tmp / "cal.h5", tmp / "cal.enc.h5", variants=["realtime_original", "realtime_speed_scaled"])
    (tmp / "small.toml").write_text(SMALL)
    return tmp, enc


def _acquire(tmp, enc, out, *extra):
    from rigctl.cli import main

    res = CliRunner().invoke(main, ["acquire", str(tmp / "small.toml"), "--out", str(tmp / out), "--quiet",
                                    "--classify", str(enc), "--pcs", "5", *extra])
    assert res.exit_code == 0, res.output
    return res.output


def test_replay_of_a_handheld_session_reproduces_its_predictions(trained, monkeypatch):
    tmp, enc = trained
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp / "rig.json"))
    live = _acquire(tmp, enc, "rt.h5", "--seed", "5")
    scans = [line for line in live.splitlines() if line.startswith("scan ")]
    assert len(scans) == 4
    replayed = _acquire(tmp, enc, "rt2.h5", "--replay", str(tmp / "rt.h5"))
    assert [line for line in replayed.splitlines() if line.startswith("scan ")] == scans
    assert "replay: 4/4 predictions equal those of the recorded run" in replayed
    with open_session(tmp / "rt.h5") as a, open_session(tmp / "rt2.h5") as b:
        assert b.rig_config["mode"] == "handheld-replay"
        assert [e["predicted"] for e in a.events if e["kind"] == "prediction"] == \
            [line.split("predicted ")[1].split()[0] for line in scans]
        for tid in a.completed_ids():
            x, y = a.trial(tid), b.trial(tid)
            assert y.attrs["replayed_trial"] == tid
            assert np.array_equal(x.taxels, y.taxels) and np.array_equal(x.seq, y.seq)  # the same frames kept
            # the window speeds again from the recorded positions (equal to float rounding: the times re-based)
            assert np.array_equal(x.speed_time_s, y.speed_time_s)
            assert np.allclose(x.speed_mm_s, y.speed_mm_s, rtol=0, atol=1e-6)
            assert y.attrs["scan_enter_s"] == pytest.approx(x.attrs["scan_enter_s"], abs=1e-9)
            assert y.attrs["scan_leave_s"] == pytest.approx(x.attrs["scan_leave_s"], abs=1e-9)
    # a recording whose logged prediction differs: the comparison names the scan
    from rigctl.operations import Prediction, ScanClassifier

    clf = ScanClassifier(enc, n_pcs=5)
    with open_session(tmp / "rt2.h5") as b:
        clf.predictions = [Prediction(int(e["trial_id"]), e["truth"], e["profile"], e["predicted"], int(e["trial_id"]))
                           for e in b.events if e["kind"] == "prediction"]
    assert clf.compare_recorded(tmp / "rt.h5") == (4, [])
    w = SessionWriter.open(tmp / "rt.h5")
    first = clf.predictions[0].predicted
    w.log_event("prediction", trial_id=0, predicted="B" if first != "B" else "L")
    w.close()
    n, diffs = clf.compare_recorded(tmp / "rt.h5")
    assert n == 4 and len(diffs) == 1 and diffs[0].startswith("scan 0 (recorded trial 0)")


def test_replay_refuses_a_drum_session_and_a_motion(trained, tmp_path):
    from rigctl.cli import main

    tmp, enc = trained
    res = CliRunner().invoke(main, ["acquire", str(tmp / "small.toml"), "--out", str(tmp_path / "x.h5"), "--replay",
                                    str(tmp / "cal.h5"), "--motion", "sim"])
    assert res.exit_code == 2 and "drop --motion" in res.output
    with open_rig("inprocess", seed=1) as rig:
        quick = load_protocol(find_protocol("quick_check"))
        assert run_protocol(type(quick)(**{**quick.__dict__, "trials_per_condition": 1}), tmp_path / "d.h5",
                            rig=rig).complete >= 1
    from rigctl.acquisition.rig import RigError

    with pytest.raises(RigError, match="no handheld scan"):
        open_rig("handheld", motion=f"replay:{tmp_path / 'd.h5'}")


def test_the_live_block_names_its_features_and_warns_of_a_shifted_session(trained, monkeypatch):
    """Issue 78 item 2: the summary names the features (window statistics by default), each prediction event records
    the session's shift; a calibration block outside the training's alignment ends the block with a WARNING line."""
    from types import SimpleNamespace

    from rigctl.cli.acquire import _prediction_lines
    from rigctl.operations import Prediction

    tmp, enc = trained
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp / "rig.json"))
    out = _acquire(tmp, enc, "rt_cal.h5", "--seed", "6", "--calibration", str(enc))
    assert "features: statistics)" in out and "WARNING" not in out  # calibrated on the training block itself
    with open_session(tmp / "rt_cal.h5") as s:
        ev = [e for e in s.events if e["kind"] == "prediction"]
    assert len(ev) == 4 and all(e["alignment"] == "statistics" and e["session_shift_mm"] == 0.0
                                and e["outside_alignment"] is False for e in ev)
    note = "the calibration block sits +6.0 mm along the plate from the training block (tolerance 2 mm: ...)"
    fake = SimpleNamespace(predictions=[Prediction(0, "B", "slow", "B")], variant="realtime_speed_scaled",
                           accuracy=lambda: 1.0, log_to=lambda out: 1,
                           model=SimpleNamespace(n_pcs=5, alignment="none", alignment_note=note))
    lines = _prediction_lines(fake, tmp / "x.h5", None)
    assert lines[-1] == f"  WARNING: {note}" and "features: none" in lines[0]
    fake.model.alignment_note = ""
    assert not any("WARNING" in line for line in _prediction_lines(fake, tmp / "x.h5", None))


def test_a_tampered_scan_is_never_replayed(trained, tmp_path):
    """The replay source reads the session's scans through the one trial validator (issue 77 item 7: it took every
    complete trial): a scan whose taxels were edited after the seal (plain h5py) is warned of and left out; the others
    are replayed."""
    import shutil

    import h5py

    from rigctl.simulation.handheld_replay import SessionScans
    from rigctl.storage.validate import TrialsExcluded

    tmp, _ = trained
    path = tmp_path / "cal.h5"
    shutil.copy(tmp / "cal.h5", path)
    whole = SessionScans(tmp / "cal.h5")
    ids = [tid for tid, _, _ in whole._scans]
    whole.close()
    assert len(ids) >= 2
    with h5py.File(path, "r+") as f:  # the second scan: one reading changed by one count
        idx = f["recording/index"][()]
        t = int(idx[idx["trial_id"] == ids[1]][0]["sample_start"]) + 5
        f["recording/taxels"][t, 0] = int(f["recording/taxels"][t, 0]) + 1
    with pytest.warns(TrialsExcluded, match="1 excluded"):
        scans = SessionScans(path)
    assert [tid for tid, _, _ in scans._scans] == [tid for tid in ids if tid != ids[1]]
    scans.close()
