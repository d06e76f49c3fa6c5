"""``rigctl serve``'s paths and queue file (issue 52 item 9): a run's ``out`` checked again as the run starts (a
subfolder replaced by a symlink while the run waited in the queue is refused: nothing written outside the data
folder); subfolders made on request (docs/serve.md's own ``mouse1/s1.h5``); one server per queue file (a second
``rigctl serve`` on it refuses in one line, exit 1); a bounded history; progress not written to the queue file at
every event; ``/docs`` from the Swagger UI files rigctl ships, with no token in the page. The in-process rig, the API
through FastAPI's test client, and two real ``rigctl serve`` processes for the lock."""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.operations import QueueError, RigSource, RunQueue, _queue, open_control

from .. import loopback
from ..conftest import wait_for

if importlib.util.find_spec("fastapi") is None:  # (not imported here: the collection of every test worker skips it)
    pytest.skip("fastapi (the serve extra) is not installed", allow_module_level=True)

TOKEN = "paths-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PROTOCOL = ('name = "paths"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
            'trials_per_condition = {n}\nduration_s = 0.3\n[settle]\nsettle_time_ms = 50\n')
ENDED = ("done", "failed", "stopped")




@pytest.fixture
def rig(tmp_path):
    control = open_control(RigSource("inprocess"), seed=2, host_config_path=tmp_path / "rig.json")
    try:
        yield control
    finally:
        control.close()


def _api(q):
    from fastapi.testclient import TestClient

    from rigctl.server import create_app

    return TestClient(create_app(q, token=TOKEN), base_url="http://127.0.0.1:8765", headers=AUTH)


def _files(root: Path) -> set[str]:
    return {os.path.relpath(os.path.join(d, f), root) for d, _, fs in os.walk(root) for f in fs}


def test_a_subfolder_replaced_by_a_symlink_before_the_run_starts_is_refused(rig, tmp_path):
    data, outside = tmp_path / "data", tmp_path / "outside"
    (data / "mouse1").mkdir(parents=True)
    outside.mkdir()
    q = RunQueue(rig, tmp_path / "queue.json", data_dir=data)  # not started: the run waits in the queue
    try:
        run = q.submit("mouse1/s1.h5", toml=PROTOCOL.format(n=1))
        assert run.out == str(data / "mouse1" / "s1.h5")
        # while it waits, the subfolder becomes a link out of the data folder
        (data / "mouse1").rename(data / "mouse1.old")
        (data / "mouse1").symlink_to(outside, target_is_directory=True)
        q.start()
        ended = wait_for(lambda: q.get(run.id).state in ENDED and q.get(run.id))
        assert ended.state == "failed", (ended.state, ended.errors)
        assert "symlink" in ended.errors[-1], ended.errors
        assert _files(outside) == set()  # nothing written outside
        assert _files(data / "mouse1.old") == set()
        # and at submit: the same rule, 422
        client = _api(q)
        r = client.post("/runs", json={"toml": PROTOCOL.format(n=1), "out": "mouse1/s2.h5"})
        assert r.status_code == 422 and "symlink" in r.json()["detail"], r.text
        assert _files(outside) == set()
    finally:
        q.close()


