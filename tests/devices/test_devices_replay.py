"""The simulated rig replaying FabricSlide recordings: what the host records through TaxelStream equals the
replayed (resampled, quantised) source sample for sample."""

from __future__ import annotations

import numpy as np

from rigctl.devices.taxel_stream import TaxelStream
from rigctl.simulation.replay import FabricSlideReplay
from rigctl.simulation.rig import SimulatedRig


def test_recorded_samples_equal_the_replayed_source(fabricslide_dir):
    source = FabricSlideReplay(fabricslide_dir)
    # unpaced, on the rig's one clock: the stream finds it by its port and awaits the frames on it (a starved host
    # pauses the rig, and the world runs no further ahead of the stream's reader than a wire's buffer)
    with SimulatedRig(seed=1, source=source, paced=False) as rig, TaxelStream(rig.taxel_port) as stream:
        assert stream.clock is rig.clock
        stream.start()
        stream.begin_capture()
        assert stream.wait_capture(2500, timeout_s=6)
        cap = stream.end_capture()
    assert cap.dropped == 0 and cap.crc_errors == 0
    seq = cap.seq.astype(np.int64)
    assert np.all(np.diff(seq) == 1)
    start = rig.uno.stream_start_sample + int(seq[0])
    expected = source.expected_samples(len(cap), start=start)
    assert np.array_equal(cap.samples, expected)
    assert cap.samples.shape[1] == 16 and stream.layout.n_channels == 16  # 16 channels on the wire, no padding
    assert np.ptp(expected.astype(np.int64), axis=0).max() > 0  # a real signal, not a constant
