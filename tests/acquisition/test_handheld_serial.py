"""The serial motion board (issue 37): its CRC-checked frame, the host's parser (CRC errors, lost frames, velocity
integrated into a position) and a short handheld run recorded from the simulated board on a pty
(``--motion serial:PORT``)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.devices.motion import MOTION_FRAME_SIZE, MotionParser, MotionTrack, pack_motion_frame
from rigctl.storage.session import open_session

FAST = """
name = "handheld_fast"
rig = "handheld"
textures = ["B"]
forces_g = [500]
trials_per_condition = 2
travel_mm = 200

[[profiles]]
name = "fast"
kind = "constant"
speed_mm_s = 120
"""


def test_the_guides_frame_table_is_the_codes():
    """docs/guides/handheld.md's table (offsets, sizes, field names) is what pack_motion_frame writes."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "guides" / "handheld.md").read_text()
    table = text.split("### A serial motion board", 1)[1].split("\n\n| offset", 1)[1].split("\n\n", 1)[0]
    rows = [[c.strip(" `") for c in r.split("|")[1:4]] for r in table.splitlines()[2:]]
    assert rows == [["0", "2", "sync"], ["2", "1", "seq"], ["3", "1", "flags"], ["4", "4", "t_us"],
                    ["8", "4", "position_um"], ["12", "4", "velocity_um_s"], ["16", "2", "crc"]]
    f = pack_motion_frame(7, 123456, 12.345, -6.5)
    assert f[:2] == bytes.fromhex("A54D") and f[2] == 7 and f[3] == 3
    assert int.from_bytes(f[4:8], "little") == 123456
    assert int.from_bytes(f[8:12], "little", signed=True) == 12345
    assert int.from_bytes(f[12:16], "little", signed=True) == -6500
    from rigctl.devices.wire import crc16

    assert int.from_bytes(f[16:18], "little") == crc16(f[2:16])


def test_frame_parser_checks_crc_counts_losses_and_resyncs():
    frames = [pack_motion_frame(i, 1000 * i, 1.5 * i, -20.25) for i in range(6)]
    assert all(len(f) == MOTION_FRAME_SIZE for f in frames)
    bad = bytearray(frames[2])
    bad[10] ^= 0x01
    stream = b"\x00\xa5junk" + frames[0] + frames[1] + bytes(bad) + frames[4] + frames[5]  # 3 lost on the way
    p = MotionParser()
    got = p.feed(stream[:7]) + p.feed(stream[7:25]) + p.feed(stream[25:])  # split anywhere
    assert [f.seq for f in got] == [0, 1, 4, 5]
    assert p.crc_errors >= 1 and p.lost_frames == 2  # seq 2 (bad CRC) and 3 never arrived
    assert got[3].position_mm == pytest.approx(7.5) and got[3].velocity_mm_s == pytest.approx(-20.25)
    assert got[3].t_us == 5000
    only_v = MotionParser().feed(pack_motion_frame(9, 0, None, 100.0))[0]
    assert np.isnan(only_v.position_mm) and only_v.velocity_mm_s == 100.0


def test_velocity_only_frames_are_integrated_into_a_position():
    """An IMU board: 100 mm/s for 1 s of its clock (wrapping through 2**32 us) -> 100 mm along the plate."""
    m = MotionTrack()
    parser = MotionParser()
    t0 = 2**32 - 500_000
    delay = np.random.default_rng(1).exponential(0.002, 101)  # each frame received 0-10 ms after it was sent
    for i in range(101):
        frame = pack_motion_frame(i, (t0 + 10_000 * i) & 0xFFFFFFFF, None, 100.0)
        m.add(parser.feed(frame), 5.0 + 0.01 * i + delay[i])
    t, x = m.since(0.0)
    assert t.size == 101 and np.allclose(np.diff(t), 0.01, atol=1e-3)
    assert x[-1, 0] == pytest.approx(100.0) and np.all(x[:, 1] == 100.0)


