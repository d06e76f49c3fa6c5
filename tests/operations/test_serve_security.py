"""``rigctl serve`` trusts nobody by default (issue 36): the token on every endpoint (the OpenAPI page and schema
included), the Host header, cross-origin and form posts, the data folder's name rules, body size limits, the one
rule for replacing files, a stopped run resumed through the API, the operator's acknowledgement; and a property
test sending random requests to every endpoint. All in this process (FastAPI's test client, the in-process rig)."""

from __future__ import annotations

import importlib.util
import json
import os
import time

import h5py
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.cli import main
from rigctl.operations import RigSource, RunQueue, open_control
from rigctl.server.tokens import TokenError

if importlib.util.find_spec("fastapi") is None:  # (not imported here: the collection of every test worker skips it)
    pytest.skip("fastapi (the serve extra) is not installed", allow_module_level=True)

TOKEN = "sec-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BASE = "http://127.0.0.1:8765"
TINY = ('name = "sec"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
        'trials_per_condition = {n}\nduration_s = 0.3\n[settle]\nsettle_time_ms = 50\n')


def _wait(pred, timeout_s=120.0):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        value = pred()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError("timed out")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    from rigctl.server import create_app

    root = tmp_path_factory.mktemp("serve-sec")
    control = open_control(RigSource("inprocess"), seed=3, host_config_path=root / "rig.json")
    q = RunQueue(control, root / "state" / "queue.json", data_dir=root / "data").start()
    app = create_app(q, token=TOKEN)
    try:
        yield q, app, root
    finally:
        q.close()
        control.close()


def _client(app, **headers):
    from fastapi.testclient import TestClient

    return TestClient(app, base_url=BASE, headers=headers)


def _endpoints(app):
    """(method, path) of every route, path parameters filled with an unknown id; the OpenAPI page and schema."""
    from fastapi.routing import APIRoute

    out = [("GET", "/docs"), ("GET", "/openapi.json")]
    for route in app.routes:
        if isinstance(route, APIRoute):
            out += [(m, route.path.replace("{run_id}", "nope")) for m in sorted(route.methods)]
    return out


def test_no_token_is_401_on_every_endpoint_docs_included(rig):
    q, app, _ = rig
    client = _client(app)
    eps = _endpoints(app)
    assert {("POST", "/stop"), ("POST", "/ack"), ("POST", "/runs/nope/resume"), ("GET", "/events")} <= set(eps)
    for method, path in eps:
        for extra in ({}, {"params": {"token": " "}}, {"params": {"token": ""}},
                      {"headers": {"Authorization": "Bearer " + TOKEN[:-1]}}, {"headers": {"Authorization": TOKEN}}):
            r = client.request(method, path, json={}, **extra)
            assert r.status_code == 401, (method, path, extra, r.status_code)
    assert _client(app, **AUTH).get("/docs").status_code == 200
    assert "/runs/{run_id}/resume" in _client(app).get("/openapi.json", params={"token": TOKEN}).json()["paths"]
    assert not q.held


def test_a_foreign_host_header_is_refused(rig):
    _, app, _ = rig
    for method, path in _endpoints(app):
        for host in ("evil.example", "evil.example:8765", "127.0.0.1.nip.io", ""):
            r = _client(app, Host=host, **AUTH).request(method, path, json={})
            assert r.status_code == 400, (method, path, host, r.status_code)
    for host in ("127.0.0.1:8765", "localhost:8765", "localhost"):
        assert _client(app, Host=host, **AUTH).get("/status").status_code == 200


def test_cross_origin_and_form_posts_to_every_state_changing_endpoint_are_refused(rig):
    q, app, _ = rig
    posts = [p for m, p in _endpoints(app) if m == "POST"]
    assert len(posts) >= 7
    form = {"Content-Type": "application/x-www-form-urlencoded"}
    for path in posts:
        for headers in ({"Origin": "http://evil.example", **form}, {"Origin": "null", **form},
                        {"Origin": "http://evil.example", "Content-Type": "text/plain"},
                        {"Origin": "http://evil.example", "Content-Type": "application/json"}):
            # even a page that knew the token (it cannot): ?token= in the URL, as a form's action could carry
            r = _client(app).post(path, params={"token": TOKEN}, headers=headers,
                                  content=b"protocol=quick_check&out=x.h5&reason=x")
            assert r.status_code == 403 and "cross-origin" in r.json()["detail"], (path, headers, r.text)
            assert "access-control-allow-origin" not in r.headers
        for ctype in ("application/x-www-form-urlencoded", "multipart/form-data; boundary=x", "text/plain", None):
            r = _client(app, **AUTH).post(path, content=b"{}", headers={"Content-Type": ctype} if ctype else {})
            assert r.status_code == 415, (path, ctype, r.status_code)
    assert not q.held and not q.list()  # nothing happened
    same = _client(app, Origin=BASE, **AUTH).post("/queue/release", json={})
    assert same.status_code == 200


