"""The on-board encoder's ring (arduino/common/sa_ring.c) and integer encoder, the board's own C run on the host
through cffi (rigctl.simulation.onboard_c): ENCODE starts at the sample it names out of the ring (issue 78 item 4), the
10-bit samples come back as pushed (spikes equal to the host's integer kernel on the same rows), a sample older than
the ring may start from starts as far back as it may and says so, one not taken yet is waited for, and a board that
catches up from the furthest back drops nothing."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core.normalisation import TaxelRange
from rigctl.devices import wire
from rigctl.encoding.fixed_sa import FixedSAEncoder
from rigctl.simulation.onboard_c import BoardModel

LO, HI = np.full(9, 100), np.full(9, 900)


@pytest.fixture(scope="module")
def rows():
    rng = np.random.default_rng(78)
    t = np.arange(600)[:, None]
    x = 500 + 350 * np.sin(t / 37.0 + np.arange(9)) + rng.normal(0, 20, (600, 9))
    x[::97] = 1023  # the top of the 10-bit range and 0 go through the packing too
    x[::89] = 0
    return np.clip(np.rint(x), 0, 1023).astype(np.uint16)


def _run(rows, from_sample: int, encode_at: int, steps: float = 1.5):
    board = BoardModel()
    board.arm(LO, HI)
    start = None
    for i, x in enumerate(rows):
        if i == encode_at:
            start = board.begin(from_sample)
        board.tick(x, steps)
    return start, board.finish(10000)


def _host(rows) -> np.ndarray:
    return FixedSAEncoder(TaxelRange(LO.astype(float), HI.astype(float))).raster(rows).astype(np.uint8)


@pytest.mark.parametrize("back", [0, 5, wire.ENC_RING_MAX_BACK])
def test_encoding_starts_at_the_entry_out_of_the_ring(rows, back):
    start, got = _run(rows, 200, 200 + back)
    assert start == got.start == 200 and got.dropped == 0
    assert got.depth_max >= back and got.raster.shape == (400, 9)
    host = _host(rows[200:])
    assert got.raster.sum() > 50 and np.array_equal(got.raster, host)


def test_an_entry_older_than_the_ring_starts_as_far_back_as_it_may(rows):
    start, got = _run(rows, 100, 200)  # 100 samples late: the ring holds 32, starts 28 back
    assert start == 200 - wire.ENC_RING_MAX_BACK
    assert np.array_equal(got.raster, _host(rows[start:])) and got.dropped == 0


def test_an_entry_not_sampled_yet_is_waited_for(rows):
    start, got = _run(rows, 250, 200)
    assert start == 250 and np.array_equal(got.raster, _host(rows[250:]))


def test_an_encoding_begun_again_starts_from_the_later_entry_out_of_the_kept_samples(rows):
    board = BoardModel()
    board.arm(LO, HI)
    for i, x in enumerate(rows):
        if i == 210:
            assert board.begin(200) == 200
        if i == 300:  # the pass begun again: its entry 10 samples back, encoded already once
            assert board.begin(290) == 290
        board.tick(x, 1.5)
    got = board.finish(10000)
    assert got.start == 290 and got.dropped == 0 and np.array_equal(got.raster, _host(rows[290:]))


def test_a_board_too_slow_to_catch_up_drops_and_counts(rows):
    _, got = _run(rows, 172, 200, steps=1.0)  # one sample a tick: the 28 behind stay behind, nothing lost
    assert got.dropped == 0 and got.depth_max == wire.ENC_RING_MAX_BACK + 1
    board = BoardModel()
    board.arm(LO, HI)
    for x in rows[:40]:
        board.tick(x)
    board.begin(12)
    for x in rows[40:60]:  # the main loop stalled: nothing encoded while the ring fills
        board.lib.onboard_host_push(board._b, board.ffi.from_buffer("uint16_t[]", np.ascontiguousarray(x)))
    got = board.finish(10000)
    assert got.dropped == 40 + 20 - 12 - wire.ENC_RING_SAMPLES and got.depth_max == wire.ENC_RING_SAMPLES
