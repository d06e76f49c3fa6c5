"""The Mega's drum index sensor input under simavr: a bouncing sensor counts once per revolution (Timer5 input
capture with a 20 ms debounce in mega_drum.cpp; the harness's --index-bounce)."""

from __future__ import annotations

import time

import pytest

from rigctl.devices.drum import DrumClient
from rigctl.devices.wire import DrumState, HoldingRegister as HR
from rigctl.simulation.hil import HilRig
from rigctl.simulation.model import DrumConfig

from .conftest import home

pytestmark = pytest.mark.hil


def test_a_bouncing_index_sensor_counts_each_revolution_once(fw_build):
    with HilRig(live=False, with_uno=False, index_bounce=3) as rig:
        drum = DrumClient(rig.drum_port, timeout_s=1.0, clock=rig.clock).open()
        try:
            drum.write_holding(HR.WATCHDOG_MS, 10000)
            home(drum)  # out of reset the Mega is NOT_HOMED and refuses RUN
            drum.set_force(250)
            drum.set_speed(120)
            drum.run()
            deadline = time.monotonic() + 120
            st = drum.read_status()
            while st.index_count < 3:
                assert time.monotonic() < deadline and st.state == DrumState.RUNNING, st
                time.sleep(0.2)
                st = drum.read_status()
            d = DrumConfig()
            assert st.index_source == "sensor"
            assert st.index_steps == d.steps_per_rev * d.microsteps  # one edge per revolution, not four
            assert st.index_speed_mm_s(d.diameter_mm) == pytest.approx(120.0, rel=0.01)
            drum.stop()
        finally:
            drum.close()
