"""Session files: round trip, plan and status, resume rules, crash safety of the writer (kill -9 of a child)."""

from __future__ import annotations

import json
import math
import os
import signal
import textwrap
import time

import h5py
import numpy as np
import pytest

from rigctl.core import PAPER_SENSOR, PAPER_TEXTURES, SensorLayout, TextureSet
from rigctl.storage.session import (
    DEFAULT_SCHEMA_VERSION,
    PLAN_DTYPE,
    SessionError,
    SessionLocked,
    SessionWriter,
    TrialData,
    TrialStatus,
    open_session,
    plan_array,
)

from ..conftest import wait_unlocked
from .forked import PythonC


def _plan(n, textures="AB"):
    return [
        dict(trial_id=i, texture=textures[i % len(textures)], speed_mm_s=40 + 20 * (i % 5), force_g=250 * (1 + i % 3),
             duration_s=240 / (40 + 20 * (i % 5)), repeat=i // 6)
        for i in range(n)
    ]


def _trial(rng, n=2000, **attrs):
    return TrialData(
        taxels=rng.integers(0, 1024, (n, 18)),
        seq=(np.arange(n) + 65000) % 65536,
        flags=rng.integers(0, 16, n),
        host_time_s=np.arange(n) / 1000 + rng.uniform(0, 2e-3, n),
        force_g=rng.normal(500, 3, 40), force_time_s=np.linspace(0, 2, 40),
        speed_mm_s=rng.normal(120, 0.5, 50), speed_time_s=np.linspace(0, 2, 50),
        dropped_frames=3, crc_errors=1, attrs=attrs,
    )


def test_round_trip_every_array_and_attribute(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=_plan(4), protocol_source="name = 'x'\n", protocol_name="x",
                             rig_config={"mode": "sim", "seed": 3}, calibration={"taxel_min": np.arange(18),
                                                                                 "taxel_max": np.arange(18) + 500,
                                                                                 "taxel_n_trials": 7})
    trials = {1: _trial(rng, started_utc="2030-01-01T00:00:10+00:00"), 3: _trial(rng, 1500)}
    for tid, data in trials.items():
        w.write_trial(tid, data)
    with open_session(path) as s:
        assert s.attrs["schema_version"] == DEFAULT_SCHEMA_VERSION == 4 and s.attrs["kind"] == "recorded"
        assert len(s.attrs["session_id"]) == 36
        assert s.rig_config == {"mode": "sim", "seed": 3}
        assert s.protocol_source == "name = 'x'\n" and s.protocol_name == "x" and s.protocol_format == "toml"
        assert s.completed_ids() == [1, 3]
        np.testing.assert_array_equal(s.calibration["taxel_max"], np.arange(18) + 500)
        assert s.calibration["taxel_n_trials"] == 7
        assert list(s.plan["texture"]) == ["A", "B", "A", "B"]
        for tid, data in trials.items():
            back = s.trial(tid)
            for name in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s",
                         "speed_time_s"):
                np.testing.assert_array_equal(getattr(back, name), getattr(data, name), err_msg=name)
                assert getattr(back, name).dtype == getattr(data, name).dtype
            assert back.dropped_frames == 3 and back.crc_errors == 1
            assert back.attrs["texture"] == s.plan["texture"][tid]
            assert back.attrs["force_g"] == s.plan["force_g"][tid]
            assert back.attrs["n_samples"] == data.n_samples
        assert [t.n_samples for t in s.iter_trials()] == [2000, 1500]
        with pytest.raises(KeyError):
            s.trial(0)
    # plain h5py, no rigctl: the documented layout
    with h5py.File(path, "r") as f:
        tax = f["trials/000001/taxels"]
        assert tax.shape == (2000, 18) and tax.dtype == np.uint16
        assert tax.attrs["rate_hz"] == 1000 and tax.attrs["unit"] == "ADC counts"
        assert tax.attrs["starting_time"] > 0  # seconds from created_utc to the trial's start
        assert f["trials"].attrs["taxels_channels"].startswith("0-8 top (type I), 9-17 bottom (type II)")
        assert SensorLayout.from_json(f.attrs["sensor_layout"]) == PAPER_SENSOR
        assert TextureSet.from_json(f.attrs["texture_set"]) == PAPER_TEXTURES
        assert list(f["plan"]["texture"]) == [b"A", b"B", b"A", b"B"]  # variable-length UTF-8
        g = f["trials/000003"]
        assert g.attrs["texture"] == "B" and g.attrs["status"] == "complete" and g.attrs["n_samples"] == 1500
        assert g.attrs["speed_mm_s"] == np.float32(100.0) and g.attrs["dropped_frames"] == 3
        assert json.loads(f["plan"].attrs["status_enum"]) == {"pending": 0, "complete": 1, "failed": 2}
        assert list(f["plan"]["status"]) == [0, 1, 0, 1]


