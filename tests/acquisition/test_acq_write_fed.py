"""A session file written between two trials while the drum turns: the run's thread keeps the drum controller's
watchdog fed meanwhile (:meth:`rigctl.acquisition.rig.Rig.while_fed`). Beside four CPU hogs the README's quick check
latched WATCHDOG when the first trial's write (~0.6 CPU-s) ran on the thread that feeds it while its process's
heartbeat ran the simulated world on; on a bench a slow disk would do the same to the controller's 1 s."""

from __future__ import annotations

import time

import pytest

from rigctl.core.drum import DrumState, Fault
from rigctl.devices.wire import HoldingRegister as HR
from rigctl.rigs import open_rig


def _turning_under_a_200_ms_watchdog(rig) -> None:
    drum = rig.drum
    drum.write_holding(HR.WATCHDOG_MS, 200)
    if drum.read_status().state == DrumState.NOT_HOMED:
        drum.home()
        drum.wait_state([DrumState.IDLE], timeout_s=30)
    drum.set_speed(60.0)
    drum.run()
    drum.wait_state([DrumState.RUNNING], timeout_s=10)


def test_a_slow_write_beside_a_turning_drum_keeps_its_watchdog_fed(tmp_path):
    with open_rig("sim", seed=2, host_config_path=tmp_path / "rig.json") as rig:
        _turning_under_a_200_ms_watchdog(rig)
        t0 = rig.drum.clock.now()
        assert rig.while_fed(lambda: time.sleep(1.0) or 42) == 42  # 1 s of wall: a slow disk, a starved writer
        assert rig.drum.clock.now() - t0 > 0.5  # the world went on meanwhile
        st = rig.drum.read_status()
        assert st.state == DrumState.RUNNING and not st.faults & Fault.WATCHDOG, (st.state.name, repr(st.faults))
        with pytest.raises(ZeroDivisionError):  # what the work raises reaches the caller
            rig.while_fed(lambda: 1 / 0)
        # the same second on the feeding thread itself: the heartbeat runs the world past WATCHDOG_MS
        time.sleep(1.0)
        assert rig.drum.read_status().faults & Fault.WATCHDOG
