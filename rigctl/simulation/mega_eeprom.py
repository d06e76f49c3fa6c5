"""The Mega firmware's EEPROM as the simavr harness holds it: where an EEMEM variable lives in the image and the
calibration record's bytes (mega_drum.cpp ``calib4_t``), for :class:`rigctl.simulation.hil.HilRig` (a board that
starts calibrated, a corrupted record)."""

from __future__ import annotations

import fcntl
import re
import subprocess
from pathlib import Path
from typing import IO

from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR, crc16

__all__ = ["CALIBRATION_SYMBOL", "EepromError", "calibration_record", "default_record", "eeprom_offset",
           "factory_stiffness", "state_address", "stored_stiffness"]

#: the firmware 1.5 calibration record's EEMEM variable (with the tare's raw zero, spec 2.11, and the contact's
#: stiffness, spec 2.12)
CALIBRATION_SYMBOL = "ee_calib4"
_CALIB_MAGIC = 0x524B  # "RK"
_EEPROM_BASE = 0x810000  # avr-gcc places .eeprom there


class EepromError(Exception):
    """The image's symbol table cannot be read, or holds no such variable."""


def _symbols(elf: Path | str) -> str:
    """The symbol table of ``elf`` (``avr-nm``), read under its build folder's lock, shared
    (:func:`rigctl.firmware.make` holds it exclusive while it builds: a CI run's avr-nm read mega_drum.elf while another
    worker's make relinked it, and failed twice). Raises :class:`EepromError`."""
    elf = Path(elf)
    try:
        lock: IO[str] | None = open(elf.parent / ".lock", "a")  # noqa: SIM115 - closed below
    except OSError:  # a folder this process cannot write (someone else's build): read it as it is
        lock = None
    try:
        if lock is not None:
            fcntl.flock(lock, fcntl.LOCK_SH)
        return subprocess.run(["avr-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise EepromError(f"cannot read the symbols of {elf}: {exc}") from None
    finally:
        if lock is not None:
            lock.close()


def eeprom_offset(elf: Path | str, symbol: str = CALIBRATION_SYMBOL) -> int:
    """The EEPROM address of the image's EEMEM variable ``symbol``, from its symbol table (``avr-nm``,
    binutils-avr). Raises :class:`EepromError`."""
    out = _symbols(elf)
    m = re.search(rf"^([0-9a-fA-F]+) \w \S*{re.escape(symbol)}\b", out, re.M)
    if m is None:
        raise EepromError(f"no {symbol} in {elf}")
    return int(m.group(1), 16) - _EEPROM_BASE


#: avr-gcc places .data and .bss at this address (the data space's 0 is 0x800000 in the ELF)
_SRAM_BASE = 0x800000


def state_address(elf: Path | str) -> int:
    """The data-space address of the controller's ``state`` byte in the Mega image (``mega_drum.cpp``'s ``static ctl_t
    ctl``; ``state`` follows the ``hreg`` array of :data:`rigctl.devices.wire.N_HOLDING` 16-bit registers,
    controller.h), from the image's symbol table (``avr-nm``): the harness's ``--state-addr``. Raises
    :class:`EepromError`."""
    out = _symbols(elf)
    m = re.search(r"^([0-9a-fA-F]+) [bBdD] (?:_ZL3ctl|ctl)(?:\.lto_priv\.\d+)?$", out, re.M)
    if m is None:
        raise EepromError(f"no controller (ctl) in {elf}")
    return int(m.group(1), 16) - _SRAM_BASE + 2 * wire.N_HOLDING


def calibration_record(scale_x100: int, actuator_steps_per_mm: int, zero_raw: int, stiffness_g_per_mm: int = 0) -> bytes:
    """The calibration record as SAVE_CALIBRATION writes it (little-endian, 16 bytes): magic 0x524B, the signed
    load-cell scale (counts per g x 100), ACTUATOR_STEPS_PER_MM, the tare's raw zero (signed 32-bit; spec 2.11), the
    contact's stiffness stored with it (g/mm, 0: none; spec 2.12), CRC-16/MODBUS of the 14 bytes before it."""
    body = _CALIB_MAGIC.to_bytes(2, "little") + int(scale_x100).to_bytes(4, "little", signed=True) + \
        int(actuator_steps_per_mm).to_bytes(2, "little") + int(zero_raw).to_bytes(4, "little", signed=True) + \
        int(stiffness_g_per_mm).to_bytes(2, "little")
    return body + crc16(body).to_bytes(2, "little")


def _default_scale() -> int:
    return wire.join_s32(*(wire.holding_range(r)[2] for r in (HR.LOADCELL_SCALE_X100_HI, HR.LOADCELL_SCALE_X100_LO)))


def factory_stiffness(contact_stiffness_g_per_mm: float, loadcell_counts_per_g: float) -> int:
    """The contact's stiffness a simulated board's factory calibration stored (spec 2.12): the rig's own plate as the
    probe measures it through the default scale (the true stiffness on a cell of the default counts per g; on a cell
    of another gain, which the factory calibrated with the default scale, scaled alike: a calibration wrong from the
    start, which only a reference mass catches)."""
    return stored_stiffness(contact_stiffness_g_per_mm * abs(loadcell_counts_per_g) * 100.0 / _default_scale())


def default_record(zero_raw: int, stiffness_g_per_mm: float = 0.0) -> bytes:
    """The record of a board calibrated with the registers' defaults (the simulated rigs' true scale and steps/mm,
    tared on an unloaded cell whose raw reading is ``zero_raw``: the rig config's loadcell_offset_counts, the contact's
    stiffness ``stiffness_g_per_mm`` stored: :func:`factory_stiffness`), what a simulated board's EEPROM holds from its
    first start (the virtual Mega's ``factory_calibrated``)."""
    return calibration_record(_default_scale(), wire.holding_range(HR.ACTUATOR_STEPS_PER_MM)[2], zero_raw,
                              stored_stiffness(stiffness_g_per_mm))


def stored_stiffness(stiffness_g_per_mm: float) -> int:
    """A contact's stiffness as CALIBRATION_STIFFNESS_G_PER_MM holds it (g/mm, rounded, within its register's range;
    spec 2.12)."""
    lo, hi, _ = wire.holding_range(HR.CALIBRATION_STIFFNESS_G_PER_MM)
    return max(lo, min(hi, int(round(stiffness_g_per_mm))))
