"""SimulatedRig end to end through both clients: the drum presses and turns, the taxel signal follows."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.devices.wire import DrumState
from rigctl.rigs import WATCHDOG_MS, drum_answer_timeout_s
from rigctl.simulation.rig import SimulatedRig

from .conftest import home

# wall (not yet moved): in-process SimulatedRigs paced to the wall clock (its default)
pytestmark = pytest.mark.realtime


def _capture(stream: TaxelStream, n: int, drum: DrumClient | None = None):
    """Capture n frames; meanwhile poll the drum every 100 ms as a host must (the watchdog trips after 1 s)."""
    stream.begin_capture()
    deadline = time.monotonic() + n / 1000 + 2
    while not stream.wait_capture(n, timeout_s=0.1):
        assert time.monotonic() < deadline
        if drum is not None:
            assert drum.read_status().state != DrumState.FAULT
    return stream.end_capture()


def test_simulated_rig_drum_and_stream(tmp_path):
    with SimulatedRig(seed=4, port_dir=tmp_path) as rig:
        rig.set_texture("G")
        assert rig.drum_port == str(tmp_path / "drum") and rig.taxel_port == str(tmp_path / "taxel")
        # the answer timeout and host watchdog of a simulated rig, as open_rig("sim") sets them (the virtual Mega is a
        # thread of this process: late on a loaded machine)
        with DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("sim"), watchdog_ms=WATCHDOG_MS["sim"]) as drum, \
                TaxelStream(rig.taxel_port) as stream:
            home(drum)
            stream.start()
            rest = _capture(stream, 300)
            drum.set_force(500)
            drum.set_speed(150)
            drum.run()
            drum.wait_speed_steady(timeout_s=8)
            status = drum.wait_force_settled(timeout_s=8)
            assert status.state == DrumState.RUNNING
            moving = _capture(stream, 2300, drum)  # 2.3 s at 150 mm/s: more than one drum revolution (314 mm)
            assert rest.dropped == 0 and moving.dropped == 0
            # pressed on the texture, the taxels read far more than at rest, and the signal moves
            assert moving.samples.mean() > rest.samples.mean() + 20
            assert moving.samples.std(axis=0).mean() > 2 * rest.samples.std(axis=0).mean()
            # the drum's index pulse reaches the stream once per revolution: 314.16 mm / 150 mm/s
            sync = np.flatnonzero(moving.flags & wire.FrameFlag.SYNC_IN)
            assert len(sync) >= 1
            revs_expected = 2300 / (np.pi * 100 / 150 * 1000)
            assert abs(len(sync) - revs_expected) <= 1
            drum.stop()
            # unplug / replug of the Uno through the rig
            rig.unplug_taxel()
            time.sleep(0.3)
            assert not stream.stats.connected
            rig.replug_taxel()
            t0 = time.monotonic()
            while stream.stats.reconnects < 1 and time.monotonic() - t0 < 5:
                time.sleep(0.05)
            assert stream.stats.reconnects == 1 and stream.stats.connected
            after = _capture(stream, 200)
            assert after.dropped == 0 and len(after) >= 200
    assert not (tmp_path / "drum").exists() and not (tmp_path / "taxel").exists()
