"""The host side of the Uno encoder image's link (rigctl.devices.encoder_stream, docs/wire-protocol.md 1.5): commands
carry their payload's CRC, the parser splits taxel, spike and counts frames out of one byte stream (with garbage and
a corrupted frame in it), and the speeds a board applied follow its HELD flags. The firmware's side runs under
simavr in tests/firmware/test_fw_uno_encoder.py."""

from __future__ import annotations

import struct
from types import SimpleNamespace

import numpy as np
import pytest

from rigctl.devices import encoder_stream, wire
from rigctl.devices.encoder_stream import (
    STOP_BURST,
    EncoderStreamParser,
    OnboardEncoder,
    SpikeFrame,
    applied_speeds,
    calibrate_command,
    encode_command,
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
    # window 0 held (a starved host's first SPEED came late): the board had no speed before it and used 0
    assert list(applied_speeds(np.array([10.0, 20.0, 30.0]), [0, 1])) == [0.0, 0.0, 30.0]


def test_counted_features_are_the_features_of_the_same_spikes():
    """A board's counts frame and the speeds it applied give realtime_features' SR of the same spikes."""
    from rigctl.encoding.features import counted_realtime_features, realtime_features
    from rigctl.encoding.speed import incremental_scale
    from rigctl.encoding.spikes import SpikeTrains

    rng = np.random.default_rng(5)
    trains = SpikeTrains.from_lists([[np.sort(rng.uniform(0, 3.0, 60)) for _ in range(9)]])
    speeds = rng.uniform(30, 130, 30)
    scaled, edges = incremental_scale(trains, [speeds])
    counts = scaled.window_counts(0.1, wire.ENC_N_WINDOWS)[0]
    expect = realtime_features(scaled, edges, n_windows=wire.ENC_N_WINDOWS)[0]
    assert np.array_equal(counted_realtime_features(counts, speeds), expect) and expect.sum() > 0
    # a window the hand stood still in or slid back through is scaled at the floor, as the board does (issue 56)
    assert np.array_equal(counted_realtime_features(counts, -speeds),
                          counted_realtime_features(counts, np.zeros_like(speeds)))
    for bad in (lambda: counted_realtime_features(counts[0], speeds), lambda: counted_realtime_features(counts, [])):
        with pytest.raises(ValueError):
            bad()


class _FakeBoard:
    """A port that plays a board: 25 samples of spike frames after ENCODE, the counts frame after FINISH; it keeps
    what the host wrote."""

    def __init__(self) -> None:
        self.written = b""
        self.out = b""

    def write(self, data: bytes) -> int:
        self.written += data
        if encode_command(0) in data:
            self.out += _spike(0, [1] * 10) + _spike(10, [2] * 10) + _spike(20, [4] * 5)
        if data[:1] == b"F":
            body = struct.pack("<IHHB", 25, 0, 0, 1) + bytes(2 * wire.ENC_N_TAXELS * wire.ENC_N_WINDOWS)
            self.out += _framed(wire.COUNTS_SYNC, body)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        chunk, self.out = self.out[:size], self.out[size:]
        return chunk


def test_the_client_gives_every_window_a_speed_before_finish():
    board = _FakeBoard()
    enc = OnboardEncoder(board)
    enc.start(np.zeros(9), np.full(9, 1000))
    assert enc.poll() == 25
    scan = enc.finish([42.0], quiet_s=0.05)
    assert scan.raster.shape == (25, 9) and scan.raster[:10, 0].all() and scan.counts.samples == 25
    # one window (25 samples) without a speed: the given one, in a SPEED for window 0, then FINISH with it
    assert speed_command(0, 42.0) + finish_command(42.0) in board.written and b"P" in board.written
    assert list(scan.speeds_mm_s) == [42.0] and scan.held == []
    silent = OnboardEncoder(_FakeBoard())  # the board sends 25 samples; the host has no speed for them
    silent.start(np.zeros(9), np.full(9, 1000))
    with pytest.raises(ValueError, match="no speed"):
        silent.finish([], quiet_s=0.05)


class _DesyncedBoard(_FakeBoard):
    """A board one of whose host bytes was lost (its receive ring overran): it streams a spike frame at every read
    and takes the next ``need`` host bytes as the payload of the command the lost byte belonged to; only a STOP after
    them stops it (as the firmware's loop() parses)."""

    def __init__(self, need: int) -> None:
        super().__init__()
        self.need = need
        self.seq = 0
        self.streaming = True

    def write(self, data: bytes) -> int:
        self.written += data
        for b in data:
            if self.need:
                self.need -= 1
            elif bytes([b]) == wire.UnoCommand.STOP.value:
                self.streaming = False
        if data[:1] == b"F":
            super().write(data)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if self.streaming:
            self.out += _spike(self.seq % 65536, [1] * 10)
            self.seq += 10
        return super().read(size)


def test_a_stop_taken_as_a_payload_byte_is_sent_again_until_the_board_stops(monkeypatch):
    monkeypatch.setattr(encoder_stream, "STOP_RESEND_S", 0.05)
    board = _DesyncedBoard(need=0)
    enc = OnboardEncoder(board)
    enc.start(np.zeros(9), np.full(9, 1000))
    board.streaming, board.need = True, 5  # a SPEED whose command byte arrived and one payload byte did not
    enc.poll()
    scan = enc.finish([42.0], quiet_s=0.05, timeout_s=5.0)
    assert not board.streaming and STOP_BURST in board.written and len(STOP_BURST) > wire.ENC_CALIBRATE_PAYLOAD + 2
    assert scan.counts.samples == 25  # then FINISH, and its counts frame
    for need in range(wire.ENC_CALIBRATE_PAYLOAD + 2 + 1):  # any payload left to fill: one burst stops the board
        lost = _DesyncedBoard(need)
        lost.write(STOP_BURST)
        assert not lost.streaming, need
    endless = OnboardEncoder(_DesyncedBoard(need=0))
    endless.port.streaming = True
    endless.port.write = lambda data: len(data)  # a board that never takes a byte
    with pytest.raises(TimeoutError, match="after STOP"):
        endless.finish([42.0], quiet_s=0.05, timeout_s=0.3)
    # a host stalled longer than quiet_s between its reads (a loaded machine: each read comes 0.06 s after the last)
    # finds the board's bytes at its next read: still streaming, not quiet (a CI run beside two CPU hogs took the
    # stall for quiet, sent FINISH to the board that never stopped and timed out waiting for its counts instead)
    clock = iter(np.arange(0.0, 100.0, 0.06))
    monkeypatch.setattr(encoder_stream, "time", SimpleNamespace(monotonic=lambda: float(next(clock))))
    stalled = OnboardEncoder(_DesyncedBoard(need=0))
    stalled.port.write = lambda data: len(data)
    with pytest.raises(TimeoutError, match="after STOP"):
        stalled.finish([42.0], quiet_s=0.05, timeout_s=0.3)


def test_a_host_catching_up_sends_only_the_speeds_the_board_can_still_use():
    """A host that stalled (its board encoded 1,000 samples meanwhile, holding windows 0-7) gives every window's speed:
    only windows 8 and 9 get a SPEED (the board, which began window w + 2 at sample 100 (w + 2) without w's speed, would
    drop the others), so catching up takes 14 bytes, not 70; the speeds the board applied follow its HELD flags."""
    board = _FakeBoard()
    enc = OnboardEncoder(board)
    enc.start(np.zeros(9), np.full(9, 1000))
    board.out = b"".join(_spike(s, [1] * 10, wire.SpikeFlag.HELD if s % 100 == 0 and s >= 200 else 0)
                         for s in range(0, 1000, 10))
    while enc.poll() < 1000:
        pass
    before = len(board.written)
    for w in range(10):
        enc.send_speed(10.0 + w)
    assert board.written[before:] == speed_command(8, 18.0) + speed_command(9, 19.0)
    assert enc.speed_windows == [8, 9] and len(enc.speeds_sent) == 10
    assert held_windows(enc.parser.spikes) == list(range(8))
    assert list(applied_speeds(np.array(enc.speeds_sent), held_windows(enc.parser.spikes))) == [0.0] * 8 + [18.0, 19.0]
    board.out += _spike(1000, [1])  # sample 1000: the board began window 10
    enc.poll()
    enc.send_speed(20.0)  # window 10: due at sample 1050, the board has not held it
    assert board.written.endswith(speed_command(10, 20.0)) and enc.speed_windows == [8, 9, 10]


def test_frames_of_an_earlier_encode_are_not_the_scans():
    """ENCODE again (a pass begun again): the frames still coming from the first encoding (seq before the new
    sample) are not the scan's; the scan's first sample is where the board began the second."""
    board = _FakeBoard()
    enc = OnboardEncoder(board)
    enc.arm(np.zeros(9), np.full(9, 1000), from_sample=100)
    board.out += _spike(100, [1] * 10) + _spike(110, [1] * 10)
    enc.poll()
    assert enc.first_sample == 100 and enc.samples == 20
    enc.encode_from(300)
    board.out += _spike(120, [1] * 10) + _spike(300, [2] * 10) + _spike(310, [4] * 10)
    enc.poll()
    assert enc.first_sample == 300 and enc.samples == 20
    assert [f.seq for f in enc.spikes] == [300, 310] and enc.speeds_sent == []
