"""The runner and the calibration helpers: Ctrl-C, stop and pause events, failed trials and their resume, ramps,
taxel calibration, a reader holding the file, on the in-process rig (rigctl.rigs.open_rig("inprocess"): the
controller logic and the physical model on a simulated clock, no ptys). On the simulated rig on real ptys (pymodbus,
pyserial), unpaced on the rig's one clock: a watchdog trip before a plate change (the host's silence in real time,
which the heartbeat grants the rig no faster than the wall clock; the same plate's trip, found by the next press, on
the in-process rig with host-silence injected) and the load-cell calibration against the virtual Mega (the Modbus
stack's answers and the calibration's waits on the rig's clock)."""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import h5py
import numpy as np
import pytest

from rigctl.acquisition import calibration, rig as rig_module
from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core.faults import FaultSpec
from rigctl.devices.wire import DrumState, HoldingRegister
from rigctl.rigs import WATCHDOG_MS, open_rig
from rigctl.simulation.model import MechanicsConfig, RigConfig
from rigctl.storage.session import open_session

TRUE_COUNTS_PER_G = 380.0  # the simulated load cell differs from the controller's default scale (420 counts/g)


def _proto(n_per=3, textures='"A", "B"', settle="settle_time_ms = 50", duration=0.3, extra=""):
    return parse_protocol(
        f'name = "t"\ntextures = [{textures}]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
        f"trials_per_condition = {n_per}\nduration_s = {duration}\n{extra}\n[settle]\n{settle}\n"
    )


@pytest.fixture(scope="module")
def config_file(tmp_path_factory):
    return tmp_path_factory.mktemp("cfg") / "rig.json"


@pytest.fixture(scope="module")
def rig(config_file):
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=TRUE_COUNTS_PER_G))
    with open_rig("inprocess", config=cfg, seed=3, host_config_path=config_file) as r:
        yield r


@pytest.fixture(scope="module")
def pty_rig(tmp_path_factory):
    """The simulated rig on real ptys, unpaced: it runs as far as the host's waits and signs of life grant on its one
    clock (rig.drum.clock; the virtual Mega's watchdog judges it), so a starved host pauses it."""
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=TRUE_COUNTS_PER_G))
    with open_rig("sim", config=cfg, seed=3, host_config_path=tmp_path_factory.mktemp("cfg") / "rig.json",
                  paced=False) as r:
        yield r


def _state(rig) -> DrumState:
    return rig.drum.read_status().state


def test_ctrl_c_mid_trial_is_a_clean_stop_then_resume(rig, tmp_path, monkeypatch):
    out = tmp_path / "c.h5"
    events = []
    fired = []
    wait_capture = rig.stream.wait_capture

    def on_trial(ev):
        events.append((ev.kind, ev.planned.trial_id if ev.planned else None))

    def ctrl_c_while_trial_2_captures(*args, **kw):
        # a real SIGINT to this process, sent while trial 2's capture runs (drum turning, force on): at that point
        # whatever the machine's load (a timer could land after the trial, or during its write)
        if events and events[-1] == ("start", 2) and not fired:
            fired.append(rig.drum.read_status().state)
            os.kill(os.getpid(), signal.SIGINT)
        return wait_capture(*args, **kw)

    monkeypatch.setattr(rig.stream, "wait_capture", ctrl_c_while_trial_2_captures)
    summary = run_protocol(_proto(2), out, rig=rig, progress=False, on_trial=on_trial)
    monkeypatch.undo()
    assert fired == [DrumState.RUNNING]
    assert summary.stopped and summary.recorded == 2 and summary.complete == 2
    assert ("complete", 2) not in events
    rig.drum.wait_state([DrumState.IDLE], timeout_s=15)  # STOP was sent: the rig backs off to IDLE
    with h5py.File(out, "r") as f:
        assert list(f["plan"]["status"]) == [1, 1, 0, 0] and sorted(f["trials"]) == ["000000", "000001"]
    events.clear()
    summary = run_protocol(_proto(2), out, rig=rig, progress=False, resume=True, on_trial=on_trial)
    assert summary.complete == 4 and summary.recorded == 2 and not summary.stopped
    assert [e[1] for e in events if e[0] == "complete"] == [2, 3]


