"""Acknowledging is not starting, on `rigctl serve` (issue 51 items 1, 2 and 4), with a controller that outlives the
server: the simulated rig on ptys in this process (paced by the wall clock), `rigctl serve --rig hardware` a process
of its own on its ports, every request over loopback. What moves is judged on the model's true actuator position,
force and drum speed, not on what the firmware or the server believe.

A served run that latches (the e-stop) is ``paused`` with its cause and a resume is 409 naming the latch; the server
stopped (SIGTERM) and, the e-stop released, started again with the same command: nothing moves for 10 s, the queue
is held and ``/status`` shows the latch; ``/queue/release`` is refused while it is held; ``POST /ack`` moves nothing
for 10 s more and says what start is needed; ``/queue/release`` then starts the run (HOME, press, the drum) and
completes it, the session logging the latch and the operator's acknowledgement."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from .. import loopback

if importlib.util.find_spec("fastapi") is None:
    pytest.skip("fastapi (the serve extra) is not installed", allow_module_level=True)

TOKEN = "test-token-0123456789-ack"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: how long a request to the server may take before the test calls it hung, s (not a judgement of speed: httpx's
#: default 5 s timed out a POST /ack, which clears the latch over Modbus, beside two CPU hogs)
HTTP_S = 60.0
PROTOCOL = ('name = "serve_ack"\ntextures = ["A"]\nspeeds_mm_s = [80]\nforces_g = [250]\n'
            'trials_per_condition = 3\nduration_s = 3\n[settle]\nsettle_time_ms = 50\n')


def _wait(pred, what: str, timeout_s: float = 120.0, every_s: float = 0.05):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError(f"timed out waiting for {what}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(tmp_path, sim, port):
    env = {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "RIGCTL_SERVE_TOKEN": TOKEN,
           "XDG_STATE_HOME": str(tmp_path / "state")}
    return subprocess.Popen([sys.executable, "-m", "rigctl", "serve", "--rig", "hardware", "--drum-port",
                             sim.drum_port, "--taxel-port", sim.taxel_port, "--host", "127.0.0.1", "--port",
                             str(port), "--data-dir", str(tmp_path / "data")], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _up(url):
    import httpx

    try:
        return loopback.client().get(f"{url}/status", timeout=5, headers=AUTH).status_code == 200
    except httpx.HTTPError:
        return False


def _still(model, seconds: float) -> tuple[float, float, float]:
    """Watch the model for ``seconds`` of wall time (the simulated rig's clock follows it): the largest change of
    the actuator's position (mm) and of the true force (g), and the largest drum speed (mm/s)."""
    act0, force0 = model.actuator_mm, model.force_g
    d_act = d_force = speed = 0.0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        d_act = max(d_act, abs(model.actuator_mm - act0))
        d_force = max(d_force, abs(model.force_g - force0))
        speed = max(speed, abs(model.drum_speed_mm_s))
        time.sleep(0.02)
    return d_act, d_force, speed


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware)
#   outliving restarted `rigctl serve` processes
@pytest.mark.realtime
def test_a_restarted_server_holds_the_latch_and_only_ack_then_release_moves(tmp_path):
    from rigctl.simulation.rig import SimulatedRig
    from rigctl.storage.session import open_session

    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    with SimulatedRig(port_dir=tmp_path / "ports") as sim:
        mega, model = sim.mega, sim.model
        proc = _serve(tmp_path, sim, port)
        try:
            _wait(lambda: _up(url), "the server", 180, 0.2)
            rid = loopback.client().post(f"{url}/runs", json={"toml": PROTOCOL, "out": "s.h5"}, headers=AUTH,
                                         timeout=HTTP_S).json()["id"]
            _wait(lambda: model.drum_speed_mm_s > 50, "the drum turning", 180)
            mega.set_estop(True)  # mid-trial
            run = _wait(lambda: (r := loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json())
                        ["state"] == "paused" and r, "the run paused on the latch")
            assert run["cause"].startswith("latched: e-stop") and run["latch"]["cause"] == "estop", run
            r = loopback.client().post(f"{url}/runs/{rid}/resume", json={}, headers=AUTH, timeout=HTTP_S)
            assert r.status_code == 409 and "e-stop" in r.json()["detail"], r.text
            proc.send_signal(signal.SIGTERM)
            proc.wait(120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(60)
        assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
        mega.set_estop(False)  # released while no face runs: the controller keeps ESTOP latched
        pressed_g = model.force_g
        proc = _serve(tmp_path, sim, port)  # the same command again (a service manager's restart)
        try:
            _wait(lambda: _up(url), "the restarted server", 180, 0.2)
            d_act, d_force, speed = _still(model, 10.0)
            assert (d_act, speed) == (0.0, 0.0) and d_force < 5.0, (d_act, d_force, speed)
            status = loopback.client().get(f"{url}/status", headers=AUTH, timeout=HTTP_S).json()
            assert status["held"] is True and status["rig"]["latch"]["cause"] == "estop", status
            run = loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json()
            assert run["state"] == "queued" and "POST /ack" in run["cause"], run
            r = loopback.client().post(f"{url}/queue/release", json={}, headers=AUTH, timeout=HTTP_S)
            assert r.status_code == 409 and "e-stop" in r.json()["detail"], r.text
            r = loopback.client().post(f"{url}/ack", json={"reason": "e-stop released, bench checked", "by": "ana"},
                                       headers=AUTH, timeout=HTTP_S)
            assert r.status_code == 200 and "/queue/release" in r.json()["start"], r.text
            d_act, d_force, speed = _still(model, 10.0)
            assert (d_act, speed) == (0.0, 0.0) and d_force < 5.0, (d_act, d_force, speed)
            assert loopback.client().get(f"{url}/status", headers=AUTH, timeout=HTTP_S).json()["rig"]["latch"] is None
            # the start
            assert loopback.client().post(f"{url}/queue/release", json={}, headers=AUTH, timeout=HTTP_S).status_code == 200
            _wait(lambda: abs(model.actuator_mm) > 0.5 or model.drum_speed_mm_s > 1.0, "the start's motion", 60)
            run = _wait(lambda: (r := loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json())
                        ["state"] in ("done", "failed", "stopped") and r, "the run's end", 300)
            assert run["state"] == "done" and run["trials_done"] == 3, run
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(120)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(60)
    print(f"e-stop pressed at {pressed_g:.0f} g: 20 s after the restart and the acknowledgement, nothing moved")
    with open_session(tmp_path / "data" / "s.h5") as s:
        events = s.events
    assert [e["kind"] for e in events] == ["latched", "acknowledged"], events
    assert events[1]["by"] == "ana" and events[1]["reason"] == "e-stop released, bench checked"
    logged = [json.loads(line) for line in (tmp_path / "state" / "rigctl" / "safety.jsonl").read_text().splitlines()]
    assert [e["kind"] for e in logged][-1] == "acknowledged" and logged[-1]["by"] == "ana"
