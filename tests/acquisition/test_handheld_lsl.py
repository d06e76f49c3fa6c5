"""The handheld rig with its motion from a tracker's LSL stream published by another process (--motion lsl:NAME)."""

from __future__ import annotations

import subprocess
import sys
import uuid

import numpy as np
import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.rig import RigError
from rigctl.acquisition.runner import run_protocol
from rigctl.core.handheld import USED_END_MM, USED_START_MM
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

#: a tracker publishing the finger's position along the plate (mm) at 100 Hz: passes from 20 to 280 mm at 150 mm/s,
#: each followed by a quick return (the finger lifted) and a rest, for ``seconds``
PUBLISHER = """
import sys, time, pylsl
name, seconds = sys.argv[1], float(sys.argv[2])
info = pylsl.StreamInfo(name, "Position", 2, 100, pylsl.cf_float32, name + "-src")
out = pylsl.StreamOutlet(info)
t0 = pylsl.local_clock()
k = 0
while pylsl.local_clock() - t0 < seconds:
    t = k / 100.0
    phase = t % 2.6                        # 1.73 s pass, 0.5 s return, 0.37 s rest
    x = 20 + 150 * phase if phase < 260 / 150 else max(20.0, 280 - 520 * (phase - 260 / 150))
    out.push_sample([99.0, x], t0 + t)     # channel 0: a decoy; channel 1: along the plate, mm
    k += 1
    time.sleep(max(0.0, t0 + (k / 100.0) - pylsl.local_clock()))
"""

PROTO = """
name = "hh_lsl"
rig = "handheld"
textures = ["L"]
forces_g = [500]
trials_per_condition = 2
travel_mm = 200
speeds_mm_s = [150]
"""


@pytest.mark.realtime
def test_scans_from_a_tracker_stream_of_another_process(lsl, tmp_path):
    name = f"tracker-{uuid.uuid4().hex[:8]}"
    pub = subprocess.Popen([sys.executable, "-c", PUBLISHER, name, "90"])
    try:
        with open_rig("handheld", motion=f"lsl:{name}@1", host_config_path=tmp_path / "rig.json",
                      resolve_s=30.0, timeout_s=20.0) as rig:
            summary = run_protocol(parse_protocol(PROTO), tmp_path / "s.h5", rig=rig)
        assert summary.ok, summary.failures
        with open_session(tmp_path / "s.h5") as s:
            assert s.rig_config["scan_source"]["lsl_stream"] == name
            for tid in s.completed_ids():
                d = s.trial(tid)
                # 200 mm at 150 mm/s: 1.33 s, cut where the tracked position crossed 50 and 250 mm
                assert d.duration_s == pytest.approx(200 / 150, abs=0.03)
                assert np.interp(0.0, d.position_time_s, d.position_mm) == pytest.approx(USED_START_MM, abs=2.0)
                assert np.interp(d.duration_s, d.position_time_s, d.position_mm) == pytest.approx(USED_END_MM, abs=2.0)
                inner = (d.speed_time_s > 0.1) & (d.speed_time_s < d.duration_s - 0.1)
                assert np.allclose(d.speed_mm_s[inner], 150.0, rtol=0.05)
                assert 80 <= d.attrs["tracker_rate_hz"] <= 120
    finally:
        pub.kill()
        pub.wait()
    with pytest.raises(RigError, match="channels"):
        open_rig("handheld", motion="lsl:x@1,2", host_config_path=tmp_path / "rig.json")


def test_scan_boundaries_and_the_run_go_out_as_lsl_markers(lsl, tmp_path):
    from rigctl.operations import ProtocolRun

    with open_rig("handheld", seed=3, host_config_path=tmp_path / "rig.json") as rig:
        run = ProtocolRun(rig, parse_protocol(PROTO), tmp_path / "m.h5", lsl=True)
        publisher = run.lsl
        assert publisher is not None and publisher.live is None  # no drum, no live ring on the handheld rig
        assert run.run().ok
    events = [m["event"] for m in publisher.markers]
    assert events.count("scan_enter") == events.count("scan_leave") == 2
    first = events.index("scan_enter")
    assert events[first + 1] == "scan_leave" and events[0] == "run_start" and events[-1] == "run_end"
    assert not rig.marker_listeners  # the publisher let go of the rig when it closed
