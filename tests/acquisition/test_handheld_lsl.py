"""The handheld rig with its motion from a tracker's LSL stream published by another process (--motion lsl:NAME)."""

from __future__ import annotations

import subprocess
import uuid

import numpy as np
import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.rig import RigError
from rigctl.acquisition.runner import run_protocol
from rigctl.core.handheld import USED_END_MM, USED_START_MM
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)

PROTO = """
name = "hh_lsl"
rig = "handheld"
textures = ["L"]
forces_g = [500]
trials_per_condition = 2
travel_mm = 200
speeds_mm_s = [150]
"""


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_scans_from_a_tracker_stream_of_another_process(lsl, tmp_path):
    """`rigctl sim operator --lsl NAME` publishes the simulated operator's wrist tracker in real time; the handheld
    rig takes its x, y, z with the plate axis calibrated in the rig config (the two ends' tracker readings)."""
    import json

    from rigctl.simulation.operator import SimulatedOperator

    name = f"tracker-{uuid.uuid4().hex[:8]}"
    op = SimulatedOperator(seed=5)  # the publisher's operator: its plate's ends in the tracker's frame
    ends = [op.to_tracker(np.array([x]), np.zeros(1))[0].tolist() for x in (0.0, 300.0)]
    (tmp_path / "rig.json").write_text(json.dumps({"handheld": {"start_xyz": ends[0], "end_xyz": ends[1]}}))
    pub = subprocess.Popen([*RIGCTL, "sim", "operator", "--lsl", name, "--seconds", "120", "--seed", "5"],
                           stdout=subprocess.DEVNULL)
    try:
        with open_rig("handheld", motion=f"lsl:{name}", host_config_path=tmp_path / "rig.json",
                      resolve_s=30.0, timeout_s=30.0) as rig:
            summary = run_protocol(parse_protocol(PROTO), tmp_path / "s.h5", rig=rig)
        assert summary.ok, summary.failures
        with open_session(tmp_path / "s.h5") as s:
            assert s.rig_config["scan_source"]["lsl_stream"] == name and s.rig_config["plate_axis"] is not None
            for tid in s.completed_ids():
                d = s.trial(tid)
                # cut where the tracked position crossed 50 and 250 mm (a tracker sample every ~10 ms)
                assert np.interp(0.0, d.position_time_s, d.position_mm) == pytest.approx(USED_START_MM, abs=3.0)
                assert np.interp(d.duration_s, d.position_time_s, d.position_mm) == pytest.approx(USED_END_MM, abs=3.0)
                assert d.duration_s == pytest.approx(d.attrs["scan_duration_s"], abs=0.002)
                assert 20.0 < np.mean(d.speed_mm_s) < 250.0
                assert 85 <= d.attrs["tracker_rate_hz"] <= 125
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
