"""Clock alignment (issue 27 item 2): a simulated taxel board whose clock runs 500 ppm fast, its frames received by
the host with USB/reader delays (chunks, exponential jitter, stalls of up to 80 ms, one of 2.5 s), fed online into
DeviceClockFit: every frame's fitted time within 1 ms of when it was sent, over 10 minutes of frames (simulated in
this process: no wall time)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core.clocksync import DeviceClockFit, measure_clock_offset

RATE_HZ = 1000.0
PPM = 500.0
BASE_DELAY_S = 0.4e-3  # the fixed part of the delivery delay: no fit can see it (it adds to the offset)


def simulated_board(minutes: float, *, ppm: float = PPM, seed: int = 0, t0: float = 1234.5):
    """(seq uint16, sent_s, received_s, chunk boundaries) of a board whose clock runs ``ppm`` fast.

    The board sends frame k at ``t0 + k / (RATE_HZ * (1 + ppm/1e6))`` (host seconds); the host reader receives them
    in chunks of 1-40 frames, each chunk stamped when its last frame arrived plus an exponential jitter (mean
    0.6 ms); 0.5 % of chunks are stalled by a further 5-80 ms (a loaded host); runs of 6 minutes or more have a
    2.5 s stall of the reader at minute 5."""
    rng = np.random.default_rng(seed)
    n = int(minutes * 60 * RATE_HZ)
    k = np.arange(n)
    sent = t0 + k / (RATE_HZ * (1 + ppm * 1e-6))
    ends = np.cumsum(rng.integers(1, 41, size=n // 10))
    ends = ends[ends < n]
    bounds = np.concatenate(([0], ends, [n]))
    delay = BASE_DELAY_S + rng.exponential(0.6e-3, size=len(bounds) - 1)
    stalled = rng.random(len(delay)) < 0.005
    delay[stalled] += rng.uniform(5e-3, 80e-3, size=int(stalled.sum()))
    # each chunk stamped when its last frame arrived
    received = np.repeat(sent[bounds[1:] - 1] + delay, np.diff(bounds))
    if minutes >= 6:  # a 2.5 s reader stall at minute 5: every frame of it arrives at its end (whole blocks late)
        stall = (sent >= t0 + 300.0) & (sent < t0 + 302.5)
        received[stall] = t0 + 302.5 + BASE_DELAY_S
    received = np.maximum.accumulate(received)  # a reader delivers in order
    return (k & 0xFFFF).astype(np.uint16), sent, received, bounds


def test_a_500_ppm_fast_board_is_fitted_within_1_ms_over_10_minutes():
    seq, sent, received, bounds = simulated_board(10.0)
    fit = DeviceClockFit(RATE_HZ)
    worst_online = 0.0
    counts = np.empty(len(seq), dtype=np.int64)
    for a, b in zip(bounds[:-1], bounds[1:]):
        counts[a:b] = fit.add(seq[a:b], received[a:b])
        if received[a] - received[0] > 10.0:  # online: each chunk's times from the fit as it stood when it arrived
            err = fit.host_time(counts[a:b]) - (sent[a:b] + BASE_DELAY_S)
            worst_online = max(worst_online, float(np.abs(err).max()))
    assert np.array_equal(counts, np.arange(len(seq)))  # 9 wraps of the 16-bit counter unwrapped
    m = fit.mapping()
    err = m.host_time(counts) - (sent + BASE_DELAY_S)
    raw = received - (sent + BASE_DELAY_S)
    nominal = received[0] + counts / RATE_HZ - (sent + BASE_DELAY_S)
    print(f"fitted drift {m.drift_ppm:.2f} ppm; worst error: final fit {np.abs(err).max() * 1e3:.3f} ms, online "
          f"{worst_online * 1e3:.3f} ms, raw receive times {raw.max() * 1e3:.1f} ms, nominal rate "
          f"{np.abs(nominal).max() * 1e3:.1f} ms; {m.n_rejected} of {m.n_blocks + m.n_rejected} blocks rejected")
    assert abs(m.drift_ppm - PPM) < 5
    assert m.n_rejected >= 1  # the blocks of the 2.5 s stall
    assert np.abs(err).max() < 1e-3 and worst_online < 1e-3
    # the fit is what does it: receive times as stamped are off by the stalls, the nominal rate by the drift
    assert raw.max() > 5e-3 and np.abs(nominal).max() > 0.25


def test_wraps_across_a_gap_longer_than_the_counter_are_counted_from_host_time():
    seq, sent, received, bounds = simulated_board(2.5, seed=1)
    keep = np.ones(len(seq), dtype=bool)
    keep[20_000:100_000] = False  # 80 s without frames (a trial break; the board counts on)
    fit = DeviceClockFit(RATE_HZ)
    counts = np.concatenate([fit.add(seq[keep][a:a + 500], received[keep][a:a + 500])
                             for a in range(0, int(keep.sum()), 500)])
    assert np.array_equal(counts, np.flatnonzero(keep))


def test_a_board_reset_starts_a_new_segment():
    seq, sent, received, bounds = simulated_board(0.5, seed=2)
    fit = DeviceClockFit(RATE_HZ)
    fit.add(seq[:20_000], received[:20_000])
    # the board resets: its counter starts at 0 again, 1 s later
    counts = fit.add(seq[:5_000], received[20_000:25_000] + 1.0)
    assert fit.segment == 1 and counts[0] == 0
    assert fit.mapping() is None or abs(fit.mapping().drift_ppm - PPM) < 200


def test_blocks_received_in_one_burst_get_the_nominal_rate_not_a_slope():
    """A reader starved for the stream's first 2.5 s receives its frames in one burst: the first blocks' minima all
    carry that one receive time, and a line through them maps every frame to nearly that instant (a handheld scan's
    200 mm in 1.6 ms, seen under load); the fit keeps the nominal rate through the least-delayed block instead."""
    seq, sent, received, bounds = simulated_board(0.05, seed=3)
    burst = received.copy()
    burst[:2500] = sent[2499] + 0.001  # all read at once, just after the last of them was sent
    fit = DeviceClockFit(RATE_HZ)
    counts = fit.add(seq[:2500], burst[:2500])
    m = fit.mapping()
    assert m is not None and abs(m.period_s * RATE_HZ - 1.0) < 0.02
    t = m.host_time(counts)
    # the frames 1 ms apart, 2.5 s from first to last (not one instant), never before the board sent them
    assert t[-1] - t[0] == pytest.approx(sent[2499] - sent[0], rel=0.01) and np.all(t >= sent[:2500] - 1e-3)


def test_the_lsl_offset_is_measured_within_its_bracket():
    host = iter(np.arange(0.0, 100.0, 1e-4)).__next__
    offset, half = measure_clock_offset(lambda: 5000.0 + host(), host=host, rounds=5)
    assert offset == pytest.approx(5000.0, abs=2e-4) and 0 < half <= 1e-4