def test_plan_status_failed_then_rewritten_and_no_trial_twice(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=_plan(3), protocol_source="src")
    w.mark_failed(0, "DrumTimeout: force did not settle")
    with open_session(path) as s:
        assert s.failed_ids() == [0] and s.completed_ids() == []
        assert s.trial_attrs(0)["error"].startswith("DrumTimeout")
    w.write_trial(0, _trial(rng))  # a failed trial is recorded again on resume
    w.write_trial(2, _trial(rng))
    with pytest.raises(SessionError, match="already complete"):
        w.write_trial(2, _trial(rng))
    with pytest.raises(SessionError, match="not in the plan"):
        w.write_trial(9, _trial(rng))
    with pytest.raises(SessionError, match="already complete"):
        w.mark_failed(0, "late")
    # resume: same source accepted, another refused, statuses come from the file
    with pytest.raises(SessionLocked, match="another writer in this process"):  # w still holds the file
        SessionWriter.open(path, protocol_source="src")
    w.close()
    w2 = SessionWriter.open(path, protocol_source="src")
    assert w2.completed_ids() == [0, 2] and w2.pending_ids() == [1]
    w2.close()
    with pytest.raises(SessionError, match="protocol differs"):
        SessionWriter.open(path, protocol_source="src changed")
    with pytest.raises(FileExistsError):
        SessionWriter.create(path, plan=_plan(1))
    with h5py.File(path, "r") as f:
        assert "000001" not in f["trials"] and f["trials/000000"].attrs["status"] == "complete"
        assert list(f["plan"]["status"]) == [TrialStatus.COMPLETE, TrialStatus.PENDING, TrialStatus.COMPLETE]


