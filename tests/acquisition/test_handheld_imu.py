"""A serial IMU (a velocity-only motion board) is integrated from its own stream start (issue 56 item 2): a board
reset by the port's opening (as DTR resets an Arduino) starts there and is recorded; one that was streaming before
rigctl opened its port is refused at open, the user told to start rigctl first (it was integrated from whatever frame
came first: a board running mid-pass missed every cue)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.core.handheld import ScanError
from rigctl.devices.motion import SerialMotion
from rigctl.simulation.motion_board import VirtualMotionBoard

ONE_FAST_SCAN = """
name = "imu"
rig = "handheld"
textures = ["A"]
forces_g = [500]
trials_per_condition = 1
travel_mm = 200
speeds_mm_s = [120]
"""


def test_an_imu_streaming_before_rigctl_opened_it_is_refused():
    board = VirtualMotionBoard(seed=1, fields="velocity", reset_on_open=False)
    try:
        deadline = time.monotonic() + 30.0
        while board.frames_sent < 30 and time.monotonic() < deadline:  # a quarter of a second of frames
            time.sleep(0.01)
        with pytest.raises(ScanError, match=r"velocity only \(an IMU\) and was streaming before rigctl opened its "
                                            r"port .*start rigctl first"):
            SerialMotion(board.path, open_timeout_s=20.0)
    finally:
        board.close()


# wall (not yet moved): the simulated motion board streams on a pty paced to the wall clock, and it has no
# shared-clock mode to take cheaply: a live motion source's samples are on time.monotonic by contract
# (rigctl.core.handheld.MotionSource; SerialMotion stamps its reads so), and the handheld rig's cue and scan waits
# (rigctl.core.handheld) are time.monotonic / time.sleep loops: the board, SerialMotion and those waits would all
# need the rig's clock
@pytest.mark.realtime
def test_an_imu_reset_by_the_ports_opening_is_integrated_from_its_stream_start(tmp_path):
    """The board starts at the open (seq 0, the finger at the plate's start): the scan's integrated position runs
    from the plate's start past its used part, as the encoder's would."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.rigs import open_rig
    from rigctl.storage.session import open_session

    board = VirtualMotionBoard(seed=1, fields="velocity", profiles=(("fast", 120.0, 120.0),))
    try:
        with open_rig("handheld", motion=f"serial:{board.path}", host_config_path=tmp_path / "rig.json",
                      open_timeout_s=20.0, timeout_s=30.0) as rig:
            summary = run_protocol(parse_protocol(ONE_FAST_SCAN), tmp_path / "s.h5", rig=rig)
    finally:
        board.close()
    assert summary.ok, summary.failures
    with open_session(tmp_path / "s.h5") as s:
        (tid,) = s.completed_ids()
        d = s.trial(tid)
        assert d.position_mm[0] < 50.0 < 250.0 < d.position_mm[-1] < 300.0
        assert 1.2 < d.attrs["scan_duration_s"] < 2.5  # 200 mm at about 120 mm/s
        assert np.median(d.speed_mm_s) > 80.0
