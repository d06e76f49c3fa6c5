"""Acknowledging is not starting, against a controller that outlives the face (issue 51 item 7): a Hypothesis state
machine drives one ``rigctl sim`` process (its own process, as a real drum controller) through random sequences of
faults (``rigctl sim inject``: e-stop press and release, reset), acknowledgements, starts, STOPs, face restarts and
``kill -9`` of the face, the faces driving it as hardware (``--drum-port DIR/drum --taxel-port DIR/taxel``): the CLI
(``rigctl acquire`` of a TOML plan and of a Python plan, ``--resume`` for "acknowledge and go on") and ``rigctl serve``
(HTTP over loopback with its token: ``POST /ack``, ``/runs/{id}/resume``, ``/queue/release``, ``/stop``), and faces
that open the rig and do not start it (``rigctl doctor`` of checks that do not move; ``rigctl serve`` until its first
start). It judges on the rig's ground truth (its truth log: true force, actuator position, drum speed) that after a
latch nothing moves (actuator towards the sensor, force rising, drum turning) until an acknowledgement and a separate
start were both given, and so also that nothing moves within 10 s of an e-stop's release without both; and that an
opening moves nothing (the actuator within 0.005 mm either way: a HOME at open backs a stranded actuator off; no
force rise, no drum turning) until a start.

The latches the machine knows it made: an e-stop press (at its time on the rig's clock, from ``sim inject``'s
answer); a reset while a face is open (the host's latch: a later face's start homes and tares, the remedy, so that
start ends it); a ``kill -9`` that left the controller in FAULT (its watchdog: read on the drum port once the
face is gone). A latch the machine did not make (a face starved past the watchdog on a loaded machine) only leaves
motion it allows unjudged, never fails the test.

Budget (CI): :data:`SEQUENCES` sequences of at most :data:`STEPS` steps each (derandomized: the same sequences every
run), one ``rigctl sim`` for all."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, settings, strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, precondition, rule, run_state_machine_as_test

from .. import loopback
from ..simulation.sim_process import HANG_S, SimProcess

# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware) and
#   faces of other processes, killed and restarted
pytestmark = [pytest.mark.realtime, pytest.mark.slow]


def _takes_ack() -> bool:
    """Whether ``rigctl acquire`` and ``rigctl serve`` take ``--ack REASON`` (an acknowledgement at open, issue 51
    item 2): the machine opens faces with it only then."""
    import click

    from rigctl.cli import main

    ctx = click.Context(main)
    return all(any(p.name == "ack" for p in main.get_command(ctx, c).params) for c in ("acquire", "serve"))


#: the ``ack`` choices of a face's opening
ACK_AT_OPEN = [False, True] if _takes_ack() else [False]

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)

#: the state machine's budget: sequences x steps (kept CI-affordable: each step waits on real processes)
SEQUENCES = int(os.environ.get("RIGCTL_OUTLIVES_SEQUENCES", "3"))
STEPS = int(os.environ.get("RIGCTL_OUTLIVES_STEPS", "8"))
TOKEN = "outlives-face-token"

#: after a latch, how long the rig may take to come to rest (the drum's stop ramp, the actuator backing off), s of the
#: rig's time; after a kill -9 the controller's watchdog (1 s on hardware) comes first
SETTLE_S = {"estop": 0.5, "reset": 0.5, "watchdog": 2.0, "open": 2.0}
#: what counts as motion on the truth log: the actuator towards the sensor by more than this (mm), the force rising by
#: more than this (g) over the rest of the window, the drum turning faster than this (mm/s)
ADVANCE_MM, RISE_G, TURNING_MM_S = 0.02, 10.0, 1.0
#: an opening moves nothing: the actuator's excursion either way within this (mm; a HOME at open backs a stranded
#: actuator off; the window begins SETTLE_S["open"] after the face is started, an earlier face's back-off done)
OPEN_MOVED_MM = 0.005
#: a reset while a face is open: injected no earlier than this long after the face first wrote to the drum link (its
#: open reads the controller's boot count then), s of wall time
OPEN_READ_S = 1.0

TOML = """name = "outlives"
description = "3 short trials"
textures = ["A"]
speeds_mm_s = [100]
forces_g = [300]
trials_per_condition = 3
travel_mm = 150
order = "blocked"
"""
PLAN = """NAME = "outlives_plan"
MAX_TRIALS = 3