def test_a_trial_recorded_under_another_condition_keeps_it_in_the_plan_and_the_planned_one_beside(tmp_path):
    """write_trial(labels=...): a replayed trial's source condition goes into its /plan row (what the encoder and the
    analyses label by), the planned values into ``planned_*`` trial attributes; the other rows stay; a refused write
    changes no label; only texture, speed and force can be relabelled; a resume reads the relabelled plan."""
    from rigctl.acquisition.labels import recorded_labels
    from rigctl.acquisition.protocol import PlannedTrial

    rng = np.random.default_rng(4)
    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=_plan(3), protocol_source="src")  # trial 0: A, 40 mm/s, 250 g
    w.write_trial(0, _trial(rng, 200), labels={"texture": "B", "speed_mm_s": 57.5})
    with pytest.raises(SessionError, match="already complete"):
        w.write_trial(0, _trial(rng, 200), labels={"speed_mm_s": 99.0})
    with pytest.raises(ValueError, match="duration_s"):
        w.write_trial(1, _trial(rng, 200), labels={"duration_s": 1.0})
    w.write_trial(1, _trial(rng, 200))
    w.close()
    with open_session(path) as s:
        plan = s.plan
        assert (str(plan["texture"][0]), float(plan["speed_mm_s"][0]), float(plan["force_g"][0])) == ("B", 57.5, 250.0)
        assert (str(plan["texture"][1]), float(plan["speed_mm_s"][1])) == ("B", 60.0)  # as planned
        a = s.trial_attrs(0)
        assert a["planned_texture"] == "A" and a["planned_speed_mm_s"] == 40.0 and "planned_force_g" not in a
        assert a["texture"] == "B" and a["speed_mm_s"] == 57.5
        assert "planned_speed_mm_s" not in s.trial_attrs(1)
    w2 = SessionWriter.open(path, protocol_source="src")
    assert float(w2.plan["speed_mm_s"][0]) == 57.5 and w2.pending_ids() == [2]
    w2.close()
    # the runner's rule: one source trial's finite labels that differ from the plan; none across source trials
    planned = PlannedTrial(trial_id=0, texture="A", speed_mm_s=40.0, force_g=250.0, duration_s=1.0)
    src = {"source_texture": "A", "source_speed_mm_s": 80.0, "source_force_g": float("nan")}
    assert recorded_labels(planned, src) == {"speed_mm_s": 80.0}
    assert recorded_labels(planned, {**src, "source_pieces": "[]"}) == {}
    assert recorded_labels(planned, {"started_utc": "x"}) == {}
    assert recorded_labels(planned, {"source_texture": "C", "source_speed_mm_s": 40.0, "source_force_g": 500}) == \
        {"texture": "C", "force_g": 500.0}


def test_file_is_closed_between_writes_and_script_plans_grow(tmp_path):
    rng = np.random.default_rng(3)
    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=[], protocol_source="def run(rig, session): ...", protocol_format="python")
    for k in range(3):
        tid = w.append_trial(dict(trial_id=None, texture="L", speed_mm_s=100, force_g=200 + 100 * k, duration_s=1),
                             _trial(rng, 1000))
        assert tid == k
        # another writable opening succeeds only if the writer closed the file
        with h5py.File(path, "r+") as f:
            assert f["plan"].shape == (k + 1,)
    with open_session(path) as s:
        assert list(s.plan["force_g"]) == [200, 300, 400] and s.completed_ids() == [0, 1, 2]


def test_several_events_are_logged_in_one_commit_after_those_before(tmp_path, monkeypatch):
    from rigctl.storage import journal

    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=_plan(2), protocol_source="src")
    w.log_event("latched", cause="estop")
    applied = []
    real_apply = journal.apply_journal
    monkeypatch.setattr(journal, "apply_journal", lambda *a, **k: (applied.append(1), real_apply(*a, **k)))
    out = w.log_events([("prediction", {"trial_id": k, "predicted": "AB"[k]}) for k in range(2)])
    assert len(applied) == 1 and [e["trial_id"] for e in out] == [0, 1]
    assert w.log_events([]) == [] and len(applied) == 1  # nothing to log: no commit
    w.close()
    with open_session(path) as s:
        assert [(e["kind"], e.get("predicted")) for e in s.events] == [("latched", None), ("prediction", "A"),
                                                                       ("prediction", "B")]
        assert all(e["at_utc"] for e in s.events)


def test_bad_input_is_refused_clearly(tmp_path):
    with pytest.raises(ValueError, match=r"\(n_samples, 18\)"):
        TrialData(taxels=np.zeros((10, 16)))
    with pytest.raises(ValueError, match="seq must be"):
        TrialData(taxels=np.zeros((10, 18)), seq=np.zeros(9))
    with pytest.raises(ValueError, match="same length"):
        TrialData(taxels=np.zeros((10, 18)), force_g=[1, 2], force_time_s=[0])
    with pytest.raises(ValueError, match="unique"):
        plan_array([dict(trial_id=0, texture="A", speed_mm_s=1, force_g=1, duration_s=1)] * 2)
    with pytest.raises(ValueError, match="kind"):
        SessionWriter.create(tmp_path / "k.h5", plan=[], kind="other")
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(SessionError, match="not a rigctl session"):
        open_session(tmp_path / "plain.h5")
    assert not (tmp_path / "k.h5").exists()


