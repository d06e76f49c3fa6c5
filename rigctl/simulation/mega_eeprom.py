"""The Mega firmware's EEPROM as the simavr harness holds it: where an EEMEM variable lives in the image and the
calibration record's bytes (mega_drum.cpp ``calib_t``), for :class:`rigctl.simulation.hil.HilRig` (a board that
starts calibrated, a corrupted record)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR, crc16

__all__ = ["CALIBRATION_SYMBOL", "EepromError", "calibration_record", "default_record", "eeprom_offset",
           "state_address"]

#: the firmware 1.2 calibration record's EEMEM variable (with the tare's raw zero, spec 2.11)
CALIBRATION_SYMBOL = "ee_calib3"
_CALIB_MAGIC = 0x525A  # "RZ"
_EEPROM_BASE = 0x810000  # avr-gcc places .eeprom there


class EepromError(Exception):
    """The image's symbol table cannot be read, or holds no such variable."""


def eeprom_offset(elf: Path | str, symbol: str = CALIBRATION_SYMBOL) -> int:
    """The EEPROM address of the image's EEMEM variable ``symbol``, from its symbol table (``avr-nm``,
    binutils-avr). Raises :class:`EepromError`."""
    try:
        out = subprocess.run(["avr-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise EepromError(f"cannot read the symbols of {elf}: {exc}") from None
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
    try:
        out = subprocess.run(["avr-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise EepromError(f"cannot read the symbols of {elf}: {exc}") from None
    m = re.search(r"^([0-9a-fA-F]+) [bBdD] (?:_ZL3ctl|ctl)(?:\.lto_priv\.\d+)?$", out, re.M)
    if m is None:
        raise EepromError(f"no controller (ctl) in {elf}")
    return int(m.group(1), 16) - _SRAM_BASE + 2 * wire.N_HOLDING


def calibration_record(scale_x100: int, actuator_steps_per_mm: int, zero_raw: int) -> bytes:
    """The calibration record as SAVE_CALIBRATION writes it (little-endian, 14 bytes): magic 0x525A, the signed
    load-cell scale (counts per g x 100), ACTUATOR_STEPS_PER_MM, the tare's raw zero (signed 32-bit; spec 2.11),
    CRC-16/MODBUS of the 12 bytes before it."""
    body = _CALIB_MAGIC.to_bytes(2, "little") + int(scale_x100).to_bytes(4, "little", signed=True) + \
        int(actuator_steps_per_mm).to_bytes(2, "little") + int(zero_raw).to_bytes(4, "little", signed=True)
    return body + crc16(body).to_bytes(2, "little")


def default_record(zero_raw: int) -> bytes:
    """The record of a board calibrated with the registers' defaults (the simulated rigs' true scale and steps/mm,
    tared on an unloaded cell whose raw reading is ``zero_raw``: the rig config's loadcell_offset_counts),
    what a simulated board's EEPROM holds from its first start (the virtual Mega's ``factory_calibrated``)."""
    scale = wire.join_s32(*(wire.holding_range(r)[2] for r in (HR.LOADCELL_SCALE_X100_HI, HR.LOADCELL_SCALE_X100_LO)))
    return calibration_record(scale, wire.holding_range(HR.ACTUATOR_STEPS_PER_MM)[2], zero_raw)