def test_stop_event_and_pause_event(rig, tmp_path):
    out = tmp_path / "p.h5"
    stop, pause = threading.Event(), threading.Event()
    seen = []

    def on_trial(ev):
        seen.append(ev.kind)
        if ev.kind == "complete" and ev.index == 0:
            pause.set()
        if ev.kind == "paused":
            seen.append(_state(rig))  # paused with the sensor released: no force, no watchdog to trip
            # resumed 0.5 s after the pause was taken (a timer started when pause was set could run out first on a
            # loaded machine, before the runner looked: no pause at all)
            threading.Timer(0.5, pause.clear).start()
        if ev.kind == "complete" and ev.index == 2:
            stop.set()

    summary = run_protocol(_proto(4, textures='"A"'), out, rig=rig, progress=False, stop_event=stop, pause_event=pause,
                           on_trial=on_trial)
    assert "paused" in seen and "resumed" in seen
    assert seen[seen.index("paused") + 1] == DrumState.IDLE
    assert seen.index("resumed") > seen.index("paused")
    assert summary.stopped and summary.complete == 3 and seen.count("complete") == 3


def test_failed_trials_are_marked_and_resumed(rig, tmp_path, monkeypatch):
    monkeypatch.setattr(rig_module, "CAPTURE_STALL_S", 0.5)
    out = tmp_path / "f.h5"
    failures = []
    record = rig.record_trial

    def record_and_replug(planned, **kw):
        try:
            return record(planned, **kw)
        except Exception:
            rig.stream.start()  # the board streams again as the trial fails
            raise

    def on_trial(ev):
        if ev.kind == "start" and ev.planned.trial_id == 1:
            rig.stream.stop()  # the taxel board goes silent during trial 1
        if ev.kind == "failed":
            failures.append(ev.error)

    monkeypatch.setattr(rig, "record_trial", record_and_replug)
    # no retries: the failed trial is marked failed and left for the resume
    proto = _proto(3, textures='"A"', extra="retries = 0")
    summary = run_protocol(proto, out, rig=rig, progress=False, on_trial=on_trial)
    assert summary.failed == 1 and summary.complete == 2 and not summary.stopped
    assert "CaptureError" in failures[0] and "trial 1" in failures[0]
    with open_session(out) as s:
        assert s.failed_ids() == [1] and "CaptureError" in s.trial_attrs(1)["error"]
    summary = run_protocol(proto, out, rig=rig, progress=False, resume=True)
    assert summary.recorded == 1 and summary.complete == 3
    with open_session(out) as s:
        assert s.completed_ids() == [0, 1, 2] and s.trial(1).n_samples == 300


def test_on_failure_stop(rig, tmp_path):
    out = tmp_path / "t.h5"
    proto = _proto(2, settle="force_timeout_s = 0.02")  # the force cannot settle that fast
    summary = run_protocol(proto, out, rig=rig, progress=False, on_failure="stop")
    assert summary.failed == 1 and summary.complete == 0
    assert "DrumTimeout" in summary.failures[0]
    with h5py.File(out, "r") as f:
        assert list(f["plan"]["status"]) == [2, 0, 0, 0]
    assert _state(rig) in (DrumState.IDLE, DrumState.HOMING)


def test_ramp_trial_follows_the_profile(rig, tmp_path):
    proto = parse_protocol(
        'name = "ramp"\ntextures = ["L"]\nforces_g = [500]\ntravel_mm = 80\n'
        '[[profiles]]\nname = "slow-to-fast"\nkind = "ramp"\nstart_mm_s = 40\nend_mm_s = 120\n'
    )
    out = tmp_path / "r.h5"
    summary = run_protocol(proto, out, rig=rig, progress=False)
    assert summary.complete == 1
    with open_session(out) as s:
        t = s.trial(0)
        assert t.n_samples == 1000 and s.plan["profile"][0] == "slow-to-fast"
        q = len(t.speed_mm_s) // 4
        early, late = t.speed_mm_s[:q].mean(), t.speed_mm_s[-q:].mean()
        assert early < 60 and late > 100, (early, late)
        assert abs(t.speed_mm_s[0] - 40) < 5  # the ramp starts at speed, not from rest
        assert np.all(np.diff(t.speed_time_s) > 0)