def test_host_rate_ignores_delivery_delays():
    rng = np.random.default_rng(4)
    n = 3000
    true_rate = 1000.4
    t = np.arange(n) / true_rate
    # frames arrive in bursts: each 5 ms chunk is stamped when received, with 0-8 ms of scheduling delay
    chunk = np.arange(n) // 5
    delay = rng.uniform(0, 8e-3, chunk.max() + 1)[chunk]
    stamp = t + delay
    d = TrialData(taxels=np.zeros((n, 18)), host_time_s=stamp)
    assert abs(d.host_rate_hz() - true_rate) < 0.5
    # dropped frames are counted by seq, so a gap does not change the rate
    keep = np.ones(n, bool)
    keep[1000:1010] = False
    d2 = TrialData(taxels=np.zeros((keep.sum(), 18)), seq=np.arange(n)[keep], host_time_s=stamp[keep])
    assert abs(d2.host_rate_hz() - true_rate) < 0.5
    assert math.isnan(TrialData(taxels=np.zeros((3, 18))).host_rate_hz())


_WRITER_CHILD = textwrap.dedent(
    """
    import sys, numpy as np
    from rigctl.storage.session import SessionWriter, TrialData
    w = SessionWriter.open(sys.argv[1])
    print("ready", flush=True)
    rng = np.random.default_rng(int(sys.argv[2]))
    for tid in w.pending_ids():
        n = 3000
        taxels = np.full((n, 18), tid % 1024) + rng.integers(0, 2, (n, 18))
        w.write_trial(tid, TrialData(taxels=taxels, force_g=[tid], force_time_s=[0.0]))
        print("wrote", tid, flush=True)
    """
)


def _check_plain(path, n_samples):
    """Read every complete trial with plain h5py (no rigctl code runs first); return the complete ids."""
    with h5py.File(path, "r") as f:
        status = f["plan"]["status"][()]
        done = np.flatnonzero(status == TrialStatus.COMPLETE)
        for tid in done:
            g = f[f"trials/{tid:06d}"]
            tax = g["taxels"][()]
            assert tax.shape == (n_samples, 18)
            assert tax.min() >= tid % 1024 and tax.max() <= tid % 1024 + 1
            assert g["force_g"][0] == tid
    return done


def test_kill_9_of_a_writer_leaves_every_finished_trial_readable(tmp_path):
    """A child writes trials back to back (the file is open most of the time); kill -9 its whole process group at
    random moments, many times: each time, plain h5py (no rigctl opening first) reads every trial marked complete
    intact, nothing finished is lost, and the next writer resumes exactly the trials that are not complete
    (docs/session-format.md, "Crash safety")."""
    from rigctl.storage import journal

    path = tmp_path / "crash.h5"
    jpath = journal.journal_path(path)
    n_trials = 3000
    SessionWriter.create(path, plan=_plan(n_trials), protocol_source="src", compression=None)
    rng = np.random.default_rng(5)
    completed_before = 0
    kills = 0
    for round_ in range(12):
        proc = PythonC(_WRITER_CHILD, str(path), str(round_), stdout=True, new_session=True)
        assert proc.stdout.readline().strip() == "ready"
        if round_ % 2:  # every other kill lands after a finished trial (on a busy machine a fixed wait may end
            assert proc.stdout.readline().startswith("wrote")  # before the first one does: nothing to judge)
        time.sleep(rng.uniform(0.05, 0.4))
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            kills += 1
        proc.wait()
        wait_unlocked(path)
        done = _check_plain(path, 3000)
        assert len(done) >= completed_before  # nothing finished was lost
        if jpath.exists():  # killed after the journal's commit mark, before its helper started: the old file
            with open_session(path) as s:  # the next rigctl opening replays it
                assert not jpath.exists()
                assert len(s.completed_ids()) in (len(done), len(done) + 1)
            done = _check_plain(path, 3000)
        completed_before = len(done)
        if completed_before == n_trials:
            break
    assert kills == 12
    assert 0 < completed_before
    w = SessionWriter.open(path, protocol_source="src")
    assert sorted(w.completed_ids() + w.pending_ids()) == list(range(n_trials))


