"""Fixtures of the firmware tests: the built images and a HilRig (both firmwares under simavr)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from rigctl import firmware
from rigctl.devices import wire
from rigctl.simulation import hil

#: the taxels the on-board encoder reads: the top layer, channels 0-8
ENCODER_TAXELS = 9


@pytest.fixture(scope="session")
def fw_build(build_tools):
    """Build both images and the harness from the package's sources (:func:`rigctl.firmware.build`); returns the
    build directory."""
    return firmware.build()


@pytest.fixture(scope="session")
def handheld_scans() -> list[tuple[np.ndarray, np.ndarray]]:
    """Simulated handheld scans for the on-board encoder's tests: (taxels 0-8 ADC counts at 1 kHz (n, 9) uint16,
    window speeds mm/s): slow, fast, slow-to-fast."""
    from rigctl.acquisition.handheld import velocity_from_position
    from rigctl.core.handheld import PlateAxis
    from rigctl.core.trial import PlannedTrial
    from rigctl.encoding.speed import window_speeds
    from rigctl.simulation.operator import SimulatedOperator

    op = SimulatedOperator(seed=7)
    plans = [PlannedTrial(0, "L", 40.0, 500.0, 200.0 / 40.0, "slow", math.nan, math.nan),
             PlannedTrial(1, "B", 120.0, 500.0, 200.0 / 120.0, "fast", math.nan, math.nan),
             PlannedTrial(2, "N", 80.0, 500.0, 200.0 / 80.0, "slow-to-fast", 40.0, 120.0)]
    axis = PlateAxis.from_touches(*op.touch_ends())
    out = []
    for plan in plans:
        scan = op.scan(plan)
        assert scan is not None
        x = np.ascontiguousarray(scan.taxels[:, :ENCODER_TAXELS], dtype=np.uint16)
        ok = np.all(np.isfinite(scan.tracker_xyz), axis=1)  # the tracker's dropouts
        t = scan.tracker_time_s[ok] - scan.host_time_s[0]
        vel = np.abs(velocity_from_position(t, axis.along_mm(scan.tracker_xyz[ok])))
        out.append((x, window_speeds(t, vel, x.shape[0] / 1000.0)))
    return out


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
    """HOME the Mega if it is NOT_HOMED (after power-up or a reset it refuses RUN and PRESS until then), as a rig's
    first start does (:meth:`rigctl.acquisition.rig.Rig.home_if_pending`)."""
    # first the HX711 rate the controller times at boot (spec 2.9: PRESS and RUN wait for it; a wrong rate faults)
    if drum.wait_hx711_rate(timeout_s=10).state == wire.DrumState.NOT_HOMED:
        drum.home()
        drum.wait_state([wire.DrumState.IDLE], timeout_s=30)
