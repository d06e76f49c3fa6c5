"""The Mega alone under simavr records trials on frames marked at its index pulses
(:class:`rigctl.simulation.hil_index_taxels.IndexFrames`, issue 80 item 4): one frame a millisecond of the rig's clock,
SYNC_IN on the first frame ending at or after each index pulse, sequence numbers from the stream's start; judged on
a clock the test moves."""

from __future__ import annotations

import numpy as np

from rigctl.devices import wire
from rigctl.simulation.hil_index_taxels import MID_SCALE, IndexFrames


class _Clock:
    """A clock the test moves: ``sleep`` moves it on."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += max(s, 1e-4)


def test_frames_follow_the_clock_and_mark_each_index_pulse():
    clock, pulses = _Clock(0.0005), []
    frames = IndexFrames(clock, lambda: pulses)  # type: ignore[arg-type]
    assert frames.open()["rate_hz"] == 1000 and "no Uno" in frames.banner["line"]
    frames.start()  # the stream's first frame ends at 0.001 s
    clock.t = 0.0102
    frames.begin_capture()  # the capture's first frame ends at 0.011 s: the stream's 11th (seq 10)
    assert frames.wait_capture(90, timeout_s=0.5)  # the clock moved on to the 90th frame's end (0.100 s)
    assert abs(clock.t - 0.100) < 1e-3
    assert frames.capture_flag_index(int(wire.FrameFlag.SYNC_IN)) is None
    pulses += [0.0005, 0.0505, 0.0700]  # before the capture; in it (the frame ending 0.051 s); the frame ending 0.070
    assert frames.capture_flag_index(int(wire.FrameFlag.SYNC_IN)) == 40
    assert frames.capture_seq_index(10) == 0 and frames.capture_seq_index(49) == 39 and frames.capture_seq_index(9) is None
    assert not frames.wait_capture(500, timeout_s=0.05)  # not within the timeout: the clock moved by it
    assert 0.149 < clock.t < 0.152
    assert frames.stats.frames == int(clock.t * 1000)
    cap = frames.end_capture()
    n = len(cap)
    assert n == int(clock.t * 1000) - 10 and cap.samples.shape == (n, 18) and (cap.samples == MID_SCALE).all()
    assert np.flatnonzero(cap.flags & int(wire.FrameFlag.SYNC_IN)).tolist() == [40, 59]
    assert (np.diff(cap.seq.astype(int)) == 1).all() and cap.seq[0] == 10
    assert np.allclose(cap.host_time_s[:2], [0.011, 0.012])
    assert not frames.wait_capture(1, timeout_s=1.0)  # no capture running