def _wait_at_gate(proc, gate, timeout_s=120):
    """Wait until the in-place writes of a commit (the journal is committed) stop at the test gate
    (``journal._TEST_WRITE_GATE``: after the first page). The timeout only bounds a hang."""
    deadline = time.monotonic() + timeout_s
    while not gate.with_name(gate.name + ".reached").exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the writer never reached its in-place writes"
        time.sleep(0.005)


_SLOW_COMMIT = textwrap.dedent(
    """
    import sys, numpy as np
    from rigctl.storage import journal
    from rigctl.storage.session import SessionWriter, TrialData
    journal._TEST_WRITE_GATE = sys.argv[3]  # the in-place writes wait after the first one until the test opens it
    if sys.argv[2] == "in-process":  # the negative control: the in-place writes made by the writer itself
        journal.apply_journal = lambda fd, jpath, durable=True: journal._replay(fd, jpath, durable,
                                                                                gate=sys.argv[3])
    w = SessionWriter.open(sys.argv[1])
    w.write_trial(1, TrialData(taxels=np.full((500, 18), 1), force_g=[1], force_time_s=[0.0]))
    """
)


@pytest.mark.parametrize("writes", ["detached", "in-process"])
def test_a_kill_during_a_commits_in_place_writes(tmp_path, writes):
    """The in-place writes of a commit (the only time the file on disk is neither version) are made by a detached
    helper: kill -9 the writer's process group in the middle of them (held after the first page until the kill),
    and the file is the new version for plain h5py, with no journal left. The negative control makes the same
    writes in the writer's own process: the same kill then leaves them unfinished (a committed journal, a file on
    disk that is not the new version)."""
    from rigctl.storage import journal

    path = tmp_path / "slow.h5"
    jpath = journal.journal_path(path)
    w = SessionWriter.create(path, plan=_plan(3), protocol_source="src", compression=None)
    w.write_trial(0, TrialData(taxels=np.zeros((500, 18)), force_g=[0], force_time_s=[0.0]))
    w.close()  # one writer per file: the child writes next
    gate = tmp_path / "gate"
    proc = PythonC(_SLOW_COMMIT, str(path), writes, str(gate), new_session=True)
    _wait_at_gate(proc, gate)
    n_writes = len(journal._read_journal(jpath)[0])
    assert n_writes >= 3  # several pages are rewritten in place: the kill lands among them (after the first)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    gate.touch()  # a detached helper goes on
    wait_unlocked(path)
    if writes == "detached":
        assert not jpath.exists()
        assert list(_check_plain(path, 500)) == [0, 1]  # plain h5py, no rigctl opening first
    else:
        assert journal._read_journal(jpath)[0] is not None  # the writes were cut short
        torn = path.read_bytes()
        with open_session(path) as s:  # rigctl's replay repairs it
            assert s.completed_ids() == [0, 1]
        assert path.read_bytes() != torn
        assert list(_check_plain(path, 500)) == [0, 1]


