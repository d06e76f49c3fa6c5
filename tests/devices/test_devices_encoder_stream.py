"""The host side of the Uno encoder image's link (rigctl.devices.encoder_stream, docs/wire-protocol.md 1.5): commands
carry their payload's CRC, the parser splits taxel, spike and counts frames out of one byte stream (with garbage and
a corrupted frame in it), and the speeds a board applied follow its HELD flags. The firmware's side runs under
simavr in tests/firmware/test_fw_uno_encoder.py."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from rigctl.devices import wire
from rigctl.devices.encoder_stream import (
    EncoderStreamParser,
    SpikeFrame,
    applied_speeds,
    calibrate_command,
    finish_command,
    held_windows,
    speed_command,
    spike_raster,
)


def _framed(sync: bytes, body: bytes) -> bytes:
    return sync + body + struct.pack("<H", wire.crc16(body))


def _spike(seq: int, masks: list[int], flags: int = 0) -> bytes:
    padded = masks + [0] * (wire.SPIKE_MASKS - len(masks))
    return _framed(wire.SPIKE_SYNC, struct.pack("<HBB", seq, len(masks), flags) + struct.pack("<10H", *padded))


def _taxel(seq: int, samples: np.ndarray) -> bytes:
    return _framed(wire.SYNC, struct.pack("<HB", seq, 0) + samples.astype("<u2").tobytes())


def test_commands_carry_the_crc_of_their_payload():
    cal = calibrate_command(np.arange(9), np.arange(9) + 500, 100)
    assert cal[:1] == b"C" and len(cal) == 1 + 38 + 2
    assert struct.unpack("<H", cal[-2:])[0] == wire.crc16(cal[1:-2])
    assert struct.unpack("<19H", cal[1:-2]) == (*range(9), *range(500, 509), 100)
    v = speed_command(70000, 123.456)
    assert v[:1] == b"V" and struct.unpack("<HH", v[1:5]) == (70000 % 65536, 12346)
    assert struct.unpack("<H", v[5:])[0] == wire.crc16(v[1:5])
    assert finish_command(40.0)[1:3] == struct.pack("<H", 4000)
    for bad in (lambda: speed_command(0, -1.0), lambda: speed_command(0, 700.0), lambda: speed_command(-1, 10.0),
                lambda: calibrate_command(np.zeros(8), np.zeros(8)), lambda: calibrate_command(np.zeros(9),
                                                                                               np.ones(9), 256)):
        with pytest.raises(ValueError):
            bad()


def test_the_parser_splits_the_three_frames_out_of_one_stream():
    rng = np.random.default_rng(3)
    samples = rng.integers(0, 1024, size=(3, wire.N_TAXELS))
    counts = rng.integers(0, 50, size=(wire.ENC_N_TAXELS, wire.ENC_N_WINDOWS))
    counts_body = struct.pack("<IHHB", 30000, 2, 0, 1) + counts.astype("<u2").tobytes()
    bad = bytearray(_spike(10, [1] * 10))
    bad[8] ^= 0xFF  # a corrupted spike frame: skipped, counted
    stream = (b"\xa5junk" + _taxel(0, samples[0]) + _spike(0, [0, 3, 0x1FF, 0, 0, 0, 0, 0, 0, 4]) + bytes(bad)
              + _taxel(1, samples[1]) + _spike(20, [5, 6], wire.SpikeFlag.HELD) + _framed(wire.COUNTS_SYNC, counts_body))
    parser = EncoderStreamParser()
    for i in range(0, len(stream), 7):  # in chunks that cut every frame
        parser.feed(stream[i:i + 7])
    assert parser.seq == [0, 1] and np.array_equal(np.stack(parser.samples), samples[:2])
    assert [f.seq for f in parser.spikes] == [0, 20] and parser.crc_errors == 1
    assert list(parser.spikes[0].masks[:3]) == [0, 3, 0x1FF] and list(parser.spikes[1].masks) == [5, 6]
    (c,) = parser.counts
    assert (c.samples, c.held, c.dropped, c.queue_max) == (30000, 2, 0, 1) and np.array_equal(c.counts, counts)


def test_a_raster_needs_every_spike_frame_and_held_windows_take_the_last_speed():
    frames = [SpikeFrame(10 * k, wire.SpikeFlag.HELD if k == 20 else 0, np.full(10, 1 << (k % 9), np.uint16))
              for k in range(30)]
    raster = spike_raster(frames)
    assert raster.shape == (300, 9) and raster[:10, 0].all() and raster[10:20, 1].all() and raster.sum() == 300
    with pytest.raises(ValueError, match="lost"):
        spike_raster(frames[:3] + frames[4:])
    assert held_windows(frames) == [0]  # the frame of sample 200 (window 2 begins): window 0 was held
    assert list(applied_speeds(np.array([10.0, 20.0, 30.0]), [1])) == [10.0, 10.0, 30.0]
