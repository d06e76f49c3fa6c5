"""One clock for a simulated rig and a face in another process (issue 54; rigctl.core.port_clock): the face holds
the rig's clock file while its drum client is open and its grants bound the rig's world; a stopped face (SIGSTOP)
does not hold the world (issue 76: rigctl.core.port_clock.ClockFile.hosts_stopped), and a face that is gone lets it
run on by itself (its controller's watchdog then judges the silence, as on a bench)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from rigctl.core.port_clock import CLOCK_NAME
from rigctl.core.shared_clock import is_port_clock
from rigctl.devices.drum import DrumClient
from rigctl.simulation.rig import SimulatedRig

from ..sim_time import wall_to_run_on

#: the face: opens the rig's drum port as hardware, says whether it found the rig's clock, then polls the status
FACE = """
import sys, time
from rigctl.core.shared_clock import is_port_clock
from rigctl.devices.drum import DrumClient
with DrumClient(sys.argv[1], timeout_s=2.0) as drum:
    print("attached" if is_port_clock(drum.clock) else "wall", flush=True)
    while True:
        drum.read_status()
        time.sleep(0.05)
"""


def _runs_on(sim: SimulatedRig, sim_s: float = 0.2, within_s: float = 60.0) -> bool:
    """Whether the world runs ``sim_s`` s on within ``within_s`` s of wall time (a bound on a hang, not a judgement of
    speed: beside two CPU hogs a face's first request sat in the kernel's pty hop longer than 0.5 s, and the world
    rightly stood for it meanwhile)."""
    return wall_to_run_on(sim.model_time_s, sim_s, within_s) is not None


def test_neither_a_stopped_face_of_another_process_nor_a_killed_one_holds_the_world(tmp_path):
    with SimulatedRig(port_dir=tmp_path / "ports") as sim:
        assert (sim.port_dir / CLOCK_NAME).is_file()
        assert _runs_on(sim)  # no face: the world runs by itself
        face = subprocess.Popen([sys.executable, "-c", FACE, sim.drum_port], stdout=subprocess.PIPE, text=True)
        try:
            assert face.stdout is not None and face.stdout.readline().strip() == "attached"
            assert _runs_on(sim)  # a face that runs grants time
            os.kill(face.pid, signal.SIGSTOP)  # a stopped face grants nothing, and never will until continued:
            time.sleep(0.3)
            assert _runs_on(sim)  # the world does not wait for it (issue 76: its controller's watchdog must act)
            os.kill(face.pid, signal.SIGCONT)
            assert _runs_on(sim)
            face.kill()  # the face is gone: its lock with it
            face.wait(30)
            assert _runs_on(sim)  # the world runs on by itself
        finally:
            if face.poll() is None:
                face.kill()
                face.wait(30)
        with DrumClient(sim.drum_port, timeout_s=2.0) as drum:  # this process's own rig: its in-process clock
            assert drum.clock is sim.clock and not is_port_clock(drum.clock)
    assert not (tmp_path / "ports" / CLOCK_NAME).exists()  # removed with the rig


def test_a_face_that_attaches_before_the_worlds_first_step_runs_it():
    """A face of another process may attach to the clock file the moment the ports appear, before the world's first
    step: the rig publishes its time from the start (the model's is 75 ms) and the face's first grant reaches the file.
    Before, the file said time 0 and no grant: the face granted up to 50 ms, short of the world, and each waited on the
    other forever (3 processes side by side hung 3 times in 45 attaches)."""
    import threading

    from rigctl.core.shared_clock import attach_port_clock, release_port_clock

    sim = SimulatedRig()
    try:
        clock = attach_port_clock(sim.drum_port)  # as another process would (the file: not this process's clock)
        try:
            assert clock is not None and clock is not sim.clock
            assert clock.now() == sim.model.time_s > 0.0  # the world's time, before any step
            sim.start()
            slept = threading.Thread(target=clock.sleep, args=(0.5,), daemon=True)
            slept.start()
            slept.join(timeout=60.0)  # (a hang guard: 0.5 s of an unpaced world takes far less)
            assert not slept.is_alive(), (sim.model.time_s, clock.now(), clock.horizon_s)
            assert sim.model.time_s >= 0.5
        finally:
            release_port_clock(clock)
    finally:
        sim.close()


def test_a_face_of_another_process_waits_for_an_answer_the_rig_says_is_on_its_way():
    """A face's answer wait does not give up on an answer the rig knows is on its way (a reply handed to the face's
    pty that the kernel still holds: a CI run beside two CPU hogs failed a `rigctl acquire --drum-port` against
    `rigctl sim` with DrumTimeout and "stale response" while the answers were late). The rig looks at each step of its
    world and writes what it saw into the clock file; the face's clock reads it (``HostSide.in_flight``), as a host of
    the rig's own process asks the board (``VirtualMega.answer_in_flight``). The face here is this process's attached
    clock, as that process would attach it; the wait is the drum client's (``wait_for(in_flight=)``)."""
    import threading

    from rigctl.core.shared_clock import attach_port_clock, release_port_clock

    with SimulatedRig() as sim:
        clock = attach_port_clock(sim.drum_port)
        assert clock is not None and clock is not sim.clock and clock.in_flight is not None
        try:
            with DrumClient(sim.drum_port, clock=clock, timeout_s=2.0) as drum:
                drum.read_status()  # the face has found a reply there (its read stamped in the file)

                def flying() -> bool:
                    assert clock.in_flight is not None
                    return clock.in_flight(sim.drum_port)

                def says(drum: bool, taxel: bool) -> bool:  # the rig's next fresh look (a stale one says True)
                    assert clock.in_flight is not None
                    t_end = time.monotonic() + 10.0
                    while time.monotonic() < t_end:
                        if (flying(), clock.in_flight(sim.taxel_port)) == (drum, taxel):
                            return True
                        time.sleep(0.005)
                    return False

                assert says(False, False)
                sim.mega.bridge.to_client_at = time.monotonic()  # a reply handed on that the face has not found
                assert sim.mega.reply_on_its_way()
                assert says(True, False)
                t0 = clock.now()
                result: list[bool] = []
                waiter = threading.Thread(target=lambda: result.append(
                    clock.wait_for(lambda: False, 0.1, in_flight=flying)), daemon=True)
                waiter.start()
                waiter.join(1.0)
                assert waiter.is_alive()  # 1 s of wall time past a 0.1 s deadline: still waiting
                assert clock.now() - t0 > 0.3  # and the world ran on meanwhile
                clock.note_read(sim.drum_port)  # the face finds the reply: nothing on its way any more
                waiter.join(10.0)
                assert result == [False]
                assert says(False, False)
        finally:
            release_port_clock(clock)