def test_subfolders_are_made_on_request_inside_the_data_folder(rig, tmp_path):
    data = tmp_path / "data"
    q = RunQueue(rig, tmp_path / "queue.json", data_dir=data).start()
    try:
        client = _api(q)
        r = client.post("/runs", json={"toml": PROTOCOL.format(n=1), "out": "mouse1/day2/s1.h5"})
        assert r.status_code == 201, r.text
        rid = r.json()["id"]
        run = wait_for(lambda: (r := client.get(f"/runs/{rid}").json())["state"] in ENDED and r)
        assert run["state"] == "done" and run["trials_done"] == 2, run
        assert (data / "mouse1" / "day2" / "s1.h5").is_file()
        (data / "notes").write_text("a file, not a folder")
        r = client.post("/runs", json={"toml": PROTOCOL.format(n=1), "out": "notes/s1.h5"})
        assert r.status_code == 422 and "notes in the data folder is not a folder" in r.json()["detail"], r.text
        # a refused protocol makes no folder
        r = client.post("/runs", json={"toml": "not a protocol", "out": "mouse2/s1.h5"})
        assert r.status_code == 400 and not (data / "mouse2").exists()
    finally:
        q.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_one_server_per_queue_file(rig, tmp_path):
    import httpx

    queue_file = tmp_path / "state" / "queue.json"
    q = RunQueue(rig, queue_file)
    try:
        with pytest.raises(QueueError, match="served already") as err:
            RunQueue(rig, queue_file)
        assert err.value.status == 409
    finally:
        q.close()
    env = {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "RIGCTL_SERVE_TOKEN": TOKEN}
    first_port = _free_port()
    cmd = [sys.executable, "-m", "rigctl", "serve", "--rig", "inprocess", "--queue", str(queue_file),
           "--data-dir", str(tmp_path / "data")]
    first = subprocess.Popen([*cmd, "--port", str(first_port)], env=env, stdout=subprocess.DEVNULL,
                             stderr=open(tmp_path / "first.log", "w"))
    try:
        url = f"http://127.0.0.1:{first_port}"

        def up():
            try:
                return loopback.client().get(f"{url}/status", headers=AUTH, timeout=5).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, timeout_s=300, every_s=0.2)  # (a loaded machine takes a minute to start one)
        token_file = queue_file.with_suffix(".token")
        before = token_file.read_bytes()
        second = subprocess.Popen([*cmd, "--port", str(_free_port())], env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        try:
            out, err = second.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            second.kill()
            second.communicate()
            raise AssertionError("a second rigctl serve on the same queue file started") from None
        lines = err.strip().splitlines()
        assert second.returncode == 1 and len(lines) == 1, (second.returncode, err)
        assert "served already" in lines[0] and f"pid {first.pid}" in lines[0] and "--queue" in lines[0], lines
        assert token_file.read_bytes() == before and up()  # the first server's token file and queue untouched
    finally:
        first.terminate()
        first.wait(60)


def test_the_queue_file_keeps_a_bounded_history(rig, tmp_path):
    queue_file = tmp_path / "queue.json"
    n_ended = _queue.MAX_ENDED_RUNS + 100 if hasattr(_queue, "MAX_ENDED_RUNS") else 600
    runs = [_queue.QueuedRun(id=f"r{i:04d}", protocol_name="p", protocol_source="", out=f"/nowhere/{i}.h5",
                             state="done", created_utc=f"2026-01-01T00:00:{i:04d}") for i in range(n_ended)]
    runs.append(_queue.QueuedRun(id="waiting", protocol_name="p", protocol_source="", out="/nowhere/w.h5"))
    queue_file.write_text(json.dumps({"format": 1, "runs": [r.to_dict() for r in runs]}))
    q = RunQueue(rig, queue_file)
    try:
        kept = [r["id"] for r in json.loads(queue_file.read_text())["runs"]]
        assert len(kept) == 501, len(kept)  # 500 ended runs and the queued one
        assert "waiting" in kept and kept[:-1] == [f"r{i:04d}" for i in range(n_ended - 500, n_ended)]
        assert [r.id for r in q.list()] == kept
    finally:
        q.close()


def test_progress_is_not_written_to_the_queue_file_at_every_event(rig, tmp_path, monkeypatch):
    """The queue file is written (and fsynced) when a run's state changes; its progress at most every
    PROGRESS_SAVE_S (here never: the bound set past the run's length), not at each progress event."""
    monkeypatch.setattr(_queue, "PROGRESS_SAVE_S", 1e9, raising=False)
    q = RunQueue(rig, tmp_path / "queue.json", data_dir=tmp_path / "data")
    writes: list[tuple[str, int]] = []
    save = q._save

    def counted():
        writes.extend((r.state, r.trials_done) for r in q.runs.values())
        save()

    q._save = counted
    try:
        run = q.submit("s.h5", toml=PROTOCOL.format(n=3))
        q.start()
        wait_for(lambda: q.get(run.id).state in ENDED)
        assert q.get(run.id).state == "done"
        states = [state for state, _ in writes]
        # one write a state: queued (submit), running, done; never one for progress alone
        assert states == ["queued", "running", "done"], writes
        assert json.loads((tmp_path / "queue.json").read_text())["runs"][0]["trials_done"] == 6
    finally:
        q.close()


def test_docs_are_served_from_rigctls_own_files_with_no_token_in_the_page(rig, tmp_path):
    from fastapi.testclient import TestClient

    from rigctl.server import create_app

    q = RunQueue(rig, tmp_path / "queue.json")
    try:
        app = create_app(q, token=TOKEN)
        client = TestClient(app, base_url="http://127.0.0.1:8765")
        r = client.get("/docs", params={"token": TOKEN})
        assert r.status_code == 200 and "text/html" in r.headers["content-type"]
        page = r.text
        assert TOKEN not in page  # the page reads it from its own address
        assert not re.search(r"https?://|//cdn|jsdelivr|unpkg", page), page  # nothing from another host
        csp = r.headers["content-security-policy"]
        assert "default-src 'none'" in csp and "connect-src 'self'" in csp and "http" not in csp
        assert r.headers["referrer-policy"] == "no-referrer"
        # the one inline script is the one the policy allows (by its hash)
        scripts = re.findall(r"<script>(.*?)</script>", page, flags=re.S)
        assert len(scripts) == 1 and "<script src" not in page
        digest = base64.b64encode(hashlib.sha256(scripts[0].encode()).digest()).decode()
        assert f"'sha256-{digest}'" in csp
        assert '"/docs/swagger-ui-bundle.js"' in scripts[0] and '"/openapi.json"' in scripts[0]
        # the Swagger UI files it fetches: rigctl's own copies, behind the token like every path
        static = Path(__file__).resolve().parents[2] / "rigctl" / "server" / "static" / "swagger-ui"
        readme = (static / "README.md").read_text()
        for name in ("swagger-ui-bundle.js", "swagger-ui.css"):
            assert client.get(f"/docs/{name}").status_code == 401
            got = client.get(f"/docs/{name}", headers=AUTH)
            assert got.status_code == 200 and got.content == (static / name).read_bytes()
            assert hashlib.sha256(got.content).hexdigest() in readme
        assert "Apache License" in (static / "LICENSE").read_text()
        assert client.get("/docs/other.js", headers=AUTH).status_code == 404
        assert client.get("/openapi.json", headers=AUTH).json()["info"]["title"] == "rigctl serve"
    finally:
        q.close()
