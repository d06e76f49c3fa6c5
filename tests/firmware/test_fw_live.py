"""The HIL rig's live taxel signal: the Uno firmware streams readings rendered from the Mega firmware's drum
travel and contact force (rigctl.simulation.hil live mode)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream

pytestmark = pytest.mark.hil


def test_live_taxel_signal_follows_the_drum_without_seams(hil_rig):
    """Live mode: the readings are rendered from the Mega's drum travel and force; waveform swaps (every 0.5 s)
    continue the texture's phase and amplitude, so the stream has no seams."""
    rig = hil_rig
    with DrumClient(rig.drum_port) as drum, TaxelStream(rig.taxel_port) as stream:
        rig.set_texture("B")  # circular ridges
        drum.set_force(500)
        drum.set_speed(40)
        drum.run()
        stream.start()
        drum.wait_force_settled(timeout_s=10.0)
        stream.begin_capture()
        while not stream.wait_capture(2500, timeout_s=0.2):
            drum.read_status()  # keep the watchdog fed
        cap = stream.end_capture()
        drum.stop()
    x = cap.samples.astype(float)
    assert x.std(axis=0).mean() > 20  # the ridges pass under the taxels
    steps = np.abs(np.diff(x, axis=0)).max(axis=1)
    worst = int(np.argmax(steps))
    assert steps[worst] < 60, f"a seam of {steps[worst]:.0f} counts at sample {worst} of {len(x)}"