def plan(ctx):
    for force in (250.0, 300.0, 350.0):
        yield ctx.trial("A", speed_mm_s=100.0, force_g=force, travel_mm=150.0)
"""


@dataclass
class Latch:
    """A latch the machine made: its kind, when it began (wall clock), and whether an acknowledgement came since."""

    kind: str
    wall_s: float
    acked: bool = False
    end_wall_s: float | None = None  # the start (after an acknowledgement) that ended it
    how: list[str] = field(default_factory=list)
    face: object = None  # the face that was open when it began


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Face:
    """One face process driving the running sim as hardware: ``cli``, ``plan`` (rigctl acquire of the TOML or the
    Python plan) or ``serve`` (rigctl serve, a run submitted over HTTP)."""

    def __init__(self, kind: str, proc: subprocess.Popen, url: str | None = None):
        self.kind, self.proc, self.url = kind, proc, url
        self.run_id: str | None = None
        self.started_ns = time.monotonic_ns()  # (the clock file's stamps are time.monotonic, one clock a machine)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def http(self, method: str, path: str, **kw):
        """The answer, or None when the server is gone (it may stop on its own: a run that ended, an open refused)."""
        import httpx

        if method == "POST" and "json" not in kw:
            kw["json"] = {}  # the server takes state-changing requests as JSON only
        try:
            return loopback.client().request(method, f"{self.url}{path}",
                                             headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0, **kw)
        except httpx.HTTPError:
            if self.alive():
                raise
            return None


class OutlivesFace(RuleBasedStateMachine):
    """The operator's and the world's actions on one running ``rigctl sim`` (see the module's doc)."""

    sim: SimProcess
    work: Path
    env: dict[str, str]
    examples = 0
    log: list[str] = []

    def __init__(self):
        super().__init__()
        OutlivesFace.examples += 1
        self.folder = self.work / f"seq{OutlivesFace.examples}"
        self.folder.mkdir()
        (self.folder / "outlives.toml").write_text(TOML)
        (self.folder / "outlives_plan.py").write_text(PLAN)
        self.face: Face | None = None
        self.latches: list[Latch] = []
        self.serve_port = _free_port()
        self.releases: list[float] = []  # wall times of e-stop releases
        self.steps: list[str] = []
        self.doctored = False
        self.files: list = []  # the faces' stderr logs
        self.t0 = time.time()

    # ------------------------------------------------------------------ what the machine records
    def _note(self, text: str) -> None:
        self.steps.append(f"{time.time() - self.t0:7.2f} s {text}")

    def _ack(self, how: str) -> None:
        for latch in self.latches:
            if latch.end_wall_s is None:
                latch.acked = True
                latch.how.append(f"ack:{how}")

    def _start(self, how: str, wall_s: float) -> None:
        """A start: it ends every latch acknowledged before it, an opening's window, and a reset's host-side latch
        of an earlier face (the start HOMEs and TAREs: its remedy)."""
        for latch in self.latches:
            if latch.end_wall_s is None and (latch.acked or latch.kind == "open"
                                             or (latch.kind == "reset" and latch.face is not self.face)):
                latch.end_wall_s = wall_s
                latch.how.append(f"start:{how}")

    def _face_gone(self) -> None:
        """The face went (killed, stopped, restarted, or found gone): its opening's window ends."""
        for latch in self.latches:
            if latch.kind == "open" and latch.end_wall_s is None:
                latch.end_wall_s = time.time()
                latch.how.append("the face went")

    def _wall_of(self, time_s: float) -> float:
        """The wall time the rig's clock reached ``time_s`` (from the truth log's rows)."""
        t = self.sim.wait_truth(time_s)
        return float(np.interp(time_s, t["time_s"], t["wall_time_s"]))

    # ------------------------------------------------------------------ faces
    def _acquire(self, kind: str, ack: bool) -> Face:
        plan = "outlives.toml" if kind == "cli" else "outlives_plan.py"
        out = self.folder / f"{kind}.h5"
        args = [*RIGCTL, "acquire", plan, "--drum-port", self.sim.drum_port, "--taxel-port", self.sim.taxel_port,
                "--plates", "skip", "--quiet", "--out", out.name]
        resume = out.exists()
        if resume:
            args.append("--resume")  # acknowledge the session's latch and go on: one command, both acts
        if ack:
            args += ["--ack", "state machine"]  # acknowledge what the controller latches at open; the run is the start
        wall = time.time()
        proc = subprocess.Popen(args, cwd=self.folder, env=self.env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=self._err(kind))
        if resume or ack:
            self._ack(f"{kind} {'--resume' if resume else '--ack'}")
        self.face = Face(kind, proc)
        self._start(f"{kind}'s run", wall)  # acquire's run is its start
        return self.face

    def _err(self, kind: str):
        f = open(self.folder / f"{kind}.err", "a")  # noqa: SIM115 - closed with the machine
        self.files.append(f)
        return f

    def _serve(self, ack: bool = False) -> Face:
        args = [*RIGCTL, "serve", "--rig", "hardware", "--drum-port", self.sim.drum_port, "--taxel-port",
                self.sim.taxel_port, "--host", "127.0.0.1", "--port", str(self.serve_port), "--queue", "queue.json",
                "--data-dir", "data"]
        if ack:
            args += ["--ack", "state machine"]  # an acknowledgement at open, not a start
        wall = time.time()
        proc = subprocess.Popen(args, cwd=self.folder, env=self.env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=self._err("serve"))
        if ack:
            self._ack("serve --ack")
        face = self.face = Face("serve", proc, f"http://127.0.0.1:{self.serve_port}")
        self.latches.append(Latch("open", wall, face=face))  # nothing moves until its first start
        deadline = time.monotonic() + HANG_S
        while face.alive():
            try:
                r = face.http("GET", "/status")
                if r is not None and r.status_code == 200:
                    break
            except Exception:  # noqa: BLE001 - not listening yet
                pass
            assert time.monotonic() < deadline, "rigctl serve did not answer"
            time.sleep(0.3)
        answer = face.http("GET", "/runs") if face.alive() else None
        if answer is not None:
            runs = answer.json()
            pending = [r for r in runs if r["state"] not in ("done", "aborted", "failed")]
            if pending:
                face.run_id = pending[-1]["id"]
            else:
                wall = time.time()
                r = face.http("POST", "/runs", json={"toml": TOML, "out": f"run{len(runs)}.h5"})
                if r is not None:
                    assert r.status_code == 201, r.text
                    face.run_id = r.json()["id"]
                    self._start("serve: POST /runs", wall)
        return face

    @initialize(kind=st.sampled_from(["serve", "cli", "plan"]), seconds=st.sampled_from([3.0, 6.0]))
    def first_face(self, kind, seconds):
        """Every sequence begins with a face running its plan for a while (homing, pressing or turning)."""
        self.open_face(kind, ack=False)
        self.wait(seconds)

    @precondition(lambda self: self.face is None or not self.face.alive())
    @rule(kind=st.sampled_from(["serve", "cli", "plan"]), ack=st.sampled_from(ACK_AT_OPEN))
    def open_face(self, kind, ack):
        self._face_gone()
        self._note(f"open {kind}{' --ack' if ack else ''}")
        self.face = self._serve(ack) if kind == "serve" else self._acquire(kind, ack)

    @precondition(lambda self: (self.face is None or not self.face.alive()) and not self.doctored)
    @rule()
    def open_without_a_start(self):
        """``rigctl doctor`` of checks that do not move: it opens the rig and closes it; nothing may move."""
        self._face_gone()
        self.doctored = True  # once a sequence: the other acts keep their share of the steps
        self._note("open doctor (no check that moves)")
        wall = time.time()
        latch = Latch("open", wall, how=["rigctl doctor"])
        self.latches.append(latch)
        r = subprocess.run([*RIGCTL, "doctor", "--drum-port", self.sim.drum_port, "--taxel-port",
                            self.sim.taxel_port, "--check", "controller-faults", "--check", "e-stop"],
                           cwd=self.folder, env=self.env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                           timeout=HANG_S)
        self._note(f"  doctor exit {r.returncode}")
        latch.end_wall_s = time.time()

    @precondition(lambda self: self.face is not None and self.face.alive())
    @rule()
    def kill_9_the_face(self):
        self._note(f"kill -9 {self.face.kind}")
        self._face_gone()
        wall = time.time()
        self.face.proc.kill()
        self.face.proc.wait(timeout=HANG_S)
        self.face = None
        time.sleep(2.5)  # the controller's watchdog (1 s on hardware) has acted on a rig that pressed or turned
        from rigctl.devices.drum import DrumClient
        from rigctl.devices.wire import DrumState

        with DrumClient(self.sim.drum_port, timeout_s=2.0) as drum:
            st_ = drum.read_status()
        if st_.state == DrumState.FAULT:
            self._note(f"  controller in FAULT {st_.faults!r}")
            self.latches.append(Latch("watchdog", wall))

    @precondition(lambda self: self.face is not None and self.face.alive())
    @rule()
    def stop(self):
        if self.face.kind == "serve":
            r = self.face.http("POST", "/stop")
            self._note(f"POST /stop -> {r and r.status_code}")
        else:
            self._note(f"Ctrl-C {self.face.kind}")
            self._face_gone()
            self.face.proc.send_signal(signal.SIGINT)
            self.face.proc.wait(timeout=HANG_S)

    @precondition(lambda self: self.face is not None and self.face.alive() and self.face.kind == "serve")
    @rule()
    def restart_serve(self):
        self._note("restart serve (SIGTERM, the same command)")
        self._face_gone()
        self.face.proc.terminate()
        self.face.proc.wait(timeout=HANG_S)
        self.face = self._serve()

    @precondition(lambda self: self.face is not None and self.face.alive() and self.face.kind == "serve"
                  and any(latch.end_wall_s is None and not latch.acked for latch in self.latches))
    @rule()
    def acknowledge(self):
        r = self.face.http("POST", "/ack", json={"reason": "state machine", "by": "pytest"})
        self._note(f"POST /ack -> {r and r.status_code}")
        if r is not None and r.status_code == 200:
            self._ack("POST /ack")

    @precondition(lambda self: self.face is not None and self.face.alive() and self.face.kind == "serve")
    @rule(how=st.sampled_from(["resume", "release"]))
    def start(self, how):
        wall = time.time()
        path = "/queue/release" if how == "release" else f"/runs/{self.face.run_id}/resume"
        r = self.face.http("POST", path)
        self._note(f"POST {path} -> {r and r.status_code}")
        if r is not None and r.status_code < 300:
            self._start(f"POST {path}", wall)

    # ------------------------------------------------------------------ faults and time
    def _open(self, kind: str) -> bool:
        return any(latch.kind == kind and latch.end_wall_s is None for latch in self.latches)

    @precondition(lambda self: not self._open("estop"))  # one e-stop at a time: the sequence goes on to other acts
    @rule(hold_s=st.sampled_from([0.5, 3.0]))
    def estop(self, hold_s):
        r = self.sim.inject(f"estop@0+{hold_s:g}")
        assert r.returncode == 0, r
        pressed = float(r.stdout.split("starts at ")[1].split(",")[0])
        self._note(f"e-stop pressed for {hold_s:g} s (rig time {pressed:.2f})")
        self.latches.append(Latch("estop", self._wall_of(pressed)))
        self.releases.append(self._wall_of(pressed + hold_s))

    def _face_has_read_the_controller(self) -> bool:
        """Wait until the face has opened the rig: it wrote to the drum link after it started (the rig's clock file:
        rigctl.core.port_clock, the faces' drum write stamp), then :data:`OPEN_READ_S` more for its open to read the
        controller (its boot count). False when the face ended first. A reset before that is one the face cannot
        have seen (a process still importing, at load ~15 for up to 8 s: 2 of 5 runs reset the controller at rest
        before `plan --ack` opened it, and judged its own start's HOME and press as motion after that reset)."""
        import struct

        face = self.face
        deadline = time.monotonic() + HANG_S
        while face is not None and face.alive() and time.monotonic() < deadline:
            with open(Path(self.sim.dir) / ".clock", "rb") as f:
                head = f.read(40)
            if len(head) == 40 and struct.unpack_from("<Q", head, 32)[0] > face.started_ns:
                time.sleep(OPEN_READ_S)
                return face.alive()
            time.sleep(0.05)
        return False

    @precondition(lambda self: self.face is not None and self.face.alive() and not self._open("reset"))
    @rule()
    def reset(self):
        if not self._face_has_read_the_controller():
            self._note("controller reset skipped: the face ended before it opened the rig")
            return
        r = self.sim.inject("reset@0")
        assert r.returncode == 0, r
        at = float(r.stdout.split("starts at ")[1].split(" ")[0])
        self._note(f"controller reset (rig time {at:.2f})")
        self.latches.append(Latch("reset", self._wall_of(at), face=self.face))

    @rule(seconds=st.sampled_from([1.0, 4.0]))
    def wait(self, seconds):
        self._note(f"wait {seconds:g} s")
        time.sleep(seconds)

    # ------------------------------------------------------------------ the judgement
    def teardown(self):
        try:
            # an e-stop's release is judged for 10 s after it (while no acknowledgement and start came)
            if self.releases:
                time.sleep(max(0.0, max(self.releases) + 10.0 - time.time()))
            self.judge(self.sim.wait_truth(self.sim.status()["time_s"]))
        finally:
            self._clean_up()
            for f in self.files:
                f.close()
            OutlivesFace.log.append("\n".join(self.steps))

    def judge(self, t: dict[str, np.ndarray]) -> None:
        for latch in self.latches:
            # the settling is the rig's (its stop ramp, its back-off, its watchdog: rig time); a face's latch and its
            # end are moments of the wall, taken onto the rig's clock (under load the rig runs slower than the wall:
            # a watchdog's back-off was still under way 2 s of wall after a kill -9 at load ~12, and judged an open's)
            begin = float(np.interp(latch.wall_s, t["wall_time_s"], t["time_s"])) + SETTLE_S[latch.kind]
            end_wall = latch.end_wall_s if latch.end_wall_s is not None else t["wall_time_s"][-1]
            end = float(np.interp(end_wall, t["wall_time_s"], t["time_s"]))
            inside = (t["time_s"] >= begin) & (t["time_s"] < end)
            if inside.sum() < 2:
                continue
            act, force, speed = t["actuator_mm"][inside], t["true_force_g"][inside], t["drum_speed_mm_s"][inside]
            where = f"{latch.kind} latch at {latch.wall_s - self.t0:.2f} s ({latch.how}); steps:\n" + \
                "\n".join(self.steps)
            if latch.kind == "open":  # either way: a HOME at open backs a stranded actuator off
                moved = float(np.ptp(act))
                assert moved <= OPEN_MOVED_MM, f"the actuator moved {moved:.3f} mm after the opening {where}"
            advance = float(np.max(act - np.minimum.accumulate(act)))
            rise = float(np.max(force - np.minimum.accumulate(force)))
            assert advance <= ADVANCE_MM, f"the actuator moved {advance:.3f} mm towards the sensor after the {where}"
            assert rise <= RISE_G, f"the force rose {rise:.1f} g after the {where}"
            assert float(np.max(np.abs(speed))) <= TURNING_MM_S, \
                f"the drum turned at {np.max(np.abs(speed)):.1f} mm/s after the {where}"

    def _clean_up(self) -> None:
        """The next sequence starts from a rig at rest and unlatched: the face stopped (Ctrl-C, then killed), the
        e-stop released, the controller's fault cleared on its port (a maintenance step, not a face's)."""
        from rigctl.devices.drum import DrumClient
        from rigctl.devices.wire import DrumState

        if self.face is not None and self.face.alive():
            self.face.proc.send_signal(signal.SIGINT)
            try:
                self.face.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.face.proc.kill()
                self.face.proc.wait(timeout=HANG_S)
        deadline = time.monotonic() + HANG_S
        while "estop" in self.sim.status()["active"]:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        with DrumClient(self.sim.drum_port, timeout_s=2.0) as drum:
            if drum.read_status().state == DrumState.FAULT:
                drum.clear_fault()


@pytest.mark.timeout(1800)  # 3 sequences of 8 steps on real processes: ~4-8 min on a loaded 2-core machine
def test_a_latch_holds_until_an_acknowledgement_and_a_separate_start(tmp_path):
    env = {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "XDG_STATE_HOME": str(tmp_path / "state"),
           "RIGCTL_SERVE_TOKEN": TOKEN}
    with SimProcess(RIGCTL, tmp_path, seed=5) as sim:
        OutlivesFace.sim, OutlivesFace.work, OutlivesFace.env = sim, tmp_path, env
        OutlivesFace.examples, OutlivesFace.log = 0, []
        try:
            run_state_machine_as_test(OutlivesFace, settings=settings(
                max_examples=SEQUENCES, stateful_step_count=STEPS, deadline=None, database=None, derandomize=True,
                # no shrinking (each step waits on real processes): a failure names its whole sequence instead
                phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck)))
        finally:
            print("\n\n".join(OutlivesFace.log))
    assert OutlivesFace.examples >= SEQUENCES