def test_one_commit_helper_serves_a_writers_commits_and_a_dead_one_is_replaced(tmp_path):
    """The in-place writes of every commit of a process go through one helper (rigctl.storage.commit_helper), in its
    own session, kept between commits; a helper killed between commits costs nothing: that commit is still applied
    (no journal left, the trial readable) and the next one starts a new helper."""
    from rigctl.storage import commit_helper, journal

    def trial(tid):  # what _check_plain reads back
        return TrialData(taxels=np.full((100, 18), tid), force_g=[tid], force_time_s=[0.0])

    path = tmp_path / "s.h5"
    w = SessionWriter.create(path, plan=_plan(4), protocol_source="src")
    w.write_trial(0, trial(0))
    first = commit_helper._state["proc"]
    w.write_trial(1, trial(1))
    w.log_event("x")
    assert commit_helper._state["proc"] is first and first.poll() is None
    assert os.getsid(first.pid) == first.pid != os.getsid(0)  # its own session: a kill of ours does not reach it
    first.kill()
    first.wait()
    w.write_trial(2, trial(2))
    assert not journal.journal_path(path).exists()
    w.write_trial(3, trial(3))
    second = commit_helper._state["proc"]
    assert second is not first and second.poll() is None
    w.close()
    assert list(_check_plain(path, 100)) == [0, 1, 2, 3]
    # a forked child commits through a helper of its own; the parent's goes on serving the parent
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        ok = False
        try:
            c = SessionWriter.create(tmp_path / "child.h5", plan=_plan(1), protocol_source="src")
            c.write_trial(0, trial(0))
            ok = commit_helper._state["proc"].pid != second.pid and list(_check_plain(tmp_path / "child.h5", 100)) == [0]
        finally:
            os._exit(0 if ok else 1)
    assert os.waitpid(pid, 0)[1] == 0
    w = SessionWriter.open(path)
    w.log_event("after the fork")
    assert commit_helper._state["proc"] is second and second.poll() is None
    w.close()


def test_a_ctrl_c_that_lands_as_the_helpers_answer_is_taken_does_not_wait_forever(tmp_path):
    """A Ctrl-C that came in just before the writer's ``recv`` is raised as that call returns, with the helper's
    answer taken and lost: the writer must not wait for it forever (a loaded CI run: still waiting after 60 s). It
    sees the commit done by the journal gone, and holds the Ctrl-C (the caller raises CommittedInterrupt)."""
    import socket
    import threading

    from rigctl.storage import commit_helper

    journal_file = tmp_path / "s.h5.journal"
    journal_file.write_bytes(b"committed")
    ours, helper = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)

    class InterruptedAsItReturns:  # the writer's end: the answer is read, then the Ctrl-C is raised
        def __init__(self, sock):
            self.sock, self.calls = sock, 0

        def __getattr__(self, name):
            return getattr(self.sock, name)

        def recv(self, n):
            self.calls += 1
            data = self.sock.recv(n)
            if self.calls == 1:
                raise KeyboardInterrupt
            return data

    def serve():  # the helper: takes the commit, makes the in-place writes (the journal removed), answers
        socket.recv_fds(helper, 1024, 1)
        journal_file.unlink()
        helper.send(b"1")

    t = threading.Thread(target=serve)
    t.start()
    with open(tmp_path / "s.h5", "wb") as f:
        result = []
        waiter = threading.Thread(target=lambda: result.append(commit_helper._request(
            InterruptedAsItReturns(ours), f.fileno(), b"1\0x", 1, lambda: not journal_file.exists())), daemon=True)
        waiter.start()
        waiter.join(10.0)
    t.join(5.0)
    assert not waiter.is_alive(), "the writer still waits for an answer it already took"
    answered, interrupted = result[0]
    assert answered and isinstance(interrupted, KeyboardInterrupt)
    ours.close()
    helper.close()


def test_plan_dtype_is_the_documented_one():
    assert PLAN_DTYPE.names == ("trial_id", "texture", "speed_mm_s", "force_g", "duration_s", "profile",
                                "ramp_start_mm_s", "ramp_end_mm_s", "repeat", "status")


_DIE_IN_COMMIT = textwrap.dedent(
    """
    import os, sys, numpy as np
    from rigctl.storage import journal
    from rigctl.storage.session import SessionWriter, TrialData
    w = SessionWriter.open(sys.argv[1])
    # die like kill -9 right after the journal got its commit mark, before the in-place writes start
    journal.apply_journal = lambda *args, **kw: os._exit(9)
    w.write_trial(1, TrialData(taxels=np.full((500, 18), 7)))
    """
)


