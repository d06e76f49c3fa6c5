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


def test_a_20pct_slip_latches_drum_slip_on_the_firmware(fw_build):
    """Issue 39 item 5 under simavr: the speed marks (8 per revolution, INT2) time every 39 mm of the real drum; the
    harness's drum slips 20 % against its STEP pulses (``--inject slip=20%``): DRUM_SLIP latches within 1.25 mark
    intervals of the slip; before it, every interval took 400 +-1 microsteps at 120 mm/s."""
    from rigctl.core.faults import parse_fault
    from rigctl.devices.wire import Fault

    with HilRig(live=False, with_uno=False) as rig:
        drum = DrumClient(rig.drum_port, timeout_s=1.0, clock=rig.clock).open()
        try:
            drum.write_holding(HR.WATCHDOG_MS, 10000)
            home(drum)
            drum.set_force(250)
            drum.set_speed(120)
            drum.run()
            deadline = time.monotonic() + 120
            st = drum.read_status()
            seen = {}
            while st.mark_count < 4:
                assert time.monotonic() < deadline and st.state == DrumState.RUNNING, st
                if st.mark_steps:
                    seen[st.mark_count] = (st.mark_steps, st.mark_period_s)
                time.sleep(0.05)
                st = drum.read_status()
            seen[st.mark_count] = (st.mark_steps, st.mark_period_s)
            assert seen and all(abs(steps - 400) <= 1 for steps, _ in seen.values()), seen
            assert all(abs(p - 0.3272) < 0.002 for _, p in seen.values()), seen  # 39.3 mm at 120 mm/s
            t_slip = rig.clock.now()
            rig.inject_faults([parse_fault("slip=20%@0")])
            st = drum.read_status()
            while not st.faults:
                assert time.monotonic() < deadline and st.state == DrumState.RUNNING, st
                time.sleep(0.05)
                st = drum.read_status()
            assert st.faults == Fault.DRUM_SLIP and st.state == DrumState.FAULT
            assert rig.clock.now() - t_slip < 1.25 * 0.3272 / 0.8 + 0.3  # the Mega's time, plus the poll
        finally:
            drum.close()
