"""Fixtures of the firmware tests: the built images and a HilRig (both firmwares under simavr)."""

from __future__ import annotations

import time

import pytest

from rigctl import firmware
from rigctl.devices import wire
from rigctl.simulation import hil


@pytest.fixture(scope="session")
def fw_build(build_tools):
    """Build both images and the harness from the package's sources (:func:`rigctl.firmware.build`); returns the
    build directory."""
    return firmware.build()


@pytest.fixture(scope="module")
def hil_rig(fw_build):
    """A running HilRig for one test module (live taxel rendering)."""
    with hil.HilRig() as rig:
        yield rig


def _wait_frames(stream, n: int, *, stall_s: float = 10.0) -> bool:
    """Wait until the capture holds ``n`` frames while frames keep coming: simavr is paced to the wall clock but
    falls behind on a starved machine, so a fixed deadline measures the machine, not the firmware. Gives up (False)
    only when no frame arrived for ``stall_s``."""
    last, last_t = -1, None

    while not stream.wait_capture(n, timeout_s=0.5):
        frames = stream.stats.frames
        now = time.monotonic()
        if frames != last:
            last, last_t = frames, now
        elif now - last_t > stall_s:
            return False
    return True


@pytest.fixture
def wait_frames():
    """:func:`_wait_frames`: wait for a capture's frames while simavr keeps delivering them."""
    return _wait_frames


def home(drum) -> None:
    """HOME the Mega if it is NOT_HOMED (after power-up or a reset it refuses RUN and PRESS until then), as a rig does
    when it opens (:meth:`rigctl.acquisition.rig.Rig.connect`)."""
    # first the HX711 rate the controller times at boot (spec 2.9: PRESS and RUN wait for it; a wrong rate faults)
    if drum.wait_hx711_rate(timeout_s=10).state == wire.DrumState.NOT_HOMED:
        drum.home()
        drum.wait_state([wire.DrumState.IDLE], timeout_s=30)
