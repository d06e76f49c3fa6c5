"""Motion as people make it (issue 56 items 1 and 2): a hand that hesitates and slips back, and the paper's window
speed (the position's change over each 100 ms window) on the host as on the board."""

from __future__ import annotations

import threading
import time
import uuid

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.acquisition.handheld import cut_scan
from rigctl.core.handheld import RawScan
from rigctl.core.sensor import PAPER_FINGER
from rigctl.devices.onboard_finger import window_speed_mm_s

from ..conftest import small_handheld_protocol


def _hand_path(t: np.ndarray, *, speed_mm_s: float = 100.0, pause_at_mm: float = 150.0, pause_s: float = 0.15,
               slip_mm: float = 2.0, slip_s: float = 0.1, start_mm: float = 15.0, stop_mm: float = 285.0) -> np.ndarray:
    """Position along the plate (mm) at ``t`` s of a pass: still 0.3 s at the start, on at ``speed_mm_s``, a
    hesitation of ``pause_s`` at ``pause_at_mm``, a slide back of ``slip_mm`` over ``slip_s``, on to ``stop_mm``."""
    t1 = 0.3 + (pause_at_mm - start_mm) / speed_mm_s
    t2, t3 = t1 + pause_s, t1 + pause_s + slip_s
    back = pause_at_mm - slip_mm
    t4 = t3 + (stop_mm - back) / speed_mm_s
    return np.interp(t, [0.0, 0.3, t1, t2, t3, t4], [start_mm, start_mm, pause_at_mm, pause_at_mm, back, stop_mm])


def _raw_scan(seed: int = 0) -> RawScan:
    rng = np.random.default_rng(seed)
    t = np.sort(np.arange(0, 3.6, 1 / 120) + rng.normal(0, 0.0015, 432))
    along = _hand_path(t) + rng.normal(0, 0.3, t.size)
    frames = np.arange(0, 3.6, 1e-3)
    taxels = rng.integers(100, 900, (frames.size, PAPER_FINGER.n_channels)).astype(np.uint16)
    return RawScan(taxels=taxels, seq=(np.arange(frames.size) % 65536).astype(np.uint16), host_time_s=frames,
                   tracker_time_s=t, along_mm=along)


def test_host_and_board_window_speeds_are_equal_and_a_backward_window_is_floored():
    """The trial's speed of each 100 ms window (the host's, which the encoder scales with) is what the host sends the
    on-board encoder for the same window: the position's change over it, floored at 0 (old main: a centred 100 ms
    velocity, 4.8 % apart on average, and negative in the slip)."""
    raw = _raw_scan()
    d = cut_scan(raw, PAPER_FINGER)
    origin = d.attrs["trial_time_origin_s"]
    t, along = np.asarray(raw.tracker_time_s), np.asarray(raw.along_mm)
    n_win = int(np.ceil(round(d.n_samples / 1000 / 0.1, 9)))
    board = np.array([window_speed_mm_s(t, along, origin + 0.1 * w, origin + 0.1 * (w + 1)) for w in range(n_win)])
    host = d.speed_mm_s[::2]
    assert host.size == n_win and np.array_equal(host, d.speed_mm_s[1::2])
    assert np.max(np.abs(host - board)) == 0.0  # bit for bit
    assert np.min(host) == 0.0 and d.attrs["floored_windows"] >= 1  # the slip's window: 0 mm/s, counted
    from rigctl.encoding.speed import window_speeds

    back = window_speeds(d.speed_time_s, d.speed_mm_s, d.n_samples / 1000)  # the encoder reads the windows back
    assert np.max(np.abs(back - host)) < 1e-9


