"""EEPROM wear (issue 39 item 8) under simavr, with the Mega's real bootloader and the DTR auto-reset of every port
opening: a port-open (warm) reset writes no EEPROM byte, its BOOT_COUNT counts in RAM (low byte +1); a power cycle
(SRAM lost) writes the boot counter once and moves BOOT_COUNT's high byte (docs/wire-protocol.md 2.7). The harness
counts the MCU's EEPROM writes (EECR's EEPE: ``TEL ... ee_writes=``). ~10 s."""

from __future__ import annotations

import pytest

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.wire import ResetCause
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation import hil

pytestmark = pytest.mark.hil


def _open_and_read(rig: hil.HilRig) -> int:
    """Open the Mega's port (the open resets it into its bootloader), read BOOT_COUNT once the sketch answers. The
    harness starts the board calibrated, as the simulated rigs (issue 38 part 5): no CALIBRATION_DEFAULTS."""
    with DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"), clock=rig.clock,
                    boot_wait_s=rig.drum_boot_wait_s, boot_quiet_s=rig.drum_boot_quiet_s) as drum:
        st = drum.read_status()
        assert not st.calibration_defaults
        return st.boot_count


def test_port_open_resets_write_no_eeprom_and_a_power_cycle_counts_once(fw_build):
    with hil.HilRig(bootloaders=True, live=False, with_uno=False) as rig:
        first = _open_and_read(rig)
        writes = rig.next_telemetry().ee_writes
        second = _open_and_read(rig)
        third = _open_and_read(rig)
        assert rig.next_telemetry().ee_writes == writes  # two port-open resets: no EEPROM byte written
        assert second == wire.boot_count_after(first, ResetCause.EXTERNAL)
        assert third == wire.boot_count_after(second, ResetCause.EXTERNAL)
        rig.reset_mega("poweron")
        # the bootloader's wait, then the sketch's cold boot, until it has counted itself (its EEPROM write), not only
        # started (the harness's APP line): a port opened in between resets the board before the sketch sets its
        # warm-boot record, and the next start counts cold once more (one cold boot, no warm one), as a real Mega would.
        # Waiting for APP alone, a host polling every 0.5 ms of simulated time met that in 2 runs of 3, the suite once in 9
        end = rig.clock.now() + 5.0
        while rig.next_telemetry().ee_writes == writes:
            assert rig.clock.now() < end, "the sketch did not count a boot after the power cycle"
            rig.clock.sleep(0.05)
        after = _open_and_read(rig)  # the power cycle (the EEPROM counter, once), then this open's warm reset
        assert after == wire.boot_count_after(wire.boot_count_after(third, ResetCause.POWER_ON), ResetCause.EXTERNAL)
        assert 1 <= rig.next_telemetry().ee_writes - writes <= 2  # the 16-bit counter: the bytes that changed
