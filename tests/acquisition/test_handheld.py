"""The handheld rig (issue 37): the simulated operator, the plate axis, trials cut by position, the run engine on it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.handheld import HandheldRig, NoDrumError, cut_scan, velocity_from_position
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core.handheld import USED_END_MM, USED_START_MM, PlateAxis, RawScan, ScanError
from rigctl.core.sensor import PAPER_FINGER
from rigctl.core.trial import PlannedTrial
from rigctl.rigs import open_rig
from rigctl.simulation.operator import OperatorConfig, SimulatedOperator
from rigctl.storage.session import open_session

from ..conftest import small_handheld_protocol

SMALL = small_handheld_protocol("A", "L")


def _planned(profile="fast", speed=120.0, ramp=(math.nan, math.nan), texture="L"):
    return PlannedTrial(0, texture, speed, 500.0, 200.0 / speed, profile, *ramp)


def _linear_scan(speed_mm_s=100.0, rate_hz=1000.0, tracker_hz=100.0):
    """A finger at constant speed from 0 to 300 mm on a plate along the tracker's x axis, frames stamped exactly."""
    span = 300.0 / speed_mm_s
    n = int(span * rate_hz)
    t_frames = 10.0 + np.arange(n) / rate_hz
    taxels = (np.arange(n)[:, None] % 1000 + np.zeros((1, 9))).astype(np.uint16)
    t_trk = 10.0 + np.arange(int(span * tracker_hz)) / tracker_hz
    xyz = np.column_stack([speed_mm_s * (t_trk - 10.0), np.zeros(t_trk.size), np.zeros(t_trk.size)])
    return RawScan(taxels=taxels, seq=(np.arange(n) % 65536).astype(np.uint16), host_time_s=t_frames,
                   tracker_time_s=t_trk, tracker_xyz=xyz)


def test_cut_by_position_exact_boundaries_and_velocity():
    raw = _linear_scan(speed_mm_s=100.0)
    data = cut_scan(raw, PAPER_FINGER, PlateAxis())
    # enters at 50 mm = 0.5 s, leaves at 250 mm = 2.5 s: 2000 frames at 1 kHz
    assert data.attrs["scan_enter_s"] == pytest.approx(10.5, abs=1e-9)
    assert data.attrs["scan_leave_s"] == pytest.approx(12.5, abs=1e-9)
    assert abs(data.n_samples - 2000) <= 1
    assert data.attrs["boundary"] == "position"
    inner = (data.speed_time_s > 0.1) & (data.speed_time_s < 1.9)
    assert np.allclose(data.speed_mm_s[inner], 100.0, atol=1e-6)
    assert data.position_mm[0] < USED_START_MM < USED_END_MM < data.position_mm[-1]
    assert data.attrs["tracker_rate_hz"] == pytest.approx(100.0)
    assert data.attrs["scan_mean_speed_mm_s"] == pytest.approx(100.0)


def test_late_frames_never_shift_the_trials_time_axis():
    """A busy host receives the scan's first 0.8 s of frames in one burst at 0.8 s: the frames kept are still those
    between the boundaries on the board's clock, and the traces' time 0 is the first kept frame's time on that clock
    (its 50 mm crossing), not its late receipt (0.3 s later)."""
    raw = _linear_scan(speed_mm_s=100.0)
    late = raw.host_time_s < 10.8
    raw.host_time_s[late] = 10.8  # received all at once
    data = cut_scan(raw, PAPER_FINGER, PlateAxis())
    assert abs(data.n_samples - 2000) <= 1
    assert data.attrs["trial_time_origin_s"] == pytest.approx(10.5, abs=0.0011)
    assert np.interp(0.0, data.position_time_s, data.position_mm) == pytest.approx(USED_START_MM, abs=0.11)
    assert data.host_time_s[0] == pytest.approx(0.3, abs=0.0011)  # the receipt, on the same axis
    assert np.interp(data.duration_s, data.position_time_s, data.position_mm) == pytest.approx(USED_END_MM, abs=0.2)


def test_stop_between_scans_pauses_the_block_and_resume_records_every_scan(tmp_path):
    """STOP (RigControl.stop) right after a scan: the block pauses before the next cue, the operator is told to lift
    the finger (a stop cue); Resume records the rest, none discarded or recorded twice."""
    import threading

    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.operations import ProtocolRun, RigSource, open_control

    events, cues = [], []
    with open_control(RigSource("handheld"), seed=4, host_config_path=tmp_path / "rig.json") as control:
        assert not control.has_drum
        control.subscribe(lambda ev: cues.append(ev.fields["cue"]) if ev.kind == "prompt" else None)
        run = ProtocolRun(control, parse_protocol(SMALL), tmp_path / "s.h5")

        def on_trial(ev):
            events.append(ev.kind)
            if ev.kind == "complete" and events.count("complete") == 1:
                control.stop("test STOP")  # in the run's thread, between the first and the second scan
            elif ev.kind == "paused":
                threading.Timer(0.2, run.resume).start()

        run.on_trial = on_trial
        summary = run.run()
    assert summary.ok and summary.complete == 4
    assert events.count("paused") == 1 and events.count("halted") == 0 and events.count("resumed") == 1
    assert events.index("paused") == events.index("complete") + 1
    assert cues.count("stop") == 1 and cues.count("go") == 4  # no scan cued twice
    assert cues.index("stop") == cues.index("go") + 1