def test_the_encoders_take_a_backward_window_as_the_board_does():
    """A negative window speed (an old session's trace, a velocity channel) is scaled with 0, never an error."""
    from rigctl.core.normalisation import TaxelRange
    from rigctl.encoding.features import counted_realtime_features
    from rigctl.encoding.realtime import ScanEncoder

    se = ScanEncoder(TaxelRange(np.full(9, 100.0), np.full(9, 900.0)))
    rng = np.random.default_rng(1)
    se.feed(rng.integers(100, 900, (1000, 9)).astype(np.uint16))
    se.feed_speed(np.arange(0, 1.0, 0.01), np.where(np.arange(100) // 10 == 4, -1.5, 80.0))
    f = se.features()["realtime_speed_scaled"]
    assert np.all(np.isfinite(f))
    assert np.array_equal(counted_realtime_features(np.ones((9, 20)), np.array([80.0, -1.0, 80.0])),
                          counted_realtime_features(np.ones((9, 20)), np.array([80.0, 0.0, 80.0])))


class _HandOnLsl:
    """A tracker on LSL (one channel: the position along the plate, mm, 120 Hz) whose hand passes again and again:
    each pass hesitates 150 ms mid-plate and slips back 2 mm (:func:`_hand_path`), returns to the start, rests."""

    def __init__(self, pylsl, name: str, *, mm_per_unit: float = 1.0, unit: str | None = None) -> None:
        info = pylsl.StreamInfo(name, "Position", 1, 120.0, pylsl.cf_float32, f"hand-{name}")
        if unit is not None:
            info.desc().append_child("channels").append_child("channel").append_child_value("unit", unit)
        self.mm_per_unit = mm_per_unit
        self.outlet = pylsl.StreamOutlet(info)
        self.pylsl, self.halt = pylsl, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        pass_s = 0.3 + 135 / 100 + 0.15 + 0.1 + 137 / 100 + 0.3
        t0 = self.pylsl.local_clock()
        k = 0
        while not self.halt.is_set():
            now = self.pylsl.local_clock()
            while t0 + k / 120 <= now:
                phase = (k / 120) % (pass_s + 0.5)
                x = _hand_path(np.array([phase]))[0] if phase < pass_s else 15.0
                self.outlet.push_sample([float(x) / self.mm_per_unit], t0 + k / 120)
                k += 1
            time.sleep(0.005)

    def close(self) -> None:
        self.halt.set()
        self.thread.join(2)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from rigctl.acquisition.builtin import find_protocol
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.encoding.pipeline import encode_session
    from rigctl.rigs import open_rig

    tmp = tmp_path_factory.mktemp("hh_motion")
    proto = load_protocol(find_protocol("handheld_calibration"))
    proto = type(proto)(**{**proto.__dict__, "textures": ("B", "L"), "trials_per_condition": 1})
    with open_rig("handheld", seed=4, host_config_path=tmp / "rig.json") as rig:
        assert run_protocol(proto, tmp / "cal.h5", rig=rig).ok
    enc = encode_session(tmp / "cal.h5", tmp / "cal.enc.h5", variants=["realtime_original", "realtime_speed_scaled"])
    (tmp / "small.toml").write_text(small_handheld_protocol("B", "L"))
    return tmp, enc


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_a_hand_that_hesitates_and_slips_back_completes_the_block_and_encodes(lsl, trained, monkeypatch):
    """`rigctl acquire --handheld --motion lsl:NAME@0 --classify` with a hand that pauses and slides back 2 mm in
    every pass: every scan recorded and classified (old main: exit 1 after the first, 'speeds must be >= 0'), the
    slip's window floored and counted, and `rigctl encode` accepts the session (old main: 'trial 0: speeds must be
    non-empty and >= 0')."""
    from rigctl.cli import main
    from rigctl.storage.session import open_session

    tmp, enc = trained
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp / "rig.json"))
    name = f"hand-{uuid.uuid4().hex[:8]}"
    hand = _HandOnLsl(lsl, name)
    try:
        res = CliRunner().invoke(main, ["acquire", str(tmp / "small.toml"), "--out", str(tmp / "rt.h5"), "--quiet",
                                        "--handheld", "--motion", f"lsl:{name}@0", "--classify", str(enc),
                                        "--pcs", "5", "--plates", "auto"])
    finally:
        hand.close()
    assert res.exit_code == 0, res.output
    assert len([line for line in res.output.splitlines() if line.startswith("scan ")]) == 4
    with open_session(tmp / "rt.h5") as s:
        ids = s.completed_ids()
        assert len(ids) == 4
        for tid in ids:
            d = s.trial(tid)
            assert d.attrs["floored_windows"] >= 1 and np.min(d.speed_mm_s) == 0.0
    res = CliRunner().invoke(main, ["encode", str(tmp / "rt.h5"), "--out", str(tmp / "rt.enc.h5"), "--variant",
                                    "realtime_original", "--variant", "realtime_speed_scaled"])
    assert res.exit_code == 0, res.output


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_a_tracker_in_metres_given_or_declared(lsl, tmp_path):
    """A tracker publishing metres (Motive and Vicon bridges): --motion-units m, or the stream's own channel unit,
    gives the positions in mm (old main: no such option; 0.015-0.285 'mm' never crossed the plate's used part)."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.operations import RigSource
    from rigctl.rigs import open_rig
    from rigctl.storage.session import open_session

    proto = parse_protocol(small_handheld_protocol("L"))
    for case, unit, given in (("given", None, "m"), ("declared", "meters", None)):
        name = f"hand-m-{uuid.uuid4().hex[:8]}"
        hand = _HandOnLsl(lsl, name, mm_per_unit=1000.0, unit=unit)
        try:
            opts = {} if given is None else {"motion_units": given}
            with open_rig("handheld", motion=f"lsl:{name}@0", host_config_path=tmp_path / "rig.json",
                          resolve_s=30.0, timeout_s=30.0, **opts) as rig:
                assert run_protocol(proto, tmp_path / f"{case}.h5", rig=rig).ok
        finally:
            hand.close()
        with open_session(tmp_path / f"{case}.h5") as s:
            src = s.rig_config["scan_source"]
            assert src["motion_units"] == "m" and src["motion_units_from"] == ("given" if given else "stream metadata")
            for tid in s.completed_ids():
                d = s.trial(tid)
                assert d.position_mm.max() > 250.0 and 1.5 < d.attrs["scan_duration_s"] < 3.5
    with pytest.raises(ValueError, match="--motion lsl"):
        RigSource.from_flags(handheld=True, motion_units="m")


def test_info_of_a_handheld_session_shows_the_measured_scans(tmp_path):
    """rigctl info divides a scan's samples by its measured length (old main: the plan's, 728-1,429 samp/s of a 1 kHz
    stream) and shows the tracker's rate, dropouts and the floored windows."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.cli.info import session_summary
    from rigctl.rigs import open_rig

    with open_rig("handheld", seed=3, host_config_path=tmp_path / "rig.json") as rig:
        assert run_protocol(parse_protocol(small_handheld_protocol("B", "L")), tmp_path / "s.h5", rig=rig).ok
    trials = session_summary(tmp_path / "s.h5")["trials"]
    assert len(trials) == 4
    for t in trials:
        assert t["samples_per_s"] == pytest.approx(1000.0, rel=0.002)
        assert t["duration_s"] != t["planned_duration_s"] and 85 <= t["tracker_rate_hz"] <= 125
        assert isinstance(t["tracker_dropouts"], int) and isinstance(t["floored_windows"], int)


