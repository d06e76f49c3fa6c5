"""SimulatedRig end to end through both clients: the drum presses and turns, the taxel signal follows."""

from __future__ import annotations

import numpy as np

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.devices.wire import DrumState
from rigctl.rigs import WATCHDOG_MS, drum_answer_timeout_s
from rigctl.simulation.rig import SimulatedRig

from .conftest import home


def _capture(rig: SimulatedRig, stream: TaxelStream, n: int, drum: DrumClient | None = None):
    """Capture n frames within their own time and 2 s more of the rig's clock; meanwhile poll the drum every 100 ms
    of it, as a host must (the watchdog trips after WATCHDOG_MS)."""
    stream.begin_capture()
    deadline = rig.clock.now() + n / 1000 + 2
    while not stream.wait_capture(n, timeout_s=0.1):
        assert rig.clock.now() < deadline
        if drum is not None:
            assert drum.read_status().state != DrumState.FAULT
    return stream.end_capture()


def test_simulated_rig_drum_and_stream(tmp_path):
    # unpaced: the rig runs as fast as this host's waits let it, on the one clock its clients find by their ports
    # (a starved host pauses it); every wait and deadline below is of that clock
    with SimulatedRig(seed=4, port_dir=tmp_path, paced=False) as rig:
        rig.set_texture("G")
        assert rig.drum_port == str(tmp_path / "drum") and rig.taxel_port == str(tmp_path / "taxel")
        # the answer timeout and host watchdog of a simulated rig, as open_rig("sim") sets them (the virtual Mega is a
        # thread of this process: late on a loaded machine)
        with DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("sim"), watchdog_ms=WATCHDOG_MS["sim"]) as drum, \
                TaxelStream(rig.taxel_port) as stream:
            home(drum)
            stream.start()
            rest = _capture(rig, stream, 300)
            drum.set_force(500)
            drum.set_speed(150)
            drum.run()
            drum.wait_speed_steady(timeout_s=8)
            status = drum.wait_force_settled(timeout_s=8)
            assert status.state == DrumState.RUNNING
            moving = _capture(rig, stream, 2300, drum)  # 2.3 s at 150 mm/s: more than one drum revolution (314 mm)
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
            # (the stream's reader, a host thread, notices: the rig's clock stands at the deadline until it has had
            # as much wall time as the rig's, so a starved reader is not a late one)
            rig.unplug_taxel()
            assert rig.clock.wait_for(lambda: not stream.stats.connected, 0.3, min_wall_s=0.3)
            rig.replug_taxel()
            rig.clock.wait_for(lambda: stream.stats.reconnects >= 1 and stream.stats.connected, 5, min_wall_s=5)
            assert stream.stats.reconnects == 1 and stream.stats.connected
            after = _capture(rig, stream, 200)
            assert after.dropped == 0 and len(after) >= 200
    assert not (tmp_path / "drum").exists() and not (tmp_path / "taxel").exists()