def test_cut_refuses_a_scan_that_never_leaves():
    raw = _linear_scan()
    short = raw.tracker_xyz[:, 0] < 200.0
    raw.tracker_time_s, raw.tracker_xyz = raw.tracker_time_s[short], raw.tracker_xyz[short]
    with pytest.raises(ScanError, match="never left"):
        cut_scan(raw, PAPER_FINGER, PlateAxis())
    with pytest.raises(ScanError, match="no position"):
        cut_scan(raw, PAPER_FINGER, None)


def test_plate_axis_from_touches_in_a_rotated_frame():
    exact = SimulatedOperator(OperatorConfig(touch_error_mm=0.0), seed=3)
    axis = PlateAxis.from_touches(*exact.touch_ends())
    pts = exact.to_tracker(np.array([0.0, 50.0, 250.0]), np.array([0.0, 3.0, -3.0]))  # sideways wobble ignored
    assert np.allclose(axis.along_mm(pts), [0.0, 50.0, 250.0], atol=0.5)
    # a session's touches off by e0 at the start and e1 at the end (1.5 mm sd each, by default): the axis reads
    # (x - e0) * 300 / (300 + e1 - e0), which the test states
    op = SimulatedOperator(seed=3)
    e0, e1 = op.touch_error_mm
    assert 0.1 < max(abs(e0), abs(e1)) < 6.0
    axis = PlateAxis.from_touches(*op.touch_ends())
    want = (np.array([0.0, 50.0, 250.0]) - e0) * 300.0 / (300.0 + e1 - e0)
    assert np.allclose(axis.along_mm(pts), want, atol=0.5)
    assert not np.allclose(axis.along_mm(pts), [0.0, 50.0, 250.0], atol=0.5) or max(abs(e0), abs(e1)) < 0.5
    with pytest.raises(ValueError, match="apart"):
        PlateAxis((0.0, 0.0, 0.0), (0.3, 0.0, 0.0))  # metres, not mm


def test_velocity_from_position_is_the_100ms_mean():
    t = np.arange(0, 2, 0.01)
    x = 20.0 * t**2  # v = 40 t
    v = velocity_from_position(t, x, np.array([1.0]))
    assert v[0] == pytest.approx(40.0, rel=1e-3)


def test_simulated_operator_tracker_and_variability():
    op = SimulatedOperator(seed=5)
    assert 90.0 <= op.tracker_rate_hz <= 120.0
    scans = [op.scan(_planned()) for _ in range(3)]
    for s in scans:
        assert s.taxels.shape[1] == 9 and s.taxels.dtype == np.uint16
        gaps = np.diff(s.tracker_time_s)
        assert np.median(gaps) == pytest.approx(1.0 / op.tracker_rate_hz, rel=0.05)
    # human variability: the same intent gives passes of different lengths; the same seed the same passes
    assert len({s.taxels.shape[0] for s in scans}) >= 2
    assert len({s.attrs["operator_speed_bias"] for s in scans}) == 3
    again = SimulatedOperator(seed=5).scan(_planned())
    assert np.array_equal(again.taxels, scans[0].taxels)
    assert op.scan(_planned(), stop=lambda: True) is None


def test_ramp_profile_speeds_up_along_the_plate():
    op = SimulatedOperator(seed=8)
    axis = PlateAxis.from_touches(*op.touch_ends())
    data = cut_scan(op.scan(_planned("slow-to-fast", 80.0, (40.0, 120.0))), PAPER_FINGER, axis)
    t, v = data.speed_time_s, data.speed_mm_s
    first = v[(t > 0.1) & (t < 0.4)].mean()
    last = v[(t > data.duration_s - 0.4) & (t < data.duration_s - 0.1)].mean()
    assert last > 1.8 * first


