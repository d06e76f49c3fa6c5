"""The model rig's drum controller's EEPROM (:class:`EmulatedEeprom`): what ``mega_drum.cpp``'s ``calib_load`` /
``calib_save`` and its boot counter keep in the Mega's EEPROM (the calibration record with its CRC, firmware 1.2's
with the tare's raw zero, docs/wire-protocol.md 2.7 and 2.11), in memory or a JSON file. Glue of
:class:`rigctl.simulation.controller.MegaController`: the controller's rules are controller.c's."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR

__all__ = ["EmulatedEeprom"]

_DEFAULT_SCALE_X100 = wire.join_s32(wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100_HI][2],
                                    wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100_LO][2])


class EmulatedEeprom:
    """The calibration record and the boot counter.

    Parameters
    ----------
    path : JSON file holding them (read now, written at every change), or None: in memory.

    Attributes
    ----------
    data : ``{"calibration": record or None (erased), "boot_count": cold boots (0xFFFF erased), "safety": the safety
        record or None (:attr:`safety`)}``; a calibration record is ``{"scale_x100", "actuator_steps_per_mm",
        "zero_raw" (optional), "stiffness_g_per_mm" (optional: the contact's stiffness stored with the calibration,
        spec 2.12), "crc"}``.
    """

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path else None
        self.data: dict[str, Any] = {"calibration": None, "boot_count": 0xFFFF, "safety": None}
        #: the safety record's writes so far (``safety_save`` writes only when it changes: the wear tests)
        self.safety_writes = 0
        self._read_file()

    @staticmethod
    def _record_crc(rec: dict) -> int:
        zero = rec.get("zero_raw")  # firmware 1.2's record carries the tare's raw zero (spec 2.11)
        stiffness = rec.get("stiffness_g_per_mm")  # firmware 1.5's the contact's stiffness (spec 2.12)
        return wire.crc16(int(rec["scale_x100"]).to_bytes(4, "little", signed=True)
                          + int(rec["actuator_steps_per_mm"]).to_bytes(2, "little")
                          + (b"" if zero is None else int(zero).to_bytes(4, "little", signed=True))
                          + (b"" if stiffness is None else int(stiffness).to_bytes(2, "little")))

    def valid_calibration(self) -> dict | None:
        """The stored record if its CRC holds and its values are usable (``calib_load``), else None."""
        rec = self.data["calibration"]
        if not isinstance(rec, dict):
            return None
        try:
            ok = rec["crc"] == self._record_crc(rec) and rec["scale_x100"] != 0 and rec["actuator_steps_per_mm"] > 0
        except (KeyError, TypeError, ValueError, OverflowError):
            return None
        return rec if ok else None

    def _read_file(self) -> None:
        if not (self.path and self.path.exists()):
            return
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return  # unreadable: an erased EEPROM
        if "calibration" in data:
            self.data["calibration"] = data["calibration"]
        elif HR.LOADCELL_SCALE_X100.name in data:  # firmware 1.0's record (no checksum in the file)
            rec = {"scale_x100": int(data[HR.LOADCELL_SCALE_X100.name]),
                   "actuator_steps_per_mm": int(data.get(HR.ACTUATOR_STEPS_PER_MM.name, 400))}
            rec["crc"] = self._record_crc(rec)
            self.data["calibration"] = rec
        self.data["boot_count"] = int(data.get("boot_count", 0xFFFF)) & 0xFFFF
        safety = data.get("safety")
        if isinstance(safety, dict) and {"reset_held", "ratchet_g"} <= set(safety):
            self.data["safety"] = {"reset_held": int(bool(safety["reset_held"])), "ratchet_g": int(safety["ratchet_g"])}

    def _write_file(self) -> None:
        if self.path:
            self.path.write_text(json.dumps(self.data))

    @property
    def boot_count(self) -> int:
        """Cold boots counted (0xFFFF: erased)."""
        return int(self.data["boot_count"])

    def count_cold_boot(self) -> None:
        """A cold boot (power-on, brown-out): the counter + 1, written."""
        self.data["boot_count"] = (self.data["boot_count"] + 1) & 0xFFFF
        self._write_file()

    @property
    def safety(self) -> dict[str, int]:
        """The safety record (firmware 1.5, ``ee_safety``): ``reset_held`` (a RESET latch not yet cleared) and
        ``ratchet_g`` (the load ratchet, g); zeros when none is stored."""
        return dict(self.data["safety"] or {"reset_held": 0, "ratchet_g": 0})

    def save_safety(self, reset_held: int, ratchet_g: int) -> None:
        """``safety_save``: the record written when it differs from the one stored (none stored and nothing to
        store: no write)."""
        rec = {"reset_held": int(bool(reset_held)), "ratchet_g": int(ratchet_g)}
        if rec == self.safety and (self.data["safety"] is not None or not any(rec.values())):
            return
        self.data["safety"] = rec
        self.safety_writes += 1
        self._write_file()

    def save(self, scale_x100: int, actuator_steps_per_mm: int, zero_raw: int | None,
             stiffness_g_per_mm: int = 0) -> None:
        """``calib_save``: the record of these values (``zero_raw`` None: none known; ``stiffness_g_per_mm`` 0: none
        stored), with its CRC."""
        rec: dict[str, int] = {"scale_x100": int(scale_x100), "actuator_steps_per_mm": int(actuator_steps_per_mm)}
        if zero_raw is not None:
            rec["zero_raw"] = int(zero_raw)
        rec["stiffness_g_per_mm"] = int(stiffness_g_per_mm)
        rec["crc"] = self._record_crc(rec)
        self.data["calibration"] = rec
        self._write_file()

    def corrupt(self, actuator_steps_per_mm: int) -> None:
        """Fault injection: flip a bit of the stored calibration (its checksum fails at the next boot)."""
        rec = self.valid_calibration() or {"scale_x100": _DEFAULT_SCALE_X100,
                                           "actuator_steps_per_mm": actuator_steps_per_mm, "crc": 0}
        self.data["calibration"] = dict(rec, scale_x100=rec["scale_x100"] ^ 0x10)
        self._write_file()
