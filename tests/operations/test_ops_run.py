"""Run control of a protocol (rigctl.operations.ProtocolRun) on the in-process rig: pause between trials with the
sensor released and resume, abort with finished trials kept, then resume the file to completion."""

from __future__ import annotations

import threading

import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.core.drum import DrumState
from rigctl.operations import ProtocolRun, RigSource, open_control
from rigctl.storage.provenance import read_provenance
from rigctl.storage.session import open_session

PROTO = ('name = "ops"\ntextures = ["A"]\nspeeds_mm_s = [80]\nforces_g = [300]\ntrials_per_condition = {n}\n'
         'duration_s = 0.2\nretries = 0\n[settle]\nsettle_time_ms = 50\n')


@pytest.fixture
def control(tmp_path):
    with open_control(RigSource("inprocess"), seed=4, host_config_path=tmp_path / "rig.json") as c:
        yield c


def test_pause_releases_the_sensor_and_resume_finishes_the_plan(control, tmp_path):
    paused = threading.Event()
    seen = []

    def on_trial(ev):
        seen.append(ev.kind)
        if ev.kind == "complete" and ev.index == 0:
            run.pause()  # asked during the run: takes effect after this trial
        if ev.kind == "paused":
            states.append(run.state)
            status.append(control.status())
            paused.set()

    states, status = [], []
    run = ProtocolRun(control, parse_protocol(PROTO.format(n=3)), tmp_path / "s.h5", on_trial=on_trial)
    assert run.state == "ready"
    run.start()
    assert paused.wait(60), seen
    assert states == ["paused"] and status[0].state == DrumState.IDLE  # between trials, nothing pressed
    run.resume()
    summary = run.wait(120)
    assert summary is not None and summary.ok and summary.recorded == 3
    assert run.state == "done" and "resumed" in seen
    assert seen.index("paused") > seen.index("complete")


def test_abort_keeps_finished_trials_and_the_file_resumes(control, tmp_path):
    out = tmp_path / "s.h5"

    def on_trial(ev):
        if ev.kind == "complete" and ev.index == 1:
            run.abort()

    run = ProtocolRun(control, parse_protocol(PROTO.format(n=5)), out, on_trial=on_trial)
    summary = run.run()  # in this thread, as the CLI does
    assert summary.stopped and summary.recorded == 2 and not summary.ok
    with open_session(out) as s:
        assert len(s.completed_ids()) == 2
    again = ProtocolRun(control, parse_protocol(PROTO.format(n=5)), out, resume=True).run()
    assert again.ok and again.recorded == 3 and again.complete == 5
    # the file names the run that recorded trials 2-4 beside the one that created it (issue 27: a resumed session
    # kept only its creator's provenance)
    prov = read_provenance(out)
    (resumed,) = prov["resumed"]
    assert resumed["complete_trials_before"] == 2 and resumed["resumed_utc"]
    assert resumed["provenance"]["provenance_id"] != prov["provenance_id"]
    assert resumed["provenance"]["protocol"]["name"] == "ops" and "firmware" in resumed["provenance"]
    with pytest.raises(RuntimeError):
        run.run()  # a run is run once
    with pytest.raises(FileExistsError):
        ProtocolRun(control, parse_protocol(PROTO.format(n=5)), out).run()  # never over a user's file