def test_the_wrist_trackers_velocity_error_is_a_stated_parameter():
    """OperatorConfig.tracker_speed_error (the tracker on the wrist, docs/results.md 3b's sweep): the tracked
    displacement over a pass is the fingertip's times 1 + e, e of about the stated size, the finger's readings
    unchanged; at 0 (the default) every scan is bit for bit the fingertip's tracker, as before the parameter."""
    from rigctl.core.handheld import PlateAxis
    from rigctl.core.trial import PlannedTrial
    from rigctl.simulation.operator import OperatorConfig, SimulatedOperator

    planned = PlannedTrial(0, "L", 80.0, 500.0, 2.5, "medium")
    base = SimulatedOperator(seed=3).scan(planned)
    same = SimulatedOperator(OperatorConfig(tracker_speed_error=0.0), seed=3).scan(planned)
    wrist = SimulatedOperator(OperatorConfig(tracker_speed_error=0.10), seed=3).scan(planned)
    assert np.array_equal(base.tracker_xyz, same.tracker_xyz) and np.array_equal(base.taxels, same.taxels)
    assert np.array_equal(base.taxels, wrist.taxels) and not np.array_equal(base.tracker_xyz, wrist.tracker_xyz)
    ratios = []
    for seed in range(12):
        true, tracked = SimulatedOperator(seed=seed), SimulatedOperator(OperatorConfig(tracker_speed_error=0.10),
                                                                         seed=seed)
        ax = PlateAxis.from_touches(*true.touch_ends())
        (_, a), (_, b) = true.tracker_pass(planned), tracked.tracker_pass(planned)
        ratios.append(np.ptp(ax.along_mm(b)) / np.ptp(ax.along_mm(a)) - 1.0)
    assert 0.04 < np.std(ratios) < 0.2 and np.max(np.abs(ratios)) > 0.05
