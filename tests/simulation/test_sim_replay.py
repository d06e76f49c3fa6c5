"""Replay sources through the simulated taxel board: a FabricSlide folder (the preset) and ANY session file (here
9 channels at 100 Hz made with SessionWriter) stream at their own layout and rate; what the host records over a
real pty equals the source sample for sample, and a session replay follows the plates mounted."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.simulation.replay import FabricSlideReplay
from rigctl.storage.fabricslide import load_fabricslide, resample_to_1khz, to_adc

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)
PATTERN = "Canvas_F250_V150mmps_*.csv"  # three short recordings (~4 s each)


def _independent_stream(fabricslide_dir):
    blocks = []
    for rec in load_fabricslide(fabricslide_dir, pattern=PATTERN):
        _, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
        blocks.append(to_adc(values))
    return np.concatenate(blocks)


def test_replay_stream_equals_the_recordings(fabricslide_dir):
    replay = FabricSlideReplay(fabricslide_dir, pattern=PATTERN)
    assert len(replay.files) == 3
    truth = _independent_stream(fabricslide_dir)
    total = truth.shape[0]
    rng = np.random.default_rng(0)
    chunks, got = [], 0
    while got < total + 500:  # past the end: the stream loops to the first recording
        n = int(rng.integers(1, 700))
        chunks.append(replay.read(n))
        got += n
    stream = np.concatenate(chunks)
    np.testing.assert_array_equal(stream[:total], truth)
    np.testing.assert_array_equal(stream[total:total + 500], truth[:500])
    np.testing.assert_array_equal(replay.expected_samples(got), stream)
    np.testing.assert_array_equal(replay.expected_samples(100, start=total - 50), np.concatenate(
        [truth[-50:], truth[:50]]))
    assert replay.samples_served == got
    replay.rewind()
    np.testing.assert_array_equal(replay.next_samples(10), truth[:10])


def test_replay_without_loop_ends(fabricslide_dir):
    replay = FabricSlideReplay(fabricslide_dir, pattern="Canvas_F250_V150mmps_0.csv", loop=False)
    n = replay.recording_lengths()[0]
    replay.read(n)
    with pytest.raises(EOFError):
        replay.read(1)
    with pytest.raises(FileNotFoundError):
        FabricSlideReplay(fabricslide_dir, pattern="Nothing_*.csv")


def test_recorded_through_the_simulated_rig_equals_the_source(fabricslide_dir, tmp_path):
    from rigctl.devices.taxel_stream import TaxelStream
    from rigctl.simulation.rig import SimulatedRig

    replay = FabricSlideReplay(fabricslide_dir, pattern=PATTERN)
    # unpaced, on the rig's one clock (the stream finds it by its port): frames awaited on it
    with SimulatedRig(seed=1, source=replay, port_dir=tmp_path, paced=False) as rig:
        with TaxelStream(rig.taxel_port) as stream:
            assert stream.clock is rig.clock
            stream.start()
            cap = _capture(stream, 1500, rig.clock.now, timeout=10)
    assert cap.dropped == 0 and cap.crc_errors == 0 and len(cap.samples) >= 1500
    served = replay.samples_served
    truth = replay.expected_samples(served)
    # the capture is one contiguous stretch of the source: find where it starts, then compare all of it
    n = len(cap.samples)
    head = cap.samples[:64]
    starts = [k for k in range(served - n + 1) if np.array_equal(truth[k:k + 64], head)]
    assert starts, "the captured samples are not a stretch of the replayed source"
    assert any(np.array_equal(truth[k:k + n], cap.samples) for k in starts)


# ------------------------------------------------------------------------------------------------ any session file
SESSION_TEXTURES = ("felt", "HB3", "silk_fine")


@pytest.fixture
def nine_channel_session(tmp_path):
    """A session of a 9-taxel sensor at 100 Hz (not FabricSlide) made with SessionWriter: 3 textures x 2 trials,
    each trial its own deterministic signal of 60-110 samples."""
    from rigctl.core import TrialData, parse_layout
    from rigctl.storage.session import SessionWriter

    layout = parse_layout("3x3x1", sample_rate_hz=100.0, adc_bits=10)
    rows, data = [], {}
    rng = np.random.default_rng(9)
    for i in range(6):
        n = 60 + 10 * i
        rows.append({"trial_id": i, "texture": SESSION_TEXTURES[i % 3], "speed_mm_s": 10.0 * (1 + i // 3),
                     "force_g": 50.0, "duration_s": n / 100.0, "repeat": i // 3})
        data[i] = rng.integers(0, 1024, (n, 9)).astype(np.uint16)
    path = tmp_path / "nine.h5"
    w = SessionWriter.create(path, plan=rows, layout=layout, protocol_format="none")
    w.write_trials((i, TrialData(taxels=data[i], layout=layout)) for i in range(6))
    return path, layout, data


def test_session_replay_stream_and_mounts(nine_channel_session):
    from rigctl.simulation.replay import SessionReplay

    path, layout, data = nine_channel_session
    replay = SessionReplay(path)
    assert replay.layout == layout and replay.trial_ids == list(range(6))
    truth = np.concatenate([data[i] for i in range(6)])
    got = np.concatenate([replay.read(n) for n in (7, 100, 333, 1, 200)])
    np.testing.assert_array_equal(got[:truth.shape[0]], truth)
    np.testing.assert_array_equal(got[truth.shape[0]:], truth[:got.shape[0] - truth.shape[0]])  # loops
    np.testing.assert_array_equal(replay.expected_samples(len(got)), got)
    # mount HB3: its next trials (1, then 4, then 1 again ...) from the next sample on
    replay.mount("HB3")
    out = replay.read(data[1].shape[0] + data[4].shape[0] + 5)
    np.testing.assert_array_equal(out, np.concatenate([data[1], data[4], data[1][:5]]))
    replay.mount("felt")
    np.testing.assert_array_equal(replay.read(3), data[0][:3])
    replay.mount("HB3")  # the texture's NEXT trial: 4 (1 was streamed before)
    np.testing.assert_array_equal(replay.read(data[4].shape[0]), data[4])
    with pytest.raises(KeyError, match="no trial of texture"):
        replay.mount("velvet")


def _capture(stream, n, now, timeout=20):
    """``n`` frames captured within ``timeout`` s of ``now()`` (a simulated rig's clock, or the wall's)."""
    stream.begin_capture()
    deadline = now() + timeout
    while not stream.wait_capture(n, timeout_s=0.1):
        assert now() < deadline, "no frames"
    return stream.end_capture()


def test_any_session_replayed_through_the_simulated_board_equals_the_source(nine_channel_session, tmp_path):
    """A 9-channel 100 Hz session through SimulatedRig + VirtualUno + a real pty + TaxelStream: the board announces
    9 channels at 100 Hz and the host's captured samples equal the session's trials exactly, before and after a
    plate is mounted."""
    from rigctl.devices.taxel_stream import TaxelStream
    from rigctl.simulation.replay import SessionReplay
    from rigctl.simulation.rig import SimulatedRig

    path, layout, data = nine_channel_session
    replay = SessionReplay(path)
    # unpaced, on the rig's one clock (the stream finds it by its port): frames awaited and waits on it
    with SimulatedRig(seed=1, source=replay, port_dir=tmp_path / "ports", paced=False) as rig:
        assert rig.layout == layout
        with TaxelStream(rig.taxel_port) as stream:
            assert stream.clock is rig.clock
            assert stream.layout.n_channels == 9 and stream.layout.sample_rate_hz == 100.0
            assert stream.layout.shape_text == "3x3x1" and stream.banner["layout"] == "3x3x1"
            stream.start()
            cap = _capture(stream, 150, rig.clock.now)
            start = rig.uno.stream_start_sample
            rig.set_texture("silk_fine")  # the protocol mounts a plate
            mount_at, label = replay.mounts[-1]
            assert label == "silk_fine"
            stream.stop()
            rig.clock.sleep(0.1)
            stream.start()
            cap2 = _capture(stream, 120, rig.clock.now)
            start2 = rig.uno.stream_start_sample
    assert cap.samples.shape[1] == 9 and cap.dropped == 0 and cap.crc_errors == 0
    assert np.all(np.diff(cap.seq.astype(np.int64)) == 1)
    first = start + int(cap.seq[0])
    np.testing.assert_array_equal(cap.samples, replay.expected_samples(len(cap), start=first))
    # after the mount: silk_fine's trials (2, 5, 2, ...) from the mount on, exactly
    assert cap2.dropped == 0 and cap2.crc_errors == 0
    pos = start2 + cap2.seq.astype(np.int64) - mount_at
    assert pos[0] >= 0
    silk = replay.texture_samples("silk_fine", int(pos[-1]) + 1)
    np.testing.assert_array_equal(cap2.samples, silk[pos])
    np.testing.assert_array_equal(silk[:data[2].shape[0]], data[2])


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware)
@pytest.mark.realtime
def test_rigctl_sim_replays_a_session_file(nine_channel_session, tmp_path):
    """`rigctl sim --replay SESSION.h5` streams the session at its own layout and rate."""
    import subprocess

    from rigctl.cli.sim import PORT_LINE
    from rigctl.devices.taxel_stream import TaxelStream
    from rigctl.simulation.replay import SessionReplay

    path, layout, data = nine_channel_session
    proc = subprocess.Popen([*RIGCTL, "sim", "--replay", str(path), "--port-dir", str(tmp_path / "p")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ports = {}
        while len(ports) < 2:
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
            m = PORT_LINE.match(line)
            if m:
                ports[m.group(1)] = m.group(2)
        with TaxelStream(ports["taxel"]) as stream:
            assert (stream.layout.n_channels, stream.layout.sample_rate_hz) == (9, 100.0)
            stream.start()
            cap = _capture(stream, 100, time.monotonic)
    finally:
        proc.terminate()
        proc.wait(timeout=60)  # a bound on a hang only: a loaded machine stretches the rig's shutdown
    assert cap.dropped == 0 and cap.crc_errors == 0
    truth = SessionReplay(path).expected_samples(3000)
    head = cap.samples[:20]
    starts = [k for k in range(truth.shape[0] - len(cap)) if np.array_equal(truth[k:k + 20], head)]
    assert any(np.array_equal(truth[k:k + len(cap)], cap.samples) for k in starts)