@pytest.mark.timeout(900)
def test_a_fixed_sequence_through_acknowledgement_restart_and_opening(tmp_path):
    """The machine's acts in one fixed order the random draws at CI's budget may miss (they depend on which faces
    are alive when): a served run e-stopped mid-press, released, ``POST /ack`` (nothing moves: the run stays
    paused), the server restarted (its opening moves nothing, the run held), killed, ``rigctl doctor`` opening the
    rig with the actuator where the e-stop left it (nothing moves); judged on the truth log as the machine judges."""
    env = {**os.environ, "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "XDG_STATE_HOME": str(tmp_path / "state"),
           "RIGCTL_SERVE_TOKEN": TOKEN}
    with SimProcess(RIGCTL, tmp_path, seed=7) as sim:
        OutlivesFace.sim, OutlivesFace.work, OutlivesFace.env = sim, tmp_path, env
        OutlivesFace.examples, OutlivesFace.log = 0, []
        machine = OutlivesFace()
        try:
            machine.first_face("serve", 6.0)
            machine.estop(3.0)
            machine.wait(4.0)
            machine.acknowledge()
            assert any(latch.acked for latch in machine.latches if latch.kind == "estop"), machine.steps
            machine.wait(4.0)
            machine.restart_serve()
            machine.wait(4.0)
            machine.kill_9_the_face()
            machine.open_without_a_start()
        finally:
            machine.teardown()
            print("\n".join(OutlivesFace.log))
