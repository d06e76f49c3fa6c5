"""Every LSL inlet rigctl opens reads its stream on this machine's clock (issue 56 item 2: liblsl's time correction
and its clock-sync post-processing for every stream): the replay source fed by a lab's taxel stream
(``--replay lsl:NAME``), published from a clock an hour ahead (a Linux time namespace, as two PCs)."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid

import pytest

from ..acquisition.test_handheld_lsl_clock import _namespace_available

AHEAD_S = 3600.0

PUBLISHER = r"""
import sys, time
import pylsl
name = sys.argv[1]
outlet = pylsl.StreamOutlet(pylsl.StreamInfo(name, "Tactile", 9, 200.0, pylsl.cf_int32, "ns-" + name))
print("up", flush=True)
t0, k = pylsl.local_clock(), 0
while k < 200 * 20:
    while t0 + k / 200 <= pylsl.local_clock():
        outlet.push_sample([500] * 9, t0 + k / 200)
        k += 1
    time.sleep(0.005)
"""


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_the_replay_inlet_reads_a_stream_from_a_clock_an_hour_ahead_on_this_machines_clock(lsl):
    """The replay source's samples are stamped on this machine's LSL clock (within 1 s of now) and it records the
    correction liblsl applied (-3600 s +- 50 ms); old main opened its inlet without the clock sync (stamps an hour
    ahead) and recorded none."""
    from rigctl.simulation.lsl_replay import LslReplay

    why = _namespace_available()
    if why:
        pytest.skip(why)
    name = f"ns-taxels-{uuid.uuid4().hex[:8]}"
    pub = subprocess.Popen(["unshare", "--time", "--monotonic", str(int(AHEAD_S)), "--fork", sys.executable, "-c",
                            PUBLISHER, name], stdout=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        assert pub.stdout.readline().strip() == "up"
        src = LslReplay(name, resolve_s=30.0)
        try:
            src.read(50)
            now = lsl.local_clock()
            d = src.describe()
        finally:
            src.close()
    finally:
        pub.kill()
        pub.wait()
    assert d["lsl_time_correction_s"] == pytest.approx(-AHEAD_S, abs=0.05)
    assert abs(d["lsl_last_stamp_s"] - now) < 1.0 and d["lsl_first_stamp_s"] <= d["lsl_last_stamp_s"]
