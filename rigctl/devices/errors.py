"""Errors raised by the device clients (:mod:`rigctl.devices.drum`, :mod:`rigctl.devices.taxel_stream`).

Every error says what went wrong in the rig's own terms: which register, which value and unit, which limit.
"""

from __future__ import annotations

from typing import Any

# the errors of any drum controller (and the setpoint check's) are the contract's: rigctl.core.drum
from rigctl.core.drum import (
    DrumError as DrumError,
    DrumFault as DrumFault,
    DrumReset as DrumReset,
    DrumState,
    DrumTimeout as DrumTimeout,
    DrumWaitAborted as DrumWaitAborted,
    SetpointRangeError as SetpointRangeError,
    describe_faults as describe_faults,
)


class ModbusExceptionError(DrumError):
    """The Mega answered a request with a Modbus exception response.

    Attributes
    ----------
    register : str
        Name of the (first) register addressed, e.g. ``"SPEED_SETPOINT_0P1MMS"`` (``"holding 99"`` if unknown).
    function_code : int
        Modbus function code of the request (3, 4, 6 or 16).
    exception_code : int
        1 = illegal function, 2 = illegal data address, 3 = illegal data value (spec section 2).
    """

    EXCEPTION_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value", 4: "device failure"}

    def __init__(self, register: str, function_code: int, exception_code: int, value: Any = None) -> None:
        self.register = register
        self.function_code = function_code
        self.exception_code = exception_code
        self.value = value
        name = self.EXCEPTION_NAMES.get(exception_code, "unknown exception")
        what = f" writing {value}" if value is not None else ""  # str: a numpy value reads as its number
        super().__init__(
            f"Modbus exception {exception_code} ({name}) from the drum controller on register {register}"
            f"{what} (function {function_code})"
        )


class DrumNotHomed(ModbusExceptionError):
    """RUN or PRESS was refused because the controller is NOT_HOMED (after a reset, an e-stop or a failed HOME):
    the actuator's position is unknown until HOME succeeds."""

    def __init__(self, register: str, function_code: int, exception_code: int, value: Any = None) -> None:
        super().__init__(register, function_code, exception_code, value)
        self.args = (f"{self.args[0]}: the controller is NOT_HOMED (it was reset, e-stopped or HOME failed since it "
                     "was last homed): HOME it first",)


class DrumHomeRefused(ModbusExceptionError):
    """HOME was refused (docs/wire-protocol.md 2.4's command table and its guards), and why, in the operator's
    words, from the controller's state when it refused (``state``, a :class:`rigctl.core.drum.DrumState` value): while
    it moves or presses (STOP first), in FAULT (acknowledge first), or NOT_HOMED with the load cell loaded past
    FORCE_LIMIT_G + 2 x FORCE_TOLERANCE_G (HOME from an unknown position never moves into a load, spec 2.11: issue
    75's reversed actuator after a reset under 1,450 g with the cell's zero 250 g off the stored one was refused so,
    and the operator read only "Modbus exception 3")."""

    def __init__(self, register: str, function_code: int, exception_code: int, value: Any = None,
                 state: int = -1) -> None:
        super().__init__(register, function_code, exception_code, value)
        self.state = state
        if state == DrumState.NOT_HOMED:
            why = ("the load cell reads the sensor loaded past FORCE_LIMIT_G + 2 x FORCE_TOLERANCE_G (against its "
                   "tare, or after a reset the zero stored with the calibration), and HOME from an unknown position "
                   "never moves into a load: nothing moved. Take the load off by hand: switch the rig off, turn the "
                   "actuator's lead screw away from the sensor until nothing presses it, switch on and start again. "
                   "If nothing presses the sensor and HOME is still refused, the load cell's zero has moved since the "
                   "calibration (a mount changed, the cell overloaded): recalibrate it (rigctl calibrate loadcell)")
        elif state == DrumState.FAULT:
            why = "a fault is latched: acknowledge it first (its cause found), then start again"
        elif state in (DrumState.HOMING, DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING):
            why = (f"the controller is {DrumState(state).name}: STOP first (the release backs the actuator off), "
                   "then HOME")
        else:
            why = "the controller refused it in its present state"
        self.args = (f"HOME refused: {why} ({self.args[0]})",)


class DrumContactTooStiff(ModbusExceptionError):
    """RUN or PRESS was refused because the contact stiffness the first press measured (g/mm) is more than the force
    loop holds with its gains (spec 2.10, fault CONTACT_STIFFNESS)."""

    def __init__(self, register: str, function_code: int, exception_code: int, value: Any = None,
                 stiffness_g_per_mm: int = 0, max_g_per_mm: int = 0) -> None:
        super().__init__(register, function_code, exception_code, value)
        self.stiffness_g_per_mm, self.max_g_per_mm = stiffness_g_per_mm, max_g_per_mm
        self.args = (f"{self.args[0]}: the contact is too stiff for the force loop ({stiffness_g_per_mm} g/mm "
                     f"measured, its gains hold up to {max_g_per_mm} g/mm): use a softer mount or slower gains (the "
                     "rig config's force_loop block)",)


class TaxelStreamError(Exception):
    """The taxel streamer (Uno) could not be opened, did not send its banner, or answered nonsense."""


class TaxelLinkLost(TaxelStreamError):
    """The taxel streamer's port vanished or failed while open (cable pulled, board reset, I/O error): what
    :class:`rigctl.devices.taxel_stream.TaxelStream` reports to ``on_error`` and keeps in ``last_error``, whatever the
    operating system or pyserial raised (that error is ``__cause__``)."""
