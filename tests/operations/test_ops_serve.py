"""The headless run queue and `rigctl serve`'s HTTP API (issue 27 item 3), on the in-process rig: a protocol queued,
paused, resumed and finished through the API; a second run waits for the first; the token; the server killed
(SIGKILL) mid-run and started again resumes the run without losing or re-recording a trial; the event feed; STOP
through the API stops the simulated drum within 0.5 s (the pty rig, paced to the wall clock: `realtime`), and Ctrl-C
with an open event feed ends the restarted server in seconds (measured on the wall clock: `realtime` too). Every
request goes to 127.0.0.1 or to the app in this process."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.operations import RigSource, RunQueue, open_control

from .. import loopback
from ..conftest import wait_for as _wait, wait_unlocked

if importlib.util.find_spec("fastapi") is None:  # (not imported here: the collection of every test worker skips it)
    pytest.skip("fastapi (the serve extra) is not installed", allow_module_level=True)

TOKEN = "test-token-0123456789"
RIGCTL: list[str] = []  # this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: how long a request may take before the test calls it hung, s (httpx's default 5 s is no bound on a loaded machine)
HTTP_S = 60.0


def api(q, token=TOKEN, **kw):
    """The app over ``q`` through FastAPI's test client, as rigctl's own clients talk to it (the token, Host
    127.0.0.1; JSON bodies: ``client.post(path, json={})``)."""
    from fastapi.testclient import TestClient

    from rigctl.server import create_app

    return TestClient(create_app(q, token=token), base_url="http://127.0.0.1:8765", headers=AUTH, **kw)

PROTOCOL = ('name = "serve_test"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
            'trials_per_condition = {n}\nduration_s = 0.4\n[settle]\nsettle_time_ms = 50\n')


@pytest.fixture
def served(tmp_path):
    control = open_control(RigSource("inprocess"), seed=1, host_config_path=tmp_path / "rig.json")
    q = RunQueue(control, tmp_path / "queue.json", data_dir=tmp_path).start()
    try:
        yield api(q), q
    finally:
        q.close()
        control.close()


def test_queued_paused_resumed_finished_and_a_second_run_waits(served, tmp_path):
    # the pause must land while run a still runs: its second trial waits at the start of its capture until the
    # pause is asked (a gate on the taxel source, not a long run that a fast machine could finish first; a
    # 40-trial run cost 8 CPU-s here), so the pause is taken at the end of that trial, with trials left to record
    import threading

    client, q = served
    gate, at_gate, begin, captures = threading.Event(), threading.Event(), q.control.taxels.begin_capture, []

    def gated_begin(*args, **kwargs):
        captures.append(None)
        if len(captures) == 2:
            at_gate.set()
            assert gate.wait(120), "the test never opened the gate"
        return begin(*args, **kwargs)

    q.control.taxels.begin_capture = gated_begin
    a = client.post("/runs", json={"toml": PROTOCOL.format(n=2), "out": "a.h5"})
    assert a.status_code == 201, a.text
    a = a.json()["id"]
    b = client.post("/runs", json={"toml": PROTOCOL.format(n=1).replace('"serve_test"', '"second"'),
                                   "out": "b.h5"}).json()["id"]
    _wait(lambda: client.get(f"/runs/{a}").json()["state"] == "running")
    assert client.get(f"/runs/{b}").json()["state"] == "queued"  # one run owns the rig
    assert client.get("/status").json()["current_run"]["id"] == a
    assert at_gate.wait(120)  # trial 0 recorded, trial 1 started
    _wait(lambda: client.get(f"/runs/{a}").json()["trials_done"] == 1)  # (trial 1 cannot end: it waits at the gate)
    trial = _wait(lambda: client.get("/status").json()["current_trial"])
    assert trial["texture"] in ("A", "L") and trial["speed_mm_s"] == 120.0 and 0 <= trial["trial_id"] < 4
    assert client.post(f"/runs/{a}/pause", json={}).status_code == 200
    assert client.get(f"/runs/{a}").json()["state"] in ("running", "pausing")  # the trial in progress ends first
    gate.set()
    _wait(lambda: client.get(f"/runs/{a}").json()["state"] == "paused")
    done = client.get(f"/runs/{a}").json()["trials_done"]
    time.sleep(1.0)
    assert client.get(f"/runs/{a}").json()["trials_done"] == done == 2  # nothing recorded while paused
    assert client.get(f"/runs/{b}").json()["state"] == "queued"
    assert client.post(f"/runs/{a}/resume", json={}).json()["state"] == "running"
    ra = _wait(lambda: (r := client.get(f"/runs/{a}").json())["state"] in ("done", "failed", "stopped") and r)
    assert ra["state"] == "done" and ra["trials_done"] == ra["trials_total"] == 4, ra
    rb = _wait(lambda: (r := client.get(f"/runs/{b}").json())["state"] in ("done", "failed", "stopped") and r)
    # b started once a had ended: the times are in milliseconds, and b may start within a's last one (it did, once,
    # when this compared with >); while a was paused b stayed queued (above)
    assert rb["state"] == "done" and rb["trials_done"] == 2 and rb["started_utc"] >= ra["ended_utc"]
    # refusals in one line with the right status
    assert client.post(f"/runs/{a}/pause", json={}).status_code == 409
    assert client.get("/runs/nope").status_code == 404
    r = client.post("/runs", json={"protocol": "no_such", "out": "c.h5"})
    assert r.status_code == 404 and "known:" in r.json()["detail"]
    r = client.post("/runs", json={"toml": PROTOCOL.format(n=1), "out": "a.h5"})
    assert r.status_code == 409 and "exists" in r.json()["detail"]
    assert "/runs/{run_id}/pause" in client.get("/openapi.json").json()["paths"]


def test_stop_pauses_the_served_run_and_one_resume_finishes_it(served, tmp_path):
    """STOP means one thing on every face (issue 76): the GUI's STOP pauses its run and one Resume goes on; `POST
    /stop` left the served run `stopped`, and `POST /runs/{id}/resume` only queued it again (waiting for `POST
    /queue/release`). Now: `POST /stop` pauses it (the trial in progress discarded), a second run stays queued
    (held), and one `POST /runs/{id}/resume` records the rest and lets the queue go on."""
    client, q = served
    a = client.post("/runs", json={"toml": PROTOCOL.format(n=2), "out": "a.h5"}).json()["id"]
    b = client.post("/runs", json={"toml": PROTOCOL.format(n=1).replace('"serve_test"', '"second"'),
                                   "out": "b.h5"}).json()["id"]
    _wait(lambda: client.get(f"/runs/{a}").json()["state"] == "running" and client.get("/status").json()
          ["current_trial"])
    stop = client.post("/stop", json={}).json()
    assert stop["acknowledged"] is True and stop["held"] is True
    ra = _wait(lambda: (r := client.get(f"/runs/{a}").json())["state"] not in ("running", "pausing") and r)
    assert ra["state"] == "paused" and "STOP" in ra["cause"], ra
    time.sleep(0.5)
    assert client.get(f"/runs/{a}").json()["state"] == "paused" and client.get(f"/runs/{b}").json()["state"] == \
        "queued"
    assert client.post(f"/runs/{a}/resume", json={}).json()["state"] == "running"  # the one start
    ra = _wait(lambda: (r := client.get(f"/runs/{a}").json())["state"] in ("done", "failed", "stopped") and r)
    assert ra["state"] == "done" and ra["trials_done"] == ra["trials_total"] == 4, ra
    rb = _wait(lambda: (r := client.get(f"/runs/{b}").json())["state"] in ("done", "failed", "stopped") and r)
    assert rb["state"] == "done" and client.get("/status").json()["held"] is False


def test_a_stop_right_after_a_resume_pauses_the_run(served):
    """A resume and a STOP within the runner's 50 ms look at its pause (the attached window's Resume then STOP): the
    runner never saw the start, so no trial event told the queue the run paused again, and the run stayed
    `pausing` for good (the attached window's STOP test in 2 of 3 CI runs). The paused runner serves the STOP and
    says so: the run is `paused`, the queue held, and one resume finishes it."""
    client, q = served
    a = client.post("/runs", json={"toml": PROTOCOL.format(n=2), "out": "a.h5"}).json()["id"]
    _wait(lambda: q.get(a).trials_done >= 1)
    q.pause(a)
    _wait(lambda: q.get(a).state == "paused")
    for _ in range(3):  # each time: both before the runner's next look (it sleeps 50 ms between looks)
        q.resume(a)
        q.stop()
        _wait(lambda: q.get(a).state not in ("running", "pausing"), timeout_s=20)
        assert q.get(a).state == "paused" and q.held, q.get(a)
    assert client.post(f"/runs/{a}/resume", json={}).json()["state"] == "running"
    ra = _wait(lambda: (r := client.get(f"/runs/{a}").json())["state"] in ("done", "failed", "stopped") and r)
    assert ra["state"] == "done" and ra["trials_done"] == ra["trials_total"] == 4, ra


def test_a_run_cut_by_a_crash_waits_for_its_session_lock_then_resumes(tmp_path):
    """A killed server's journal helper may still hold the session's writer lock when the server restarts: the
    resumed run waits for it instead of failing."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.storage.journal import WriterLock
    from rigctl.storage.session import SessionWriter

    proto = parse_protocol(PROTOCOL.format(n=1))
    out = tmp_path / "cut.h5"
    SessionWriter.create(out, plan=proto.plan(), textures=proto.texture_set, protocol_source=proto.source,
                         protocol_name=proto.name).close()
    (tmp_path / "queue.json").write_text(json.dumps({"format": 1, "runs": [{
        "id": "cut1", "protocol_name": proto.name, "protocol_source": proto.source, "out": str(out),
        "state": "running", "trials_total": 2, "starts": 1, "created_utc": "2026-01-01T00:00:00+00:00"}]}))
    lock = WriterLock(out)  # the helper of the killed writer, finishing its last commit
    control = open_control(RigSource("inprocess"), seed=1, host_config_path=tmp_path / "rig.json")
    q = RunQueue(control, tmp_path / "queue.json")
    assert q.get("cut1").state == "queued" and "interrupted" in q.get("cut1").errors[-1]
    assert q.held and "POST /queue/release" in q.get("cut1").cause  # a restart is no start
    q.release()  # the operator's start
    attempts, attempt = [], q._protocol_run
    q._protocol_run = lambda *a, **kw: attempts.append(None) or attempt(*a, **kw)  # each try to open the session
    q.start()
    try:
        # it found the session locked and tried again, twice, instead of failing (counted, not a span of the wall
        # clock: a queue thread starved on a loaded machine had not even started the run 1.5 s after start())
        _wait(lambda: len(attempts) >= 3 or q.get("cut1").state not in ("queued", "running"))
        assert q.get("cut1").state == "running" and q.get("cut1").trials_done == 0  # waiting for the lock
        lock.release()
        run = _wait(lambda: q.get("cut1").state not in ("queued", "running") and q.get("cut1"))
        assert run.state == "done" and run.trials_done == 2 and run.starts == 2, run
    finally:
        q.close()
        control.close()


def test_a_token_is_required(served):
    _, q = served
    from fastapi.testclient import TestClient

    from rigctl.server import create_app

    client = TestClient(create_app(q, token="s3cret-s3cret-s3cret"), base_url="http://127.0.0.1:8765")
    assert client.get("/status").status_code == 401
    assert client.get("/status", headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert client.get("/status", headers={"Authorization": "Bearer s3cret-s3cret-s3cret"}).status_code == 200


def test_a_non_loopback_bind_without_a_token_is_refused(tmp_path, monkeypatch):
    monkeypatch.delenv("RIGCTL_SERVE_TOKEN", raising=False)
    res = CliRunner().invoke(main, ["serve", "--host", "0.0.0.0", "--rig", "inprocess",
                                    "--queue", str(tmp_path / "q.json")])
    assert res.exit_code == 2 and "--token" in res.output and not (tmp_path / "q.json").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(tmp_path):
    """The servers' environment: their queue (and token file) in $XDG_STATE_HOME/rigctl, as by default."""
    return {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "RIGCTL_SERVE_TOKEN": TOKEN,
            "XDG_STATE_HOME": str(tmp_path / "state")}


def _server(tmp_path, port, rigctl=(sys.executable, "-m", "rigctl")):
    return subprocess.Popen([*rigctl, "serve", "--rig", "inprocess", "--host", "127.0.0.1",
                             "--port", str(port), "--data-dir", str(tmp_path)], env=_env(tmp_path),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _curl_examples(tmp_path, url):
    """docs/serve.md's curl examples, run as written against the server at ``url`` (its port): the token read from
    the token file, a run queued, the event feed (read for 2 s), STOP and release."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "serve.md").read_text()
    block = text.split("## Examples with curl", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    lines = [line.replace("http://127.0.0.1:8765", url) for line in block.strip().splitlines()]
    assert lines[0].startswith("TOKEN=$(") and all(line.startswith("curl ") for line in lines[1:]), lines
    out = {}
    for line in lines[1:]:
        feed = " -N " in line
        r = subprocess.run(["bash", "-c", f"{lines[0]}\n{'timeout 2 ' if feed else ''}{line}"], env=_env(tmp_path),
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == (124 if feed else 0), (line, r.returncode, r.stderr)
        out[line.split()[-1].rsplit("/", 1)[-1]] = r.stdout
    return out


def _trials(path):
    import numpy as np

    from rigctl.storage.session import open_session

    with open_session(path) as s:
        return {t: (s.trial_attrs(t)["started_utc"], int(np.asarray(s.trial(t).taxels, dtype=np.int64).sum()))
                for t in s.completed_ids()}, len(s.plan)


# wall: Ctrl-C with an open event feed says 'stopped' within 2 s of wall time
@pytest.mark.realtime
def test_killed_mid_run_and_restarted_resumes_without_losing_or_repeating_a_trial(tmp_path):
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    # the server killed below: this worker's preloaded rigctl (a process of its own, killed with its client; not a
    # fresh interpreter's start), the one started again is a fresh interpreter (its Ctrl-C exit is the interpreter's)
    proc = _server(tmp_path, port, RIGCTL)
    try:
        _wait(lambda: _get(f"{url}/status"), timeout_s=120, every_s=0.2)
        # the event feed: progress as it happens, subscribed before the run is queued (the feed sends what comes
        # after it subscribes: a run posted first can emit its first events before the feed is there)
        with loopback.client().stream("GET", f"{url}/events", timeout=60, headers=AUTH) as feed:
            rid = loopback.client().post(f"{url}/runs", json={"toml": PROTOCOL.format(n=4), "out": "s.h5"},
                                         headers=AUTH, timeout=HTTP_S).json()["id"]
            events = []
            for line in feed.iter_lines():
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
                    if events[-1]["type"] == "trial" and events[-1]["kind"] == "complete":
                        break
        assert any(e["type"] == "progress" and e["id"] == rid for e in events)
        _wait(lambda: loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json()["trials_done"]
              >= 2, every_s=0.01)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    from rigctl.storage.journal import lock_path

    # the killed command gone (it dies just after its client: its writer lock on <name>.lock) and its commit helper
    for held in (lock_path(tmp_path / "s.h5"), tmp_path / "s.h5"):
        if held.exists():
            wait_unlocked(held)
    before, planned = _trials(tmp_path / "s.h5")
    assert 2 <= len(before) < planned == 8
    proc = _server(tmp_path, port)
    try:
        _wait(lambda: _get(f"{url}/status"), timeout_s=120, every_s=0.2)
        # a restart is no start: the cut run waits, the queue held, until the operator releases it
        status = loopback.client().get(f"{url}/status", headers=AUTH, timeout=HTTP_S).json()
        assert status["held"] is True
        assert loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json()["state"] == "queued"
        assert loopback.client().post(f"{url}/queue/release", json={}, headers=AUTH, timeout=HTTP_S).status_code == 200
        run = _wait(lambda: (r := loopback.client().get(f"{url}/runs/{rid}", headers=AUTH, timeout=HTTP_S).json())
                    ["state"] in ("done", "failed", "stopped") and r, timeout_s=240, every_s=0.2)
        curl = _curl_examples(tmp_path, url)
        assert json.loads(curl["status"])["rig"]["mode"] and json.loads(curl["runs"])["state"] == "queued"
        assert ": rigctl events" in curl["events"] and json.loads(curl["stop"])["held"] is True
        stopped_s, exit_s, said = _ctrl_c_with_an_open_feed(proc, url)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(60)
    print(f"Ctrl-C with an open event feed: 'stopped' said after {stopped_s:.2f} s, exited after {exit_s:.2f} s")
    assert "stopped in" in said and "event stream(s) closed" in said and "(0 event" not in said, said
    # measured 0.1-0.2 s to the line and 0.4-0.8 s to the exit at a load of 12-13 on 2 cores (once 3.0 s: the
    # interpreter's own teardown of numba and FastAPI is most of it); the exit bound leaves room for a busier machine
    assert stopped_s < 2.0 and exit_s < 5.0
    assert not (tmp_path / "state" / "rigctl" / "queue.token").exists()  # its token file removed
    assert run["state"] == "done" and run["starts"] == 2 and run["trials_done"] == 8, run
    after, _ = _trials(tmp_path / "s.h5")
    assert sorted(after) == list(range(8))  # none lost
    assert {t: after[t] for t in before} == before  # the trials finished before the kill were not recorded again


def _ctrl_c_with_an_open_feed(proc, url):
    """SIGINT to the server while an /events client is connected: (s until it says it stopped, s until it exits,
    what it said)."""
    import threading

    opened = threading.Event()

    def feed():
        with loopback.client().stream("GET", f"{url}/events", timeout=30, headers=AUTH) as r:
            for _ in r.iter_lines():
                opened.set()

    threading.Thread(target=feed, daemon=True).start()
    assert opened.wait(30)
    lines: list[tuple[float, str]] = []
    reader = threading.Thread(target=lambda: lines.extend((time.monotonic(), line) for line in proc.stderr),
                              daemon=True)
    reader.start()
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.wait(60)
    exit_s = time.monotonic() - t0
    reader.join(10)
    said = [(t, line) for t, line in lines if "stopped in" in line]
    assert proc.returncode == 0 and said, (proc.returncode, lines)
    return said[0][0] - t0, exit_s, said[0][1]


def _get(url):
    import httpx

    try:
        return loopback.client().get(url, timeout=2, headers=AUTH).status_code == 200
    except httpx.HTTPError:
        return False


# wall: STOP through the API judged within 0.5 s of wall time
@pytest.mark.realtime
def test_stop_through_the_api_stops_the_drum_within_half_a_second(tmp_path):
    control = open_control(RigSource("sim"), seed=1, host_config_path=tmp_path / "rig.json")
    q = RunQueue(control, tmp_path / "queue.json", data_dir=tmp_path).start()
    try:
        client = api(q)
        proto = PROTOCOL.format(n=2).replace("duration_s = 0.4", "duration_s = 4")
        rid = client.post("/runs", json={"toml": proto, "out": "s.h5"}).json()["id"]
        _wait(lambda: (client.get("/status").json()["rig"]["drum"] or {}).get("speed_mm_s", 0) > 100,
              timeout_s=120, every_s=0.05)
        t0 = time.monotonic()
        assert client.post("/stop", json={}).json()["acknowledged"] is True
        # the drum's speed read every 10 ms until it is at rest; the longest of those reads is the host's own
        # scheduling delay on this machine while the drum stopped (a read is one Modbus exchange with the virtual
        # Mega: ~5 ms on an idle machine), measured in the window it judges, not at another moment
        reads_s: list[float] = []
        while time.monotonic() - t0 < 5:
            t1 = time.monotonic()
            speed_mm_s = control.status().speed_mm_s
            reads_s.append(time.monotonic() - t1)
            if abs(speed_mm_s) < 1.0:
                break
            time.sleep(0.01)
        stopped_s = time.monotonic() - t0
        read_s = max(reads_s)
        print(f"STOP through the API -> drum at rest in {stopped_s * 1e3:.0f} ms ({len(reads_s)} reads, the longest "
              f"{read_s * 1e3:.0f} ms)")
        assert abs(speed_mm_s) < 1.0, f"the drum still turned at {speed_mm_s:.1f} mm/s 5 s after STOP"
        assert stopped_s < 0.5 + read_s, f"the drum took {stopped_s:.2f} s to stop (the longest read {read_s:.2f} s)"
        run = _wait(lambda: (r := client.get(f"/runs/{rid}").json())["state"] in ("paused", "failed") and r)
        assert run["state"] == "paused" and client.get("/status").json()["held"] is True  # STOP pauses
    finally:
        q.close()
        control.close()


@pytest.mark.lsl
def test_the_queue_publishes_every_run_on_the_same_lsl_streams(lsl, tmp_path):
    import uuid

    sid = f"rigctl-queue-{uuid.uuid4().hex[:8]}"
    (tmp_path / "rig.json").write_text(json.dumps({"lsl": {"enabled": True, "source_id": sid}}))
    control = open_control(RigSource("inprocess"), seed=1, host_config_path=tmp_path / "rig.json")
    q = RunQueue(control, tmp_path / "queue.json", lsl=True)
    found = lsl.resolve_byprop("source_id", f"{sid}-markers", minimum=1, timeout=10)
    inlet = lsl.StreamInlet(found[0], max_buflen=60, recover=False)
    inlet.open_stream(timeout=10)
    q.start()
    try:
        ids = [q.submit(tmp_path / f"{k}.h5", toml=PROTOCOL.format(n=1).replace('"serve_test"', f'"run{k}"')).id
               for k in range(2)]
        for rid in ids:
            _wait(lambda rid=rid: q.get(rid).state == "done")
        events, t_end = [], time.monotonic() + 10
        while time.monotonic() < t_end and sum(e["event"] == "run_end" for e in events) < 2:
            chunk, _ = inlet.pull_chunk(timeout=0.5)
            events += [json.loads(c[0]) for c in chunk]
    finally:
        inlet.close_stream()
        q.close()
        control.close()
    starts = [e["protocol"] for e in events if e["event"] == "run_start"]
    assert starts == ["run0", "run1"]
    assert sum(e["event"] == "trial_end" for e in events) == 4


@pytest.mark.lsl
def test_lsl_wait_holds_run_start_until_a_recorder_has_the_markers(lsl, tmp_path):
    """``--lsl-wait``: run_start waits (bounded) for a consumer of the marker stream, so a recorder started first
    holds it; without a consumer the wait ends after its bound."""
    import uuid

    from rigctl.operations import LslPublisher

    sid = f"rigctl-wait-{uuid.uuid4().hex[:8]}"
    (tmp_path / "rig.json").write_text(json.dumps({"lsl": {"enabled": True, "source_id": sid}}))
    control = open_control(RigSource("inprocess"), seed=1, host_config_path=tmp_path / "rig.json")
    pub = LslPublisher(control, protocol_name="wait", wait_s=0.5)
    try:
        t0 = time.monotonic()
        assert pub.wait_for_recorder() is False and time.monotonic() - t0 >= 0.45  # nobody: bounded
        inlet = lsl.StreamInlet(lsl.resolve_byprop("source_id", f"{sid}-markers", minimum=1, timeout=10)[0])
        inlet.open_stream(timeout=10)
        assert pub.wait_for_recorder(10.0) is True
        pub.run_marker("run_start", out="x.h5")
        sample, _ = inlet.pull_sample(timeout=10)
        assert sample is not None and json.loads(sample[0])["event"] == "run_start"
        inlet.close_stream()
    finally:
        pub.close()
        control.close()


def test_status_reads_the_monitor_not_the_controller_and_the_feed_carries_rig_events(served):
    """``rigctl serve`` is a face of the rig's one event stream: ``/status`` shows what the library's monitor read
    (a client polling it never reads the controller, so never feeds its watchdog), and the event feed carries the
    monitor's state, fault and latch events."""
    import threading

    from rigctl.core.faults import parse_fault

    client, q = served
    control = q.control
    callers: list[str] = []
    from rigctl.operations._control import rig_of

    drum = rig_of(control).drum  # the client itself: who reads it (a face gets a read-only view of it)
    read = drum.read_status

    def counted():
        callers.append(threading.current_thread().name)
        return read()

    drum.read_status = counted
    try:
        for _ in range(10):
            rig = client.get("/status").json()["rig"]
            assert rig["drum"]["state"] is not None and rig["drum_age_s"] >= 0
        assert set(callers) <= {"rig-monitor"}, set(callers)
    finally:
        drum.read_status = read
    feed = q.subscribe()
    control.bench.inject_faults([parse_fault("estop@0")])
    seen: list[dict] = []

    def latched_and_faults():  # (the monitor's state event latches the rig before its faults event is published)
        while not feed.empty():
            seen.append(feed.get_nowait())
        return (any(e["type"] == "rig" and e["kind"] == "latch" for e in seen)
                and any(e["type"] == "rig" and e["kind"] == "faults" for e in seen))

    _wait(latched_and_faults, 60)
    assert any(e["type"] == "rig" and e["kind"] == "faults" and "ESTOP" in e["message"].upper() for e in seen), seen
    assert client.get("/status").json()["rig"]["latch"]["cause"] == "estop"


def test_status_says_the_rig_in_the_words_every_face_shows(served):
    """``/status``'s ``rig.text`` is :func:`rigctl.core.drum.status_line` of the status it serves (the GUI's words,
    one home): a rig just opened moved nothing, so the controller is not homed and the actuator released."""
    from rigctl.core.drum import DrumState, describe_state, status_line

    client, q = served
    body = _wait(lambda: (b := client.get("/status").json())["rig"].get("text") and b)
    drum = body["rig"]["drum"]
    assert drum["state"] == DrumState.NOT_HOMED.name, drum  # opening is not starting
    assert body["rig"]["text"] == status_line(q.control.monitor.latest) or body["rig"]["text"].startswith(
        describe_state(int(DrumState.NOT_HOMED)).split(" - ")[0])
    assert "actuator released" in body["rig"]["text"], body["rig"]["text"]
