"""The virtual drum controller's emulated EEPROM (the firmware's calibration record with its CRC, firmware 1.2's with the
tare's raw zero, docs/wire-protocol.md 2.11; the boot counter), in memory or a JSON file: :class:`EmulatedEeprom`, a
part of :class:`rigctl.simulation.controller.MegaController`."""

from __future__ import annotations

import json
import threading
from pathlib import Path

from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR

__all__ = ["EmulatedEeprom"]

_DEFAULT_SCALE_X100 = wire.join_s32(wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100_HI][2],
                                    wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100_LO][2])


class EmulatedEeprom:
    """The calibration record and the boot counter; the state they use is :class:`MegaController`'s."""

    eeprom: dict
    eeprom_path: Path | None
    holding: dict[int, int]
    tared: bool
    calibration_defaults: bool
    _tare_raw: int
    _zero_raw: int | None
    _lock: threading.RLock

    @property
    def scale_x100(self) -> int:  # (MegaController's)
        raise NotImplementedError

    @staticmethod
    def _record_crc(rec: dict) -> int:
        zero = rec.get("zero_raw")  # firmware 1.2's record carries the tare's raw zero (spec 2.11)
        return wire.crc16(int(rec["scale_x100"]).to_bytes(4, "little", signed=True)
                          + int(rec["actuator_steps_per_mm"]).to_bytes(2, "little")
                          + (b"" if zero is None else int(zero).to_bytes(4, "little", signed=True)))

    def _valid_calibration(self) -> dict | None:
        rec = self.eeprom["calibration"]
        if not isinstance(rec, dict):
            return None
        try:
            ok = rec["crc"] == self._record_crc(rec) and rec["scale_x100"] != 0 and rec["actuator_steps_per_mm"] > 0
        except (KeyError, TypeError, ValueError, OverflowError):
            return None
        return rec if ok else None

    def _read_eeprom_file(self) -> None:
        if not (self.eeprom_path and self.eeprom_path.exists()):
            return
        try:
            data = json.loads(self.eeprom_path.read_text())
        except (OSError, ValueError):
            return  # unreadable: an erased EEPROM
        if "calibration" in data:
            self.eeprom["calibration"] = data["calibration"]
        elif HR.LOADCELL_SCALE_X100.name in data:  # firmware 1.0's record (no checksum in the file)
            rec = {"scale_x100": int(data[HR.LOADCELL_SCALE_X100.name]),
                   "actuator_steps_per_mm": int(data.get(HR.ACTUATOR_STEPS_PER_MM.name, 400))}
            rec["crc"] = self._record_crc(rec)
            self.eeprom["calibration"] = rec
        self.eeprom["boot_count"] = int(data.get("boot_count", 0xFFFF)) & 0xFFFF

    def _write_eeprom_file(self) -> None:
        if self.eeprom_path:
            self.eeprom_path.write_text(json.dumps(self.eeprom))

    def _save_eeprom(self) -> None:
        zero = self._tare_raw if self.tared else self._zero_raw  # the tare in force (spec 2.11)
        rec = {"scale_x100": self.scale_x100, "actuator_steps_per_mm": self.holding[HR.ACTUATOR_STEPS_PER_MM]}
        if zero is not None:
            rec["zero_raw"] = int(zero)
            self._zero_raw = int(zero)
        rec["crc"] = self._record_crc(rec)
        self.eeprom["calibration"] = rec
        self.calibration_defaults = False
        self._write_eeprom_file()

    def corrupt_eeprom(self) -> None:
        """Fault-injection hook: flip a bit of the stored calibration (its checksum fails at the next boot)."""
        with self._lock:
            rec = self._valid_calibration() or {"scale_x100": _DEFAULT_SCALE_X100,
                                                "actuator_steps_per_mm": self.holding[HR.ACTUATOR_STEPS_PER_MM],
                                                "crc": 0}
            rec = dict(rec, scale_x100=rec["scale_x100"] ^ 0x10)
            self.eeprom["calibration"] = rec
            self._write_eeprom_file()

