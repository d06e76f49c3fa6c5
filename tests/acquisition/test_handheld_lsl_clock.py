"""A tracker publishing from another clock (issue 56 item 4): liblsl's time correction puts its samples on this
machine's clock. Emulated on one machine by a publisher in a Linux time namespace whose monotonic clock (liblsl's)
runs 3,600 s ahead, which liblsl measures as two PCs' clocks."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid

import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

AHEAD_S = 3600.0
PERIOD_S = 4.0  # a pass every 4 s on the publisher's clock: at 0.3 s it leaves 15 mm at 100 mm/s, at 3.0 s it is at 285

PUBLISHER = r"""
import sys, time
import numpy as np
import pylsl
name, seconds = sys.argv[1], float(sys.argv[2])
outlet = pylsl.StreamOutlet(pylsl.StreamInfo(name, "Position", 1, 120.0, pylsl.cf_float32, "ns-" + name))
t0 = pylsl.local_clock() + 0.5
print(repr(t0), flush=True)
k = 0
while True:
    t = t0 + k / 120.0
    if t - t0 > seconds:
        break
    while pylsl.local_clock() < t:
        time.sleep(0.002)
    phase = (t - t0) % 4.0
    x = float(np.interp(phase, [0.0, 0.3, 3.0, 3.2, 4.0], [15.0, 15.0, 285.0, 15.0, 15.0]))
    outlet.push_sample([x], t)
    k += 1
"""

PROTO = """
name = "hh_clock"
rig = "handheld"
textures = ["L"]
forces_g = [500]
trials_per_condition = 3
travel_mm = 200
speeds_mm_s = [100]
"""


def _namespace_available() -> str | None:
    """Why a time namespace cannot be made here, or None."""
    if shutil.which("unshare") is None:
        return "no unshare command"
    r = subprocess.run(["unshare", "--time", "--monotonic", "10", "--fork", sys.executable, "-c", "pass"],
                       capture_output=True, text=True, timeout=30)
    return None if r.returncode == 0 else f"unshare --time failed: {r.stderr.strip()}"


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_a_tracker_on_a_clock_an_hour_ahead_records_each_scan_from_the_pass_after_its_cue(lsl, tmp_path):
    why = _namespace_available()
    if why:
        pytest.skip(why)  # (where unshare works, CI runs it: the skip names the reason)
    name = f"ns-{uuid.uuid4().hex[:8]}"
    pub = subprocess.Popen(["unshare", "--time", "--monotonic", str(int(AHEAD_S)), "--fork", sys.executable, "-c",
                            PUBLISHER, name, "120"], stdout=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        t0_pub = float(pub.stdout.readline())  # the first pass's start on the publisher's clock
        with open_rig("handheld", motion=f"lsl:{name}@0", host_config_path=tmp_path / "rig.json",
                      resolve_s=30.0, timeout_s=30.0) as rig:
            summary = run_protocol(parse_protocol(PROTO), tmp_path / "s.h5", rig=rig)
        assert summary.ok, summary.failures
        with open_session(tmp_path / "s.h5") as s:
            src = s.rig_config["scan_source"]
            assert src["lsl_time_correction_s"] == pytest.approx(-AHEAD_S, abs=0.05)
            passes, errors = [], []
            for tid in s.completed_ids():
                a = s.trial(tid).attrs
                # the truth on the host's clock: the pass crosses 50 mm 0.65 s and 250 mm 2.65 s after it starts
                k = round((a["scan_enter_s"] + AHEAD_S - t0_pub - 0.65) / PERIOD_S)
                enter = t0_pub - AHEAD_S + k * PERIOD_S + 0.65
                errors += [a["scan_enter_s"] - enter, a["scan_leave_s"] - (enter + 2.0)]
                passes.append(k)
        assert len(passes) == 3 and len(set(passes)) == 3 and passes == sorted(passes)  # distinct passes
        assert max(abs(e) for e in errors) <= 0.010, errors
    finally:
        pub.kill()
        pub.wait()
