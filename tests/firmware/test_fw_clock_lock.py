"""The simavr harnesses on the rig's one clock (rigctl.simulation.hil_clock, ``arduino/simavr/rigctl_simavr.c``
"clock lock"): a host's write the kernel still holds keeps both boards standing, as it keeps the model world's
watchdog from judging a silent host (tests/simulation/test_sim_shared_clock.py).

A pty hands a writer's bytes on through a kernel worker, which a loaded machine held back for up to 0.83 s: the Uno
encoder image then held a window whose speed the host had sent in time (test_fw_uno_encoder, a CI run), and the Mega's
firmware watchdog judges a request held so as a silent host. The host stamps each write on the rig's clock before it
makes it; a harness whose host wrote after it last read its pty waits for those bytes (at most KERNEL_HOP_MAX_S of wall
time).
"""

from __future__ import annotations

import time

import pytest
import serial

from rigctl.devices import wire
from rigctl.simulation import hil

pytestmark = pytest.mark.hil


def _world_over(rig: hil.HilRig, wall_s: float) -> float:
    """The boards' simulated time that passes over ``wall_s`` of wall time while the host lives and waits (its
    heartbeat grants the world the wall time), s."""
    t0 = rig.clock.now()
    time.sleep(wall_s)
    return rig.clock.now() - t0


@pytest.mark.parametrize("board", ["mega", "uno"])
def test_a_host_write_the_kernel_still_holds_keeps_the_boards_standing(fw_build, board):
    with hil.HilRig(live=False, with_uno=board == "uno") as rig:
        port = rig.drum_port if board == "mega" else rig.taxel_port
        with serial.Serial(port, timeout=0.05) as raw:  # opened first: the Uno's reset on open passes meanwhile
            t0 = time.monotonic()
            while rig.clock.now() < 1.0:
                assert time.monotonic() - t0 < 30, "the boards did not start"
                time.sleep(0.02)
            assert _world_over(rig, 0.4) > 0.2  # nothing on the way: the world runs on the heartbeat's grants
            rig.clock.note_write(port)  # a write the kernel holds: stamped, its bytes not yet in the pty
            held = _world_over(rig, 0.6)
            assert held < 0.02, f"the {board} ran {held * 1e3:.0f} ms while the host's bytes were on their way"
            raw.write(wire.UnoCommand.STOP.value)  # the bytes arrive (a STOP: harmless to either image)
            raw.flush()
            assert _world_over(rig, 0.4) > 0.2, "the world did not go on once the bytes had come"
