"""The controller that outlives the face keeps a real controller's time (issue 76): a face SIGSTOPped while the rig
presses and turns no longer freezes the simulated world (it held the world at its last grant: no truth row for 106 s,
so the controller's watchdog could never act). The world waits for a starved face (its grant comes when it gets the
CPU) but not for a stopped one (rigctl.core.port_clock.ClockFile.hosts_stopped), nor for its taxel reader (the
world stood again 1.3 s after the SIGSTOP for the unread frames, the back-off begun: SimulatedRig._reader_stopped):
WATCHDOG_MS of the rig's time later
the controller stops the rig by itself, and a face continued afterwards finds WATCHDOG latched."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from rigctl.core.drum import Fault

FACE = """
import sys
from rigctl.operations import RigSource, open_control
c = open_control(RigSource("hardware", drum_port=sys.argv[1], taxel_port=sys.argv[2]), home="unless_faulted")
c.run_at(60.0, 300.0)
print("running", flush=True)
while True:  # a face at work: it reads the rig on the rig's clock (each wait grants the world its time)
    c.status()
    c.drum.clock.sleep(0.1)
"""


# wall: the point is the wall clock: a face SIGSTOPped (it gets no CPU and grants no time) must not hold the simulated
# world, which then runs on the wall's pace until the controller's watchdog stops the rig
@pytest.mark.realtime
def test_a_stopped_face_does_not_freeze_the_world_and_the_watchdog_stops_the_rig(tmp_path):
    from rigctl.simulation.rig import SimulatedRig

    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state"), "RIGCTL_CONFIG": str(tmp_path / "rig.json")}
    with SimulatedRig(port_dir=tmp_path / "ports") as sim:
        face = subprocess.Popen([sys.executable, "-c", FACE, sim.drum_port, sim.taxel_port], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert face.stdout.readline().strip() == "running", face.stderr.read()
            model, mega = sim.model, sim.mega
            t_up = time.monotonic()
            while abs(model.drum_speed_mm_s - 60.0) > 5.0 and time.monotonic() - t_up < 30.0:  # the drum's ramp
                time.sleep(0.01)
            assert abs(model.drum_speed_mm_s - 60.0) < 5.0 and model.contact_force_g > 100, \
                (model.drum_speed_mm_s, model.contact_force_g)
            face.send_signal(signal.SIGSTOP)
            t0, rig0 = time.monotonic(), model.time_s
            while Fault.WATCHDOG not in mega.faults and time.monotonic() - t0 < 10.0:
                time.sleep(0.01)
            latched_s, rig_s = time.monotonic() - t0, model.time_s - rig0
            while (abs(model.drum_speed_mm_s) > 0.5 or model.contact_force_g > 5.0) and time.monotonic() - t0 < 10:
                time.sleep(0.01)
            safe_s = time.monotonic() - t0
            print(f"SIGSTOP -> WATCHDOG after {latched_s:.2f} s of wall ({rig_s:.2f} s of the rig's clock); drum at "
                  f"rest and < 5 g after {safe_s:.2f} s of wall")
            assert Fault.WATCHDOG in mega.faults, f"no WATCHDOG {latched_s:.1f} s after the face stopped"
            assert latched_s < 1.5 + 0.5, latched_s  # WATCHDOG_MS (1 s) of the rig's time, paced by the wall
            assert safe_s < 3.0, (safe_s, model.drum_speed_mm_s, model.contact_force_g)
        finally:
            face.send_signal(signal.SIGCONT)
            face.kill()
            face.wait(10)
