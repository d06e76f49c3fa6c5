"""Opening is not starting (issue 51; docs/safety.md, the hazard table's 'a face opens the rig' row): every face that
opens a rig (a Python protocol's context, ``rigctl.open_rig``; the GUI's connect; ``rigctl doctor``'s checks that do
not move; ``rigctl acquire`` of a plan that asks for no trial; ``rigctl serve`` at start) leaves the actuator and
the drum where they are, judged on the ground truth of a ``rigctl sim`` that outlives the faces (its truth log: true
actuator position and drum speed), with the actuator stranded away from home by an acknowledged e-stop (where a HOME
at open would move it back); the separate start (a press: HOME, TARE, press) then moves it."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import numpy as np
import pytest

from rigctl.core.drum import DrumState

from .. import loopback
from ..simulation.sim_process import HANG_S, SimProcess

# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware) and
#   faces of other processes
pytestmark = [pytest.mark.realtime]

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)

#: what counts as motion on the truth log: the actuator off its position by more than this (mm), the drum turning
#: faster than this (mm/s)
MOVED_MM, TURNING_MM_S = 0.005, 0.5

NO_TRIAL_PLAN = '''NAME = "no_trial"
MAX_TRIALS = 1  # the progress bar's total; it yields none


def plan(ctx):
    return
    yield
'''


def _motion(t: dict[str, np.ndarray], since_wall: float) -> tuple[float, float]:
    """The actuator's excursion (mm) and the drum's top speed (mm/s) on the truth log's rows from ``since_wall`` on."""
    inside = t["wall_time_s"] >= since_wall
    assert inside.sum() >= 2, "no truth rows in the window"
    act = t["actuator_mm"][inside]
    return float(np.ptp(act)), float(np.max(np.abs(t["drum_speed_mm_s"][inside])))


def _serve_opens(env: dict[str, str], hardware: list[str], folder) -> None:
    """``rigctl serve --rig hardware`` on the sim with an empty queue: up (its /status answers), then SIGTERM."""
    import httpx

    from .test_ops_outlives_face import _free_port

    port = _free_port()
    proc = subprocess.Popen([*RIGCTL, "serve", "--rig", "hardware", *hardware, "--host", "127.0.0.1", "--port",
                             str(port), "--queue", "q.json", "--data-dir", "data"], cwd=folder, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + HANG_S
        while proc.poll() is None:
            try:
                auth = {"Authorization": f"Bearer {env['RIGCTL_SERVE_TOKEN']}"}
                r = loopback.client().get(f"http://127.0.0.1:{port}/status", headers=auth, timeout=5)
                if r.status_code == 200:
                    assert "NOT_HOMED" in r.text or "not homed" in r.text.lower(), r.text
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "rigctl serve did not answer"
            time.sleep(0.3)
        assert proc.poll() is None, proc.communicate()[1]
        time.sleep(1.0)  # open and idle: still nothing moves
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=HANG_S)


def _strand_the_actuator(sim: SimProcess, source) -> None:
    """A press, an e-stop (drivers off where they stand), its release and the operator's acknowledgement (nothing
    moves): the controller NOT_HOMED and unlatched with the actuator away from home, where a HOME (at an opening)
    would visibly move it back."""
    from rigctl.operations import open_control

    with open_control(source) as control:
        control.press(300.0)
        r = sim.inject("estop@0+0.5")
        assert r.returncode == 0, r
        deadline = time.monotonic() + HANG_S
        while control.latch is None or "estop" in sim.status()["active"]:
            control.status()  # the owner's read latches it
            assert time.monotonic() < deadline, "the e-stop never latched and released"
            time.sleep(0.2)
        control.acknowledge("e-stop released, bench checked", by="pytest")
        st = control.status()
        assert st.state == DrumState.NOT_HOMED, st.describe()
    t = sim.wait_truth(sim.status()["time_s"])
    assert t["actuator_mm"][-1] > 0.1, t["actuator_mm"][-1]  # away from home: a HOME would move it back


def test_opening_any_face_moves_nothing_until_the_start(tmp_path, monkeypatch):
    from rigctl.operations import RigSource, open_control
    from rigctl.rigs import open_rig
    from rigctl_gui.app import open_rig_keeping_faults

    env = {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "XDG_STATE_HOME": str(tmp_path / "state"),
           "RIGCTL_SERVE_TOKEN": "open-moves-nothing"}
    for k in ("RIGCTL_CONFIG", "XDG_STATE_HOME"):
        monkeypatch.setenv(k, env[k])
    (tmp_path / "no_trial.py").write_text(NO_TRIAL_PLAN)
    with SimProcess(RIGCTL, tmp_path, seed=6) as sim:
        hardware = ["--drum-port", sim.drum_port, "--taxel-port", sim.taxel_port]
        source = RigSource("hardware", drum_port=sim.drum_port, taxel_port=sim.taxel_port)
        _strand_the_actuator(sim, source)
        w0 = time.time()
        with open_rig("hardware", drum_port=sim.drum_port, taxel_port=sim.taxel_port) as rig:  # a Python protocol
            st = rig.drum.read_status()
            assert st.state == DrumState.NOT_HOMED and rig.home_pending
        handle = open_rig_keeping_faults(source)  # the GUI's connect
        try:
            assert handle.control.status().state == DrumState.NOT_HOMED
        finally:
            handle.control.close()
        for args in (["doctor", *hardware, "--check", "controller-faults", "--check", "e-stop"],
                     ["acquire", "no_trial.py", *hardware, "--plates", "skip", "--quiet", "--out", "none.h5"]):
            r = subprocess.run([*RIGCTL, *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                               timeout=HANG_S, stdin=subprocess.DEVNULL)
            assert r.returncode == 0, f"{args[0]}: {r.stdout}{r.stderr}"
        _serve_opens(env, hardware, tmp_path)
        t = sim.wait_truth(sim.status()["time_s"])
        moved_mm, turned = _motion(t, w0)
        assert moved_mm <= MOVED_MM and turned <= TURNING_MM_S, \
            f"opening moved the rig: actuator {moved_mm:.3f} mm, drum {turned:.1f} mm/s"
        w1 = time.time()
        with open_control(source) as control:  # the start moves it: a press HOMEs and TAREs first, then presses
            control.press(200.0)
            assert control.status().homed
        t = sim.wait_truth(sim.status()["time_s"])
        moved_mm, _ = _motion(t, w1)
        assert moved_mm > 0.1 and np.max(t["true_force_g"][t["wall_time_s"] >= w1]) > 100, \
            f"the start (a press) did not move the actuator ({moved_mm:.3f} mm)"
