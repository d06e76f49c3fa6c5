"""The handheld rig's real finger (issue 37): the taxels from the finger's taxel board (``--taxel-port PORT``: the
Uno's CRC-checked frames through rigctl.devices.taxel_stream) beside a live motion source, its frames put on the host
clock by the board's clock fit and cut by the tracked position.

The first test runs the simulated Uno on a pty with countable frames and a scripted tracker: every frame of every
trial must be one of the board's (in order, none from the sensor model), and the frames kept are those between the
finger's entry into and exit from the plate's used part. The second runs the whole chain as a lab would: `rigctl sim
operator --lsl NAME --taxel-board` in another process (the simulated operator's tracker on LSL, machine-local, and
the finger's board on a pty, the sensor model at the finger's place) and `rigctl acquire PROTOCOL --handheld
--motion lsl:NAME@3 --taxel-port PORT` (a 4-scan handheld protocol).
"""

from __future__ import annotations

import re
import subprocess
import time
import uuid

import numpy as np
import pytest

from rigctl.acquisition.clock import fitted_times
from rigctl.acquisition.handheld import HandheldRig
from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core.handheld import USED_END_MM, USED_START_MM
from rigctl.core.sensor import PAPER_FINGER
from rigctl.devices.finger_board import open_finger_board
from rigctl.simulation.counting import counting_samples, intact_frames
from rigctl.simulation.virtual_uno import VirtualUno
from rigctl.storage.session import open_session

from ..conftest import small_handheld_protocol

# wall: the finger board's frames put on the host clock by a fit against time.monotonic, beside an LSL stream
#   (timestamps of LSL's local_clock, the wall)
pytestmark = pytest.mark.realtime
RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)

#: two scans of plate L (the scripted finger ignores the profile)
TWO_SCANS = small_handheld_protocol("L")

#: the scripted finger: at the plate's start for REST_S, along it at SPEED_MM_S, back in RETURN_S, again
REST_S, SPEED_MM_S, RETURN_S = 0.4, 150.0, 0.4
PERIOD_S = REST_S + 300.0 / SPEED_MM_S + RETURN_S


def scripted_along(t: np.ndarray) -> np.ndarray:
    """The scripted finger's position along the plate (mm) at times ``t`` (s of its own clock)."""
    p = np.mod(t, PERIOD_S)
    forward = np.clip((p - REST_S) * SPEED_MM_S, 0.0, 300.0)
    back = np.clip(300.0 * (1.0 - (p - REST_S - 300.0 / SPEED_MM_S) / RETURN_S), 0.0, 300.0)
    return np.where(p < REST_S + 300.0 / SPEED_MM_S, forward, back)


class ScriptedTracker:
    """A motion source (core.handheld.Tracker) sampling the scripted finger at 100 Hz on the host clock."""

    name = "scripted"
    channels = (0,)

    def __init__(self) -> None:
        self.t0 = time.monotonic()

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        k = np.arange(int(np.ceil((max(t0, self.t0) - self.t0) * 100)), int((time.monotonic() - self.t0) * 100) + 1)
        t = self.t0 + k / 100.0
        return t, scripted_along(t - self.t0)[:, None]

    def describe(self) -> dict:
        return {"tracker": self.name}

    def close(self) -> None:
        pass


@pytest.fixture
def counting_finger(tmp_path):
    """The simulated Uno streaming the 3x3 finger on a pty (its port), every frame a countable sample."""
    board = VirtualUno(tmp_path / "finger", reset_delay_s=0.05, layout=PAPER_FINGER)
    sent = {"k": 0}

    def counting(n: int):
        k = sent["k"] + np.arange(n)
        sent["k"] += n
        return counting_samples(k, PAPER_FINGER.n_channels), None

    board.run_paced(counting)
    yield str(tmp_path / "finger")
    board.close()


def assert_board_frames(d) -> None:
    """Every row of trial ``d`` is one of the counting board's frames, consecutive, none lost."""
    assert d.taxels.shape[1] == 9 and bool(np.all(intact_frames(d.taxels)))
    step = np.diff(d.taxels[:, 0].astype(np.int64)) % 1024
    assert np.all(step == 7) and d.dropped_frames == 0