def test_handheld_protocol_records_position_cut_trials(tmp_path):
    proto_path = tmp_path / "small.toml"
    proto_path.write_text(SMALL)
    proto = load_protocol(proto_path)
    assert proto.rig == "handheld"
    out = tmp_path / "hh.h5"
    with open_rig("handheld", seed=2, host_config_path=tmp_path / "rig.json") as rig:
        assert isinstance(rig, HandheldRig) and rig.layout == PAPER_FINGER
        with pytest.raises(NoDrumError):
            rig.drum.read_status()
        summary = run_protocol(proto, out, rig=rig)
    assert summary.ok and summary.complete == 4
    with open_session(out) as s:
        assert s.rig_config["mode"] == "handheld" and s.layout.n_channels == 9
        for tid in s.completed_ids():
            d = s.trial(tid)
            # the speed trace: each 100 ms window's position change (the paper's window speed), two samples a window
            n_win = int(np.ceil(round(d.duration_s / 0.1, 9)))
            assert d.speed_mm_s.size == d.speed_time_s.size == 2 * n_win and d.position_mm.size > n_win
            assert np.all(d.speed_mm_s >= 0.0)
            w = np.arange(n_win) * 0.1
            want = np.maximum(np.diff(np.interp(np.append(w, n_win * 0.1), d.position_time_s, d.position_mm)) / 0.1, 0)
            assert np.allclose(d.speed_mm_s[::2], want, atol=1e-6)
            assert d.attrs["boundary"] == "position"
            t_in = np.interp(0.0, d.position_time_s, d.position_mm)
            t_out = np.interp(d.duration_s, d.position_time_s, d.position_mm)
            assert t_in == pytest.approx(USED_START_MM, abs=3.0) and t_out == pytest.approx(USED_END_MM, abs=3.0)


def test_cli_refuses_mixed_rigs(tmp_path):
    from rigctl.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["acquire", "quick_check", "--handheld", "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and "drum protocol" in res.output
    res = runner.invoke(main, ["acquire", "handheld_training", "--inprocess", "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and "handheld rig" in res.output
    res = runner.invoke(main, ["acquire", "handheld_training", "--motion", "udp:1", "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2


def test_protocol_rig_key_is_checked_with_its_line():
    from rigctl.acquisition.protocol import ProtocolError, parse_protocol

    base = 'name = "t"\ntextures = ["A"]\nspeeds_mm_s = [40]\nforces_g = [250]\n'
    assert parse_protocol(base).rig == "drum"
    with pytest.raises(ProtocolError, match=r":5: rig: 'boat' is not one of drum, handheld"):
        parse_protocol(base + 'rig = "boat"\n')
    shipped = {n: load_protocol(find_protocol(n)).plan() for n in ("handheld_training", "handheld_calibration", "handheld_realtime")}
    per_texture = {n: sum(p.texture == "A" for p in plan) for n, plan in shipped.items()}
    assert per_texture == {"handheld_training": 20, "handheld_calibration": 10, "handheld_realtime": 20}


def test_plate_axis_from_the_rig_config(tmp_path):
    import json

    cfg = tmp_path / "rig.json"
    cfg.write_text(json.dumps({"handheld": {"start_xyz": [10, 20, 0], "end_xyz": [10, 320, 0]}}))
    rig = HandheldRig(SimulatedOperator(seed=1), host_config_path=str(cfg))
    assert rig.axis is not None and rig.axis.along_mm(np.array([[10.0, 70.0, 5.0]]))[0] == pytest.approx(50.0)
    assert rig.describe()["plate_axis"]["end_xyz"] == [10.0, 320.0, 0.0]
    cfg.write_text(json.dumps({"handheld": {"start_xyz": [10, 20, 0]}}))
    from rigctl.acquisition.rigconfig import RigConfigError

    with pytest.raises(RigConfigError, match="end_xyz"):
        HandheldRig(SimulatedOperator(seed=1), host_config_path=str(cfg))


def test_nwb_export_holds_the_tracker_as_time_series(tmp_path):
    pynwb = pytest.importorskip("pynwb")
    from rigctl.storage.nwb import export_nwb

    proto_path = tmp_path / "small.toml"
    proto_path.write_text(small_handheld_protocol("L"))
    with open_rig("handheld", seed=6, host_config_path=tmp_path / "rig.json") as rig:
        assert run_protocol(load_protocol(proto_path), tmp_path / "hh.h5", rig=rig).ok
    export_nwb(tmp_path / "hh.h5", tmp_path / "hh.nwb")
    with pynwb.NWBHDF5IO(str(tmp_path / "hh.nwb"), "r") as io:
        nwb = io.read()
        assert "drum_speed" not in nwb.acquisition
        pos, vel = nwb.acquisition["tracker_position"], nwb.acquisition["tracker_velocity"]
        # the velocity: each trial's 100 ms window speeds (two samples a window), the position: every tracker sample
        assert pos.unit == "mm" and vel.unit == "mm/s" and len(pos.data[:]) > len(vel.data[:]) > 50
        starts = nwb.trials["start_time"][:]
        stops = nwb.trials["stop_time"][:]
        t, x = pos.timestamps[:], pos.data[:]
        assert np.all((t >= starts[0]) & (t <= stops[-1]))  # only the samples inside the trials
        for a, b in zip(starts, stops):  # each trial spans the finger's pass through the middle 200 mm
            inside = x[(t >= a) & (t <= b)]
            assert inside[0] == pytest.approx(USED_START_MM, abs=3.0)
            assert inside[-1] == pytest.approx(USED_END_MM, abs=3.0)
