"""Errors raised by the device clients (:mod:`rigctl.devices.drum`, :mod:`rigctl.devices.taxel_stream`).

Every error says what went wrong in the rig's own terms: which register, which value and unit, which limit.
"""

from __future__ import annotations

from typing import Any

from rigctl.devices import wire


class DrumError(Exception):
    """Base class of the drum-controller client's errors (I/O failure, exception response, timeout, fault)."""


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


class DrumTimeout(DrumError):
    """The drum controller did not answer, or did not reach the awaited state in time."""


class DrumFault(DrumError):
    """The drum controller latched a fault (state FAULT); ``faults`` holds the :class:`wire.Fault` bits."""

    def __init__(self, faults: wire.Fault, message: str = "") -> None:
        self.faults = wire.Fault(int(faults))
        names = describe_faults(self.faults)
        super().__init__((message + ": " if message else "") + f"drum controller fault: {names}")


class SetpointRangeError(ValueError):
    """A setpoint outside its allowed range was refused before anything was sent to the rig.

    Attributes
    ----------
    name : str     what was set (e.g. ``"speed"``)
    value : float  the refused value, in ``unit``
    unit : str     e.g. ``"mm/s"``, ``"g"``
    low, high : float  the allowed closed range, in ``unit``
    """

    def __init__(self, name: str, value: float, unit: str, low: float, high: float, reason: str = "") -> None:
        self.name, self.value, self.unit, self.low, self.high = name, value, unit, low, high
        extra = f" ({reason})" if reason else ""
        super().__init__(f"{name} {value:g} {unit} is outside the allowed range {low:g}-{high:g} {unit}{extra}")


class TaxelStreamError(Exception):
    """The taxel streamer (Uno) could not be opened, did not send its banner, or answered nonsense."""


class TaxelLinkLost(TaxelStreamError):
    """The taxel streamer's port vanished or failed while open (cable pulled, board reset, I/O error): what
    :class:`rigctl.devices.taxel_stream.TaxelStream` reports to ``on_error`` and keeps in ``last_error``, whatever the
    operating system or pyserial raised (that error is ``__cause__``)."""


def describe_faults(faults: int) -> str:
    """Names of the set fault bits in words, e.g. ``"FORCE_LIMIT (measured force exceeded FORCE_LIMIT_G)"``."""
    words = {
        wire.Fault.FORCE_LIMIT: "measured force exceeded FORCE_LIMIT_G",
        wire.Fault.WATCHDOG: "host went silent for longer than WATCHDOG_MS",
        wire.Fault.LOADCELL_TIMEOUT: "the load cell gave no reading for 200 ms",
        wire.Fault.ACTUATOR_TRAVEL: "actuator reached its end of travel without reaching the force setpoint",
    }
    parts = [f"{bit.name} ({text})" for bit, text in words.items() if int(faults) & int(bit)]
    return ", ".join(parts) if parts else "none"