def test_taxel_normalisation_goes_into_the_config_and_the_next_session(rig, tmp_path, config_file):
    calib = tmp_path / "calib.h5"
    run_protocol(_proto(1, textures='"A", "L"', duration=0.5), calib, rig=rig, progress=False)
    norm = calibration.taxel_normalisation_from_session(calib, store=True, config_file=config_file)
    with h5py.File(calib, "r") as f:
        allx = np.concatenate([g["taxels"][()] for g in f["trials"].values()])
    np.testing.assert_array_equal(norm.taxel_min, allx.min(0))
    np.testing.assert_array_equal(norm.taxel_max, allx.max(0))
    scaled = norm.apply(allx)
    assert scaled.dtype == np.float32 and scaled.min() == 0.0 and scaled.max() == 1.0
    rig.reload_host_config()
    out = tmp_path / "next.h5"
    run_protocol(_proto(1, textures='"L"'), out, rig=rig, progress=False)
    with open_session(out) as s:
        np.testing.assert_array_equal(s.calibration["taxel_max"], norm.taxel_max)
        assert s.calibration["taxel_n_trials"] == 2
        assert s.rig_config["host_config"]["taxel_normalisation"]["taxel_max"] == norm.taxel_max.tolist()


def test_a_reader_holding_the_file_delays_a_write_but_loses_nothing(rig, tmp_path):
    out = tmp_path / "busy.h5"
    released = []

    def hold_until_released(f):
        # keep the file open until the runner, unable to write trial 1, has released the rig (or 15 s passed)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            if rig.drum.read_status().state == DrumState.IDLE:
                released.append(time.monotonic())
                break
            time.sleep(0.05)
        time.sleep(0.3)
        f.close()

    def on_trial(ev):
        if ev.kind == "complete" and ev.index == 0:
            # a reader (plain h5py: it holds HDF5's file lock) opens the file before trial 1 is written
            f = h5py.File(out, "r")
            threading.Thread(target=hold_until_released, args=(f,), daemon=True).start()

    summary = run_protocol(_proto(3, textures='"A"'), out, rig=rig, progress=False, on_trial=on_trial)
    assert released, "the runner never released the rig while the file was held"
    assert summary.complete == 3 and summary.failed == 0 and not summary.stopped
    with open_session(out) as s:
        assert [s.trial(i).n_samples for i in s.completed_ids()] == [300, 300, 300]


def test_loadcell_calibration_against_the_virtual_mega(pty_rig, tmp_path):
    rig, config_file = pty_rig, tmp_path / "rig.json"
    place, remove = calibration.simulated_mass(rig)
    rig.home_if_pending()  # the start: opening moved nothing, the calibration needs the actuator at home
    rig.drum.set_loadcell_scale(400.0)  # a wrong scale to start from
    result = calibration.calibrate_loadcell(rig.drum, 500.0, place_mass=place, remove_mass=remove,
                                            config_file=config_file)
    assert abs(result.counts_per_g - TRUE_COUNTS_PER_G) / TRUE_COUNTS_PER_G < 0.01
    assert rig.drum.read_holding(HoldingRegister.LOADCELL_SCALE_X100) == result.scale_x100
    assert abs(result.check_force_g - 500.0) < 5  # with the new scale the controller reads the mass right
    clock = rig.drum.clock  # the rig's one clock (unpaced: its waits let it run on)
    t0 = clock.now()  # mass removed: the controller reads ~0 g at its next load-cell sample (bound: a hang)
    while abs(force := rig.drum.read_status().force_g) >= 5 and clock.now() - t0 < 10:
        clock.sleep(0.05)
    assert abs(force) < 5
    stored = json.loads(config_file.read_text())["loadcell"]
    assert stored["scale_x100"] == result.scale_x100
    with pytest.raises(ValueError):
        calibration.calibrate_loadcell(rig.drum, 0, place_mass=place)


