"""FabricSlide replay: the stream is the resampled, quantised recordings, exactly, in chunks of any size, looping;
and through the simulated rig what the host records equals the replayed source sample for sample."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.simulation.replay import FabricSlideReplay
from rigctl.storage.fabricslide import load_fabricslide, resample_to_1khz, to_adc

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
    with SimulatedRig(seed=1, source=replay, port_dir=tmp_path) as rig:
        with TaxelStream(rig.taxel_port) as stream:
            stream.start()
            stream.begin_capture()
            deadline = time.monotonic() + 10
            while not stream.wait_capture(1500, timeout_s=0.1):
                assert time.monotonic() < deadline
            cap = stream.end_capture()
    assert cap.dropped == 0 and cap.crc_errors == 0 and len(cap.samples) >= 1500
    served = replay.samples_served
    truth = replay.expected_samples(served)
    # the capture is one contiguous stretch of the source: find where it starts, then compare all of it
    n = len(cap.samples)
    head = cap.samples[:64]
    starts = [k for k in range(served - n + 1) if np.array_equal(truth[k:k + 64], head)]
    assert starts, "the captured samples are not a stretch of the replayed source"
    assert any(np.array_equal(truth[k:k + n], cap.samples) for k in starts)
