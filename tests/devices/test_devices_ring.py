"""The taxel ring buffer: readers with their own cursors, wrap-around, and the timing-only read."""

from __future__ import annotations

import numpy as np

from rigctl.devices.ring import RingBuffer


def _frames(start: int, n: int, n_ch: int = 3):
    k = np.arange(start, start + n)
    samples = (k[:, None] * 10 + np.arange(n_ch)[None, :]).astype(np.uint16)
    return samples, (k % 65536).astype(np.uint16), np.zeros(n, np.uint8), k / 1000.0


def test_a_reader_behind_by_more_than_the_capacity_gets_the_newest_frames_in_order():
    ring = RingBuffer(capacity=50, n_channels=3)
    for start in range(0, 130, 13):  # 130 frames in odd-sized chunks: the ring wraps more than twice
        ring.write(*_frames(start, 13))
    cursor, samples, seq, t = ring.read_since(0)
    assert cursor == 130 == ring.total
    np.testing.assert_array_equal(seq, np.arange(80, 130))
    np.testing.assert_array_equal(samples[:, 0], np.arange(80, 130) * 10)
    np.testing.assert_array_equal(t, np.arange(80, 130) / 1000.0)
    cursor2, samples2, seq2, _ = ring.read_since(120)
    assert cursor2 == 130 and list(seq2) == list(range(120, 130)) and samples2.shape == (10, 3)


def test_timing_since_is_read_since_without_the_samples():
    ring = RingBuffer(capacity=64, n_channels=3)
    for start in range(0, 200, 7):
        ring.write(*_frames(start, 7))
    for cursor, max_frames in [(0, None), (150, None), (0, 20), (190, 5), (ring.total, None)]:
        total, _, seq, t = ring.read_since(cursor, max_frames)
        total2, seq2, t2 = ring.timing_since(cursor, max_frames)
        assert total2 == total
        np.testing.assert_array_equal(seq2, seq)
        np.testing.assert_array_equal(t2, t)
    _, seq, t = ring.timing_since(0)
    seq[:] = 0  # a copy: the ring keeps its frames
    assert ring.timing_since(0)[1][-1] == 202 % 65536