def test_blank_or_short_tokens_are_refused(rig, tmp_path, monkeypatch):
    from rigctl.server import create_app

    q, _, _ = rig
    for bad in ("", " ", " " * 20, "short", "x" * 15, "sixteen chars ok"):
        with pytest.raises(TokenError):
            create_app(q, token=bad)
    monkeypatch.delenv("RIGCTL_SERVE_TOKEN", raising=False)
    for bad in (" ", "abc"):
        r = CliRunner().invoke(main, ["serve", "--rig", "inprocess", "--token", bad, "--queue", str(tmp_path / "q.json")])
        assert r.exit_code == 2 and "--token" in r.output and not (tmp_path / "q.json").exists(), r.output


def test_out_is_a_name_inside_the_data_folder(rig):
    q, app, root = rig
    client = _client(app, **AUTH)
    victim = root / "victim.txt"
    victim.write_text("keep me")
    (q.data_dir / "out-link").symlink_to(root, target_is_directory=True)
    cases = {str(victim): "absolute", "/dev/null": "absolute", "../victim.txt": "'..'", "a/../../victim.txt": "'..'",
             "a\x00b.h5": "control characters", "": "file name", "out-link/victim.txt": "outside the data folder",
             "x" * 300 + ".h5": "too long", "~/s.h5": "absolute", str(q.path): "absolute"}
    for out, rule in cases.items():
        r = client.post("/runs", json={"protocol": "quick_check", "out": out, "overwrite": True})
        assert r.status_code == 422 and rule in r.json()["detail"], (out, r.status_code, r.text)
    assert victim.read_text() == "keep me" and not q.list()
    r = client.post("/runs", content=b'{"toml": "' + b"#" * 1_100_000 + b'", "out": "big.h5"}',
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 413
    r = client.post("/runs", content=b"x" * 2_000_000, headers={"Content-Type": "application/json",
                                                               "Content-Length": "2000000"})
    assert r.status_code == 413
    assert not q.path.exists() or q.path.stat().st_size < 10_000


def test_overwrite_replaces_only_a_session(rig):
    q, app, _ = rig
    client = _client(app, **AUTH)
    notes = q.data_dir / "notes.h5"
    notes.write_text("a lab notebook, not a session")
    other = q.data_dir / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = [1, 2, 3]
    before = {p: p.read_bytes() for p in (notes, other)}
    for name in ("notes.h5", "other.h5"):
        r = client.post("/runs", json={"toml": TINY.format(n=1), "out": name, "overwrite": True})
        assert r.status_code == 422 and "not a rigctl session file" in r.json()["detail"], r.text
    r = client.post("/runs", json={"toml": TINY.format(n=1), "out": "notes.h5"})
    assert r.status_code == 409 and "exists" in r.json()["detail"]
    assert {p: p.read_bytes() for p in before} == before and not q.list()


def test_a_stopped_run_resumes_through_the_api_without_a_trial_lost_or_twice(rig):
    from rigctl.storage.session import open_session

    q, app, _ = rig
    client = _client(app, **AUTH)
    rid = client.post("/runs", json={"toml": TINY.format(n=6), "out": "resume.h5"}).json()["id"]
    _wait(lambda: client.get(f"/runs/{rid}").json()["trials_done"] >= 2)
    assert client.post("/stop", json={}).status_code == 200
    # STOP pauses the run (Queue.stop: the trial in progress discarded, recorded again at its resume); "pausing" while
    # the rig stops. (On the model rig's old Python copy of the controller this run ended "stopped" 3 s after the
    # STOP instead, by a path not traced; with controller.c it pauses, as Queue.stop says.)
    run = _wait(lambda: (r := client.get(f"/runs/{rid}").json())["state"] not in ("running", "aborting", "pausing")
                and r)
    assert run["state"] == "paused" and 2 <= run["trials_done"] < 12, run
    with open_session(q.data_dir / "resume.h5") as s:
        before = {t: s.trial_attrs(t)["started_utc"] for t in s.completed_ids()}
    assert client.post(f"/runs/{rid}/resume", json={}).json()["state"] == "running"  # the one start after STOP
    run = _wait(lambda: (r := client.get(f"/runs/{rid}").json())["state"] not in ("queued", "running") and r)
    assert run["state"] == "done" and run["trials_done"] == run["trials_total"] == 12, run
    with open_session(q.data_dir / "resume.h5") as s:
        done = s.completed_ids()
        index = s.recording_index()
        assert sorted(done) == list(range(12)) and len(index) == 12  # none lost, none recorded twice
        assert {t: s.trial_attrs(t)["started_utc"] for t in before} == before  # the first ones kept as they were
    assert client.post("/runs/nope/resume", json={}).status_code == 404


def test_ack_reaches_the_rig_control_with_reason_and_who(rig, monkeypatch):
    q, app, _ = rig
    client = _client(app, **AUTH)
    assert client.get("/status").json()["rig"]["latch"] is None
    r = client.post("/ack", json={"reason": "nothing to clear"})  # the real RigControl: nothing latched
    assert r.status_code == 409 and r.json()["detail"].startswith("acknowledgement refused"), r.text
    calls = []
    monkeypatch.setattr(q.control, "acknowledge", lambda reason, by: calls.append((reason, by)) or "cleared",
                        raising=False)
    client = _client(app, **AUTH)
    r = client.post("/ack", json={"reason": "e-stop released after checking the drum", "by": "ana"})
    assert r.status_code == 200 and r.json()["by"] == "ana", r.text
    assert client.post("/ack", json={"reason": "checked"}).json()["by"].startswith("rigctl serve client")
    assert client.post("/ack", json={}).status_code == 422 and client.post("/ack", json={"reason": ""}).status_code == 422
    assert calls == [("e-stop released after checking the drum", "ana"), ("checked", calls[1][1])]


# ------------------------------------------------------------------------------------------- the property test
_TEXT = st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=40)
_OUT = st.one_of(st.sampled_from(["p.h5", "sub/p.h5", "../victim.txt", "notes.h5", "link.h5", "/tmp/x.h5", "a\x00.h5",
                                  "..", ".", "", "victim-dir/../notes.h5", "queue.json"]),
                 st.text(max_size=30))