def test_a_watchdog_trip_before_the_next_press_latches_until_acknowledged(rig, tmp_path):
    """The same plate: the next press finds the WATCHDOG latched by the host's silence after trial 0 (in-process: a
    ``host-silence`` of 1.5 s on the simulated clock; the real-time trip is the plate-change case below and the
    conformance suite's). The run ends, resumable; the acknowledgement (logged) goes on."""
    out = tmp_path / "wd.h5"

    def on_trial(ev):
        if ev.kind == "complete" and ev.index == 0:
            assert rig.drum.read_holding(HoldingRegister.WATCHDOG_MS) == 1000  # the controller's default (1 s)
            rig.backend.inject_faults([FaultSpec("host-silence", 0.0, 1.5)])
            for _ in range(16):  # a slow callback: the host is silent with the force engaged, 1.6 s
                rig.drum.clock.sleep(0.1)
            assert rig.drum.read_status().state == DrumState.FAULT

    proto = _proto(2, textures='"A"')
    summary = run_protocol(proto, out, rig=rig, progress=False, on_trial=on_trial)
    assert summary.complete == 1 and summary.stopped and "watchdog" in summary.latched, summary.lines()
    rig.acknowledge("slow callback", by="pytest")
    summary = run_protocol(proto, out, rig=rig, progress=False, resume=True)
    assert summary.complete == 2 and summary.failed == 0, summary.failures


# wall: a trial callback busy for 1.5 s of wall time (the heartbeat grants the rig that time, as on a bench)
@pytest.mark.realtime
def test_a_watchdog_trip_before_a_plate_change_latches_until_acknowledged(pty_rig, tmp_path):
    # the host silent in real time after trial 0: the release before mounting B finds the latched WATCHDOG (the
    # same plate's next press finds it too: the in-process test above). The watchdog is a latched fault
    # (docs/safety.md): the run ends, resumable; the acknowledgement (logged) goes on
    out = tmp_path / "wd.h5"

    def on_trial(ev):
        if ev.kind == "complete" and ev.index == 0:
            # the controller's default watchdog (1 s), not the simulated rig's longer one (rigs.WATCHDOG_MS), from
            # here on only (a loaded machine's host may pause for 1 s inside trial 0 too: a latch there, not here)
            pty_rig.drum.write_holding(HoldingRegister.WATCHDOG_MS, 1000)
            time.sleep(1.5)  # a slow callback: the host is silent with the force engaged, the watchdog trips
            assert pty_rig.drum.read_status().state == DrumState.FAULT

    proto = _proto(1, textures='"A", "B"')
    try:
        summary = run_protocol(proto, out, rig=pty_rig, progress=False, on_trial=on_trial)
    finally:
        pty_rig.drum.write_holding(HoldingRegister.WATCHDOG_MS, WATCHDOG_MS["sim"])
    assert summary.complete == 1 and summary.stopped and "watchdog" in summary.latched, summary.lines()
    pty_rig.acknowledge("slow callback", by="pytest")
    summary = run_protocol(proto, out, rig=pty_rig, progress=False, resume=True)
    assert summary.complete == 2 and summary.failed == 0, summary.failures


def test_a_calibration_run_of_noise_is_refused_and_the_previous_one_kept(tmp_path):
    """check_taxel_span refuses a run whose taxels span noise (the idle drum: ~16 of 1023 counts), reports single
    dead taxels without refusing; store / undo / reset keep the replaced normalisation for going back."""
    from rigctl.acquisition.rigconfig import CalibrationError

    rng = np.random.default_rng(0)
    idle = 300 + rng.integers(0, 17, (2000, 18))
    with pytest.raises(CalibrationError, match="spans only"):
        calibration.check_taxel_span(calibration.taxel_normalisation([idle]), 1023)
    run = 50 + rng.integers(0, 700, (2000, 18))
    run[:, 4] = idle[:, 4]  # one taxel that barely moved
    good = calibration.taxel_normalisation([run], source="run")
    assert calibration.check_taxel_span(good, 1023) == [4]
    cfg = tmp_path / "rig.json"
    first = calibration.TaxelNormalisation(np.zeros(18), np.full(18, 900.0), 1, "first")
    calibration.store_taxel_normalisation(first, cfg)
    calibration.store_taxel_normalisation(good, cfg)
    doc = calibration.load_rig_config(cfg)
    assert doc["taxel_normalisation"]["source"] == "run" and doc["taxel_normalisation_previous"]["source"] == "first"
    assert calibration.undo_taxel_normalisation(cfg)["taxel_normalisation"]["source"] == "first"
    assert calibration.undo_taxel_normalisation(cfg)["taxel_normalisation"]["source"] == "run"  # redo
    doc = calibration.reset_taxel_normalisation(cfg)
    assert "taxel_normalisation" not in doc and doc["taxel_normalisation_previous"]["source"] == "run"