# wall (not yet moved): the simulated motion board streams on a pty paced to the wall clock, and it has no
# shared-clock mode to take cheaply: a live motion source's samples are on time.monotonic by contract
# (rigctl.core.handheld.MotionSource; SerialMotion stamps its reads so), and the handheld rig's cue and scan waits
# (rigctl.core.handheld) are time.monotonic / time.sleep loops: the board, SerialMotion and those waits would all
# need the rig's clock
@pytest.mark.realtime
def test_a_handheld_run_recorded_from_the_simulated_motion_board(tmp_path, monkeypatch):
    from rigctl.cli import main
    from rigctl.simulation.motion_board import VirtualMotionBoard

    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    (tmp_path / "fast.toml").write_text(FAST)
    board = VirtualMotionBoard(seed=1, profiles=(("fast", 120.0, 120.0),), drift_ppm=300.0)
    try:
        board.corrupt_every(50)
        res = CliRunner().invoke(main, ["acquire", str(tmp_path / "fast.toml"), "--motion", f"serial:{board.path}",
                                        "--out", str(tmp_path / "s.h5"), "--quiet", "--plates", "auto"])
    finally:
        board.close()
    assert res.exit_code == 0, res.output
    # the operator's cues on the terminal (a live motion source: nobody else tells the operator what to scan); the
    # plate cue asks for no confirmation under --plates auto (nothing waits)
    cues = [line for line in res.output.splitlines() if line.startswith("operator: ")]
    assert cues[0] == "operator: plate B: put the finger at the start of plate B"
    assert cues[1:] == ["operator: plate B, profile fast at about 120 mm/s: go"] * 2
    with open_session(tmp_path / "s.h5") as s:
        assert s.rig_config["scan_source"]["kind"] == "tracked_finger"
        assert s.rig_config["scan_source"]["port"] == board.path
        for tid in s.completed_ids():
            d = s.trial(tid)
            assert d.attrs["boundary"] == "position" and d.attrs["motion_crc_errors"] >= 3
            assert 90.0 <= d.attrs["tracker_rate_hz"] <= 120.0  # the board's frames, one per tracker sample
            assert d.position_mm[0] < 50.0 < 250.0 < d.position_mm[-1]
            inner = (d.speed_time_s > 0.3) & (d.speed_time_s < d.duration_s - 0.3)
            assert 70.0 < np.median(d.speed_mm_s[inner]) < 180.0  # the board's velocity: a fast pass
            assert 1.0 < d.duration_s < 3.5  # 200 mm at about 120 mm/s
        assert len(s.completed_ids()) == 2


# wall (not yet moved): the simulated motion board streams on a pty paced to the wall clock (above); the plate cue
# waits on a person's Enter on a real terminal (a pty as the command's stdin)
@pytest.mark.realtime
def test_a_live_operators_plate_cue_waits_for_enter_on_the_terminal(tmp_path, monkeypatch):
    """Issue 78 item 5: with a live motion source the plate cue says "then confirm" and the run waits for Enter on the
    terminal before it cues the first scan (--plates prompt, the default); without a terminal on stdin that is refused
    before anything starts (exit 2, naming --plates auto), as on the drum rig's hardware."""
    import os
    import select
    import subprocess
    import sys
    import time

    from rigctl.simulation.motion_board import VirtualMotionBoard

    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    (tmp_path / "fast.toml").write_text(FAST.replace("trials_per_condition = 2", "trials_per_condition = 1"))
    board = VirtualMotionBoard(seed=1, profiles=(("fast", 120.0, 120.0),), drift_ppm=300.0)
    args = [sys.executable, "-m", "rigctl", "acquire", str(tmp_path / "fast.toml"), "--motion", f"serial:{board.path}",
            "--quiet"]
    try:
        no_tty = subprocess.run([*args, "--out", str(tmp_path / "n.h5")], capture_output=True, text=True,
                                timeout=120, stdin=subprocess.DEVNULL)
        assert no_tty.returncode == 2 and "stdin is not a terminal" in no_tty.stderr, no_tty.stderr
        assert "--plates auto" in no_tty.stderr and not (tmp_path / "n.h5").exists()
        master, slave = os.openpty()
        proc = subprocess.Popen([*args, "--out", str(tmp_path / "s.h5")], stdin=slave, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        os.close(slave)
        said: list[str] = []

        def read_until(what: str, timeout_s: float) -> bool:
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                if select.select([proc.stderr], [], [], 0.2)[0]:
                    line = proc.stderr.readline()
                    said.append(line.rstrip("\n"))
                    if what in line:
                        return True
            return False

        try:
            assert read_until("then confirm", 120), said
            assert not read_until(": go", 3.0), said  # no scan is cued while nobody has confirmed the plate
            os.write(master, b"\n")
            assert read_until(": go", 60), said
            assert proc.wait(timeout=300) == 0, said + proc.stderr.read().splitlines()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            os.close(master)
    finally:
        board.close()
    assert said[0] == "operator: plate B: put the finger at the start of plate B, then confirm", said
    with open_session(tmp_path / "s.h5") as s:
        assert len(s.completed_ids()) == 1