_VALUE = st.one_of(st.none(), st.booleans(), st.integers(), _TEXT, _OUT, st.lists(st.integers(), max_size=3))
_BODY = st.one_of(
    st.binary(max_size=200),
    st.fixed_dictionaries({}, optional={"protocol": st.one_of(st.sampled_from(["quick_check", "nope"]), _VALUE),
                                        "toml": st.one_of(st.just(TINY.format(n=1)), _VALUE), "out": _OUT,
                                        "overwrite": st.one_of(st.booleans(), _VALUE),
                                        "reason": _VALUE, "by": _VALUE}).map(lambda d: json.dumps(d).encode()))


@pytest.fixture
def prop_rig(tmp_path):
    from rigctl.server import create_app

    control = open_control(RigSource("inprocess"), seed=4, host_config_path=tmp_path / "rig.json")
    q = RunQueue(control, tmp_path / "state" / "queue.json", data_dir=tmp_path / "data").start()
    q.end_streams()  # /events answers and ends at once (the test client would read an open feed forever)
    (tmp_path / "victim.txt").write_text("not yours")
    (q.data_dir / "notes.h5").write_text("not a session")
    (q.data_dir / "link.h5").symlink_to(tmp_path / "victim.txt")
    try:
        yield q, create_app(q, token=TOKEN), tmp_path
    finally:
        q.close()
        control.close()


def _files(root):
    return {os.path.relpath(os.path.join(d, f), root) for d, _, fs in os.walk(root) for f in fs}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                HealthCheck.too_slow])
@given(method=st.sampled_from(["GET", "POST", "POST", "POST", "PUT", "DELETE", "OPTIONS", "PATCH", "HEAD"]),
       path=st.one_of(st.sampled_from(["/status", "/runs", "/runs/{id}", "/runs/{id}/pause", "/runs/{id}/resume",
                                       "/runs/{id}/abort", "/stop", "/queue/release", "/ack", "/events", "/docs",
                                       "/openapi.json"]),
                      st.text(alphabet="abcxyz/._-%09?=&", max_size=30).map(lambda s: "/" + s)),
       run_id=st.one_of(st.just("known"), _TEXT.filter(lambda s: "/" not in s and "?" not in s and "#" not in s)),
       token=st.sampled_from([TOKEN, TOKEN, TOKEN, None, "", " ", TOKEN + "x"]),
       host=st.sampled_from(["127.0.0.1:8765", "127.0.0.1:8765", "localhost", "evil.example", "[::1]", "a b"]),
       origin=st.sampled_from([None, None, None, BASE, "http://evil.example", "null", "\x7f"]),
       ctype=st.sampled_from(["application/json", "application/json", "application/json; charset=utf-8",
                              "application/x-www-form-urlencoded", "text/plain", None]),
       body=_BODY)
def test_random_requests_to_every_endpoint(prop_rig, method, path, run_id, token, host, origin, ctype, body):
    q, app, root = prop_rig
    victim, notes = root / "victim.txt", q.data_dir / "notes.h5"
    outside_before = {f for f in _files(root) if not f.startswith(("data", "state"))}
    known = [r.id for r in q.list()]
    path = path.replace("{id}", known[0] if run_id == "known" and known else run_id)
    headers = {k: v for k, v in (("Host", host), ("Origin", origin), ("Content-Type", ctype)) if v is not None}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    client = _client(app)
    try:
        r = client.request(method, path, headers=headers, content=body)
    except (UnicodeEncodeError, ValueError) as exc:  # httpx refuses to send it: nothing reached the server
        assert "header" in str(exc).lower() or "url" in str(exc).lower() or isinstance(exc, UnicodeEncodeError), exc
        return
    assert r.status_code < 500, (method, path, headers, body, r.status_code, r.text)
    assert victim.read_text() == "not yours" and notes.read_text() == "not a session"
    assert (q.data_dir / "link.h5").is_symlink()
    outside_after = {f for f in _files(root) if not f.startswith(("data", "state"))}
    assert outside_after == outside_before, outside_after ^ outside_before