def starve_the_reader(scans, from_mm: float, stall_s: float) -> list[float]:
    """Make the board's reader thread stall once for ``stall_s`` after the first chunk it reads once the scripted
    finger has passed ``from_mm`` on its way out (or is on its way back: a reader that did not run meanwhile), a host
    starved on a loaded machine: the board's frames wait in the port meanwhile. Returns the list the stall's start
    (the finger's position, mm) is noted in."""
    stream, tracker, stalled = scans.taxels, scans.tracker, []
    handle = stream._handle

    def starved(data: bytes, t_rx: float) -> None:
        handle(data, t_rx)
        p = (time.monotonic() - tracker.t0) % PERIOD_S
        if not stalled and p >= REST_S + from_mm / SPEED_MM_S:
            stalled.append(float(scripted_along(np.array([p]))[0]))
            time.sleep(stall_s)

    stream._handle = starved
    return stalled


def test_trials_hold_the_boards_frames_cut_by_the_tracked_position(tmp_path, counting_finger):
    scans = open_finger_board(counting_finger, ScriptedTracker(), None, timeout_s=30.0)
    assert scans.layout.layers == PAPER_FINGER.layers  # from the board's banner (layout=3x3x1), not assumed
    with HandheldRig(scans, host_config_path=str(tmp_path / "rig.json")) as rig:
        summary = run_protocol(parse_protocol(TWO_SCANS), tmp_path / "s.h5", rig=rig)
        # a cue a busy host gave late: the finger entered the used part 0.07-0.13 s before it
        tracker = scans.tracker
        phase = (REST_S + 60.0 / SPEED_MM_S, REST_S + 70.0 / SPEED_MM_S)  # on the way out, 60-70 mm
        while not phase[0] <= (time.monotonic() - tracker.t0) % PERIOD_S < phase[1]:
            time.sleep(0.002)
        # and its reader starved from 200 mm for 0.6 s: when the tracker shows the finger past the plate, the frames
        # of its last 50 mm are still in the port
        stalled = starve_the_reader(scans, 200.0, 0.6)
        late = rig.record_trial(parse_protocol(TWO_SCANS).plan()[0])
    assert summary.ok, summary.failures
    assert stalled
    # its entry's frames kept, and its exit's: the scan waits for frames a busy host has not read yet
    assert late.n_samples == pytest.approx(1000 * late.attrs["scan_duration_s"], abs=3)
    assert_cut_at_the_crossings(late)
    with open_session(tmp_path / "s.h5") as s:
        assert s.layout.layers == PAPER_FINGER.layers
        assert s.rig_config["scan_source"]["kind"] == "taxel_board_finger"
        for tid in s.completed_ids():
            d = s.trial(tid)
            assert_board_frames(d)
            # the frames between the finger's entry (50 mm) and exit (250 mm): 200 mm at 150 mm/s, 1.33 s at 1 kHz
            assert d.attrs["scan_duration_s"] == pytest.approx(200.0 / SPEED_MM_S, abs=0.011)  # tracker at 100 Hz
            assert d.n_samples == pytest.approx(1000 * d.attrs["scan_duration_s"], abs=3)
            assert d.attrs["clock_residual_s"] < 0.005 and d.attrs["taxels_from"].startswith("taxel board on")
            assert np.median(d.speed_mm_s[5:-5]) == pytest.approx(SPEED_MM_S, rel=0.02)
            assert_cut_at_the_crossings(d)


def test_a_serial_motion_board_beside_the_fingers_board(tmp_path, counting_finger, monkeypatch):
    """`acquire --motion serial:PORT --taxel-port PORT`: the motion board's frames (its clock fitted to the host's)
    cut the taxel board's frames (its own clock fit)."""
    from click.testing import CliRunner

    from rigctl.cli import main
    from rigctl.simulation.motion_board import VirtualMotionBoard

    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    (tmp_path / "two.toml").write_text(TWO_SCANS)
    motion = VirtualMotionBoard(seed=2, profiles=(("fast", 120.0, 120.0),), drift_ppm=300.0)
    try:
        res = CliRunner().invoke(main, ["acquire", str(tmp_path / "two.toml"), "--motion", f"serial:{motion.path}",
                                        "--taxel-port", counting_finger, "--out", str(tmp_path / "s.h5"), "--quiet",
                                        "--plates", "auto"])
    finally:
        motion.close()
    assert res.exit_code == 0, res.output
    with open_session(tmp_path / "s.h5") as s:
        src = s.rig_config["scan_source"]
        assert src["kind"] == "taxel_board_finger" and src["port"] == motion.path
        assert src["taxel_port"] == counting_finger and len(s.completed_ids()) == 2
        for tid in s.completed_ids():
            d = s.trial(tid)
            assert_board_frames(d)
            clock = {k: d.attrs[k] for k in d.attrs if k.startswith(("clock_", "taxel_", "motion_", "scan_"))}
            assert d.n_samples == pytest.approx(1000 * d.attrs["scan_duration_s"], abs=3), (tid, clock)
            assert_cut_at_the_crossings(d)
            inner = (d.speed_time_s > 0.3) & (d.speed_time_s < d.duration_s - 0.3)
            assert 70.0 < np.median(d.speed_mm_s[inner]) < 180.0  # the motion board's own velocity


