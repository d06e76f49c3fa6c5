"""Property-based tests of the taxel frame parser (rigctl.devices.frames.FrameParser) with hypothesis.

Streams are built from frames that are kept intact, bit-flipped, truncated or dropped, with random garbage between
them, and fed in random chunks. The parser must never crash, never yield a frame that was not in the stream with a
valid CRC-16 (re-checked here with wire.crc16), yield every intact frame in order, and account for every byte.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from rigctl.devices import wire
from rigctl.devices.frames import FrameParser, SequenceTracker, encode_frames


def frame_bytes(seq: int, flags: int, samples) -> bytes:
    """One frame built independently of encode_frames: sync, payload, CRC-16 from wire.crc16."""
    payload = struct.pack("<HB18H", seq, flags, *(int(v) for v in samples))
    crc = wire.crc16(payload)
    return wire.SYNC + payload + struct.pack("<H", crc)


frame_st = st.tuples(
    st.integers(0, 65535), st.integers(0, 255), st.lists(st.integers(0, 1023), min_size=18, max_size=18)
)
action_st = st.one_of(
    st.just(("keep",)),
    st.tuples(st.just("flip"), st.lists(st.tuples(st.integers(0, 42), st.integers(0, 7)), min_size=1, max_size=3)),
    st.tuples(st.just("truncate"), st.integers(1, 42)),
    st.just(("drop",)),
)
garbage_st = st.one_of(st.just(b""), st.binary(max_size=60), st.just(wire.SYNC), st.just(wire.SYNC * 3))


@st.composite
def streams(draw):
    n = draw(st.integers(0, 25))
    pieces, intact, flipped_with_sync = [], [], 0
    for _ in range(n):
        seq, flags, samples = draw(frame_st)
        raw = frame_bytes(seq, flags, samples)
        action = draw(action_st)
        pieces.append(draw(garbage_st))
        if action[0] == "keep":
            pieces.append(raw)
            intact.append((seq, flags, tuple(samples)))
        elif action[0] == "flip":
            buf = bytearray(raw)
            for pos, bit in action[1]:
                buf[pos] ^= 1 << bit
            if bytes(buf) == raw:  # flips cancelled out: still intact
                intact.append((seq, flags, tuple(samples)))
            elif buf[:2] == wire.SYNC:
                flipped_with_sync += 1
            pieces.append(bytes(buf))
        elif action[0] == "truncate":
            pieces.append(raw[: action[1]])
    pieces.append(draw(garbage_st))
    stream = b"".join(pieces)
    cuts = sorted(draw(st.lists(st.integers(0, len(stream)), max_size=12)))
    chunks = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)])]
    return stream, chunks, intact, flipped_with_sync


def _is_subsequence(needles, haystack) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


@settings(max_examples=200, deadline=None)
@given(streams())
def test_parser_never_crashes_never_yields_bad_frames_and_finds_every_intact_frame(case):
    stream, chunks, intact, flipped_with_sync = case
    parser = FrameParser()
    got = []
    for chunk in chunks:
        frames = parser.feed(chunk)
        assert frames.samples.shape == (len(frames), wire.N_TAXELS) and frames.samples.dtype == np.uint16
        for seq, flags, samples in zip(frames.seq, frames.flags, frames.samples):
            got.append((int(seq), int(flags), tuple(int(v) for v in samples)))
    for seq, flags, samples in got:
        # re-check the CRC independently: the frame with its correct CRC must be in the stream byte for byte
        assert frame_bytes(seq, flags, samples) in stream
    assert _is_subsequence(intact, got)
    stats = parser.stats
    assert stats.frames == len(got)
    assert stats.bytes_in == len(stream)
    # every byte is accounted for: in a frame, skipped, or kept as the tail of a possibly incomplete frame
    assert stats.bytes_skipped + wire.FRAME_SIZE * stats.frames + len(parser._buf) == len(stream)
    assert len(parser._buf) < wire.FRAME_SIZE  # only an incomplete frame can be waiting
    assert stats.crc_errors >= flipped_with_sync
    if len(got) == len(intact) and len(stream) == wire.FRAME_SIZE * len(intact):
        assert stats.bytes_skipped == 0 and stats.crc_errors == 0


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(1, 300), max_size=20))
def test_parser_survives_pure_garbage(data, sizes):
    parser = FrameParser()
    pos = 0
    for size in sizes + [len(data)]:
        frames = parser.feed(data[pos: pos + size])
        for seq, flags, samples in zip(frames.seq, frames.flags, frames.samples):
            assert frame_bytes(int(seq), int(flags), samples) in data
        pos += size
    stats = parser.stats
    assert stats.bytes_in == len(data)
    assert stats.bytes_skipped + wire.FRAME_SIZE * stats.frames + len(parser._buf) == len(data)
    assert len(parser._buf) < wire.FRAME_SIZE


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 65535), st.integers(1, 200), st.lists(st.integers(1, 500), min_size=1, max_size=10))
def test_encoded_stream_round_trips_in_any_chunking(seq0, n, sizes):
    rng = np.random.default_rng(n)
    samples = rng.integers(0, 1024, (n, wire.N_TAXELS))
    seq = (seq0 + np.arange(n)) & 0xFFFF
    data = encode_frames(seq, 0, samples)
    assert data == b"".join(frame_bytes(int(s), 0, row) for s, row in zip(seq, samples))
    parser, tracker = FrameParser(), SequenceTracker()
    out = []
    pos = 0
    while pos < len(data):
        for size in sizes:
            frames = parser.feed(data[pos: pos + size])
            tracker.update(frames.seq)
            out.append(frames.samples)
            pos += size
    assert np.array_equal(np.concatenate(out), samples)
    assert tracker.dropped == 0 and parser.stats.bytes_skipped == 0 and parser.stats.crc_errors == 0


def frame_bytes_ch(seq: int, flags: int, samples) -> bytes:
    """A frame of any channel count, built independently of encode_frames (7 + 2 * ch bytes)."""
    payload = struct.pack(f"<HB{len(samples)}H", seq, flags, *(int(v) for v in samples))
    return wire.SYNC + payload + struct.pack("<H", wire.crc16(payload))


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 64), st.integers(1, 16), st.integers(0, 65535), st.integers(1, 80),
       st.lists(st.integers(1, 300), min_size=1, max_size=8), st.binary(max_size=40))
def test_any_channel_count_round_trips_with_garbage(ch, bits, seq0, n, sizes, garbage):
    """Frames of ``ch`` channels (the banner's ``ch``), counts up to ``2**bits - 1``: the parser for ``ch`` finds
    every frame behind leading garbage, in any chunking, and accounts for every byte."""
    rng = np.random.default_rng(ch * 1000 + n)
    samples = rng.integers(0, 1 << bits, (n, ch))
    seq = (seq0 + np.arange(n)) & 0xFFFF
    data = encode_frames(seq, 0, samples, adc_max=(1 << bits) - 1)
    size = wire.frame_size(ch)
    assert size == 7 + 2 * ch and len(data) == n * size
    assert data == b"".join(frame_bytes_ch(int(s), 0, row) for s, row in zip(seq, samples))
    stream = garbage + data
    parser = FrameParser(n_channels=ch, adc_max=(1 << bits) - 1)
    out, pos = [], 0
    while pos < len(stream):
        for step in sizes:
            frames = parser.feed(stream[pos: pos + step])
            assert frames.samples.shape[1] == ch
            out.append(frames.samples)
            pos += step
    got = np.concatenate(out)
    # garbage can hide at most the frames whose bytes it makes look like an earlier (valid-CRC) candidate: none
    # here unless the garbage itself holds a valid frame, which a random 40-byte string essentially never does
    assert np.array_equal(got[-n:], samples)
    st_ = parser.stats
    assert st_.bytes_skipped + size * st_.frames + len(parser._buf) == len(stream)


def test_encode_refuses_counts_above_the_links_bits():
    import pytest

    with pytest.raises(ValueError, match="0-1023"):
        encode_frames([0], 0, np.full((1, 9), 1024))
    assert len(encode_frames([0], 0, np.full((1, 9), 4095), adc_max=4095)) == wire.frame_size(9) == 25
    with pytest.raises(ValueError, match="at least one channel"):
        FrameParser(n_channels=0)


def test_a_crc_valid_candidate_beyond_the_adc_range_does_not_hide_the_frame_it_overlaps():
    """Garbage that starts with the sync bytes and whose CRC happens to match (1 in 65,536) once hid the real frame
    it overlapped (Hypothesis found such a stream): the candidate was accepted, the real frame inside it dropped as
    overlap. A 10-bit link never carries a sample above 1023, so the candidate is rejected on its range and the real
    frame is found. Built here on purpose: 11 bytes of garbage (sync, seq, flags, a first sample of 0xFFFF, two free
    bytes, one more) before a real frame, the free bytes searched so that the 43-byte candidate's CRC matches."""
    real = frame_bytes(7, 0, list(range(100, 118)))
    head = bytearray(wire.SYNC + bytes([1, 0, 0, 0xFF, 0xFF, 0, 0, 0]))  # 10 bytes; index 7, 8: the free bytes
    head += b"\x00"
    assert len(head) == 11
    rows = np.tile(np.frombuffer(bytes(head) + real[: wire.FRAME_SIZE - len(head)], np.uint8), (65536, 1))
    rows[:, 7] = np.arange(65536) & 0xFF
    rows[:, 8] = np.arange(65536) >> 8
    crcs = wire.crc16_rows(rows[:, wire.CRC_START: wire.FRAME_SIZE - 2])
    want = rows[0, wire.FRAME_SIZE - 2].astype(np.uint16) | (rows[0, wire.FRAME_SIZE - 1].astype(np.uint16) << 8)
    hits = np.flatnonzero(crcs == want)
    assert hits.size, "no two free bytes give a matching CRC"
    head[7], head[8] = int(hits[0]) & 0xFF, int(hits[0]) >> 8
    candidate = bytes(head) + real[: wire.FRAME_SIZE - len(head)]
    assert wire.crc16(candidate[wire.CRC_START:-2]) == struct.unpack("<H", candidate[-2:])[0]  # a CRC-valid candidate
    stream = bytes(head) + real
    parser = FrameParser()
    frames = parser.feed(stream)
    assert [(int(s), tuple(int(v) for v in row)) for s, row in zip(frames.seq, frames.samples)] == \
        [(7, tuple(range(100, 118)))]
    assert parser.stats.out_of_range == 1 and parser.stats.crc_errors == 0
    # a 16-bit link carries 0xFFFF: there the candidate is a frame (and the overlapped one is lost, as before)
    wide = FrameParser(adc_max=0xFFFF).feed(stream)
    assert len(wide) == 1 and int(wide.samples[0, 0]) == 0xFFFF
    for bad in (0, 70000):
        with pytest.raises(ValueError):
            FrameParser(adc_max=bad)