def test_a_commit_killed_after_its_journal_is_finished_on_the_next_opening(tmp_path):
    path = tmp_path / "j.h5"
    rng = np.random.default_rng(6)
    w = SessionWriter.create(path, plan=_plan(3), protocol_source="src")
    w.write_trial(0, _trial(rng))
    w.close()  # one writer per file: the child writes next
    assert PythonC(_DIE_IN_COMMIT, str(path)).wait() == 9
    jpath = path.with_name(path.name + ".journal")
    assert jpath.exists()
    with h5py.File(path, "r") as f:  # the file on disk is still the old, consistent one
        assert list(f["plan"]["status"]) == [1, 0, 0] and "000001" not in f["trials"]
    with open_session(path) as s:  # rigctl replays the committed journal
        assert s.completed_ids() == [0, 1]
        assert (s.trial(1).taxels == 7).all()
    assert not jpath.exists()
    with h5py.File(path, "r") as f:
        assert list(f["plan"]["status"]) == [1, 1, 0]


def test_overwriting_a_file_drops_the_old_files_journal(tmp_path):
    """A committed journal left by a killed writer belongs to the old file: creating a new session over it
    (``overwrite=True``) must not replay it onto the new one."""
    path = tmp_path / "o.h5"
    SessionWriter.create(path, plan=_plan(3), protocol_source="old")
    assert PythonC(_DIE_IN_COMMIT, str(path)).wait() == 9
    assert path.with_name(path.name + ".journal").exists()
    w = SessionWriter.create(path, plan=_plan(2), protocol_source="new", overwrite=True)
    w.write_trial(0, TrialData(taxels=np.full((100, 18), 3)))
    with open_session(path) as s:
        assert s.protocol_source == "new" and s.completed_ids() == [0] and len(s.plan) == 2
        assert (s.trial(0).taxels == 3).all()


_CTRL_C_IN_COMMIT = textwrap.dedent(
    """
    import sys, numpy as np
    from rigctl.storage import journal
    from rigctl.storage.session import SessionWriter, TrialData
    journal._TEST_WRITE_GATE = sys.argv[2]  # the in-place writes wait after the first one until the test opens it
    w = SessionWriter.open(sys.argv[1])
    try:
        w.write_trial(1, TrialData(taxels=np.full((500, 18), 1), force_g=[1], force_time_s=[0.0]))
        print("no interrupt")
    except KeyboardInterrupt as exc:
        print(type(exc).__name__, w.completed_ids(), flush=True)
    """
)


def test_ctrl_c_during_a_commit_finishes_it_first(tmp_path):
    """SIGINT while the in-place writes run: the writer waits for them, then raises CommittedInterrupt (a
    KeyboardInterrupt), and its view of the plan agrees with the file (the trial is complete in both)."""
    from rigctl.storage import journal

    path = tmp_path / "c.h5"
    jpath = journal.journal_path(path)
    w = SessionWriter.create(path, plan=_plan(3), protocol_source="src", compression=None)
    w.write_trial(0, TrialData(taxels=np.zeros((500, 18)), force_g=[0], force_time_s=[0.0]))
    w.close()  # one writer per file: the child writes next
    gate = tmp_path / "gate"
    proc = PythonC(_CTRL_C_IN_COMMIT, str(path), str(gate), stdout=True)
    _wait_at_gate(proc, gate)  # the journal is committed and the in-place writes have begun
    proc.send_signal(signal.SIGINT)
    gate.touch()
    assert proc.wait(60) == 0
    assert proc.stdout.read().strip() == "CommittedInterrupt [0, 1]"
    assert not jpath.exists()
    assert list(_check_plain(path, 500)) == [0, 1]