def crossing_s(t: np.ndarray, x: np.ndarray, level: float) -> float:
    """When ``x`` first rises through ``level``, linearly between the samples (s of ``t``)."""
    i = int(np.flatnonzero((x[1:] >= level) & (x[:-1] < level))[0]) + 1
    return float(t[i - 1] + (level - x[i - 1]) / (x[i] - x[i - 1]) * (t[i] - t[i - 1]))


def assert_cut_at_the_crossings(d) -> None:
    """The trial's frames, on the board's fitted clock, start where the tracked position crossed 50 mm and end where
    it crossed 250 mm (within a frame: the first frame at or after the entry, the last before the exit)."""
    a = d.attrs
    frames = fitted_times(a, d.seq) - a["trial_time_origin_s"]  # on the trial's time axis, like position_time_s
    t_in = crossing_s(d.position_time_s, d.position_mm, USED_START_MM)
    t_out = crossing_s(d.position_time_s, d.position_mm, USED_END_MM)
    assert t_out - t_in == pytest.approx(a["scan_duration_s"], abs=1e-9)
    assert 0.0 <= frames[0] - t_in < 0.0011 and 0.0 < t_out - frames[-1] <= 0.0011


def _port(proc: subprocess.Popen, timeout_s: float = 120.0) -> str:
    """The ``taxel port: PATH`` line `rigctl sim operator --taxel-board` prints."""
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        m = re.match(r"taxel port:\s+(\S+)", line)
        if m:
            return m.group(1)
    raise AssertionError(f"rigctl sim operator printed no taxel port: {proc.stderr.read() if proc.stderr else ''}")


@pytest.mark.slow
def test_handheld_training_from_a_tracker_stream_and_the_fingers_board(lsl, tmp_path):
    """The whole chain in real time: 2 passes of the simulated operator (plate A, its 2 profiles: constant and ramp;
    handheld_training's 25 passes took 170-220 s, the suite's longest unit but one, and judged nothing more; so did
    4 passes on 2 plates, 35 s: every check below is per scan)."""
    name = f"finger-{uuid.uuid4().hex[:8]}"
    proto = tmp_path / "small.toml"
    proto.write_text(small_handheld_protocol("A"))
    pub = subprocess.Popen([*RIGCTL, "sim", "operator", "--lsl", name, "--taxel-board", "--seconds", "400", "--seed",
                            "5"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = _port(pub)
        out = tmp_path / "tr.h5"
        run = subprocess.run([*RIGCTL, "acquire", str(proto), "--handheld", "--motion", f"lsl:{name}@3", "--taxel-port",
                              port, "--out", str(out), "--plates", "auto"], capture_output=True, text=True, timeout=600)
    finally:
        pub.kill()
        pub.wait()
    assert run.returncode == 0, run.stdout + run.stderr
    assert "operator: plate A" in run.stderr  # the cues on the terminal: a person scans
    with open_session(out) as s:
        assert s.layout.layers == PAPER_FINGER.layers  # the board's identify reply
        src = s.rig_config["scan_source"]
        assert src["kind"] == "taxel_board_finger" and src["taxel_port"] == port and src["lsl_stream"] == name
        ids = s.completed_ids()
        assert len(ids) == 2 == len(s.plan)  # 1 plate x 2 profiles x 1
        for tid in ids:
            d = s.trial(tid)
            a = d.attrs
            assert a["boundary"] == "position" and a["taxels_from"] == f"taxel board on {port}"
            assert a["scan_leave_s"] - a["scan_enter_s"] == pytest.approx(a["scan_duration_s"])
            clock = {k: a[k] for k in a if k.startswith(("clock_", "taxel_")) or k == "attempts"}
            # 1 kHz between the boundaries
            assert d.n_samples == pytest.approx(1000 * a["scan_duration_s"], abs=3), (tid, d.dropped_frames, clock)
            # the tracker's position beside the taxels at the tracker's rate, and each 100 ms window's speed
            rate = (len(d.position_time_s) - 1) / (d.position_time_s[-1] - d.position_time_s[0])
            assert rate >= 85 and 20.0 < np.mean(d.speed_mm_s) < 250.0
            assert d.speed_mm_s.size == 2 * int(np.ceil(round(d.duration_s / 0.1, 9)))
            assert_cut_at_the_crossings(d)
            assert a["clock_residual_s"] < 0.002
