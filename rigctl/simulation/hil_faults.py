"""Fault injection on the firmware under simavr (``--hil``): :class:`HilFaults`, the harness's side of
:class:`rigctl.core.faults.FaultInjector` for :class:`rigctl.simulation.hil.HilRig`.

Each fault acts where the real one would, through the harness's stdin commands (arduino/simavr/rigctl_simavr.c): the
e-stop contact, the reset pin, the load cell's sign, the actuator motor's coil pair, the host's USB link to the Mega,
the taxels' source impedance, the HX711's SCK wire and its output (frozen), the contact's stiffness (a plate swap),
the EEPROM (a brown-out while writing it, a wrong calibration saved), the HX711's RATE pin and its DOUT wire (bit
errors), the home switch's wire (stuck closed or open), the load cell's gain and zero, the actuator's coupling (a
slip that catches up) and its lost steps, the drivers' EN input (stuck active), the drum motor's coil pair (the
Uno's rendered taxels follow the drum's step count, not its reversed turn). The schedule runs on the Mega's simulated
time (its ``TEL`` reports). Commands are sent
without waiting for the harness's acknowledgement: they are applied from the thread that reads the harness's reports.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from rigctl.core.faults import FaultSchedule, FaultSpec

__all__ = ["HilFaults"]

log = logging.getLogger(__name__)

#: fault -> (the Mega harness's command when it starts, when it ends)
_MEGA_COMMANDS: dict[str, tuple[str, str]] = {
    "estop": ("estop open", "estop close"),
    "reset": ("reset", ""),
    "reversed-cell": ("polarity -1", "polarity 1"),
    "reversed-actuator": ("actuator reversed", "actuator ok"),
    "host-silence": ("link down", "link up"),
    "stall": ("drum slip 1", "drum ok"),
    "hx711-sck-broken": ("hx711 sck-broken", "hx711 ok"),
    "hx711-frozen": ("hx711 frozen", "hx711 ok"),
    "driver-enable-stuck": ("driver en-stuck", "driver ok"),
    "hx711-10sps": ("hx711 rate 10", ""),
    "reversed-drum": ("drum reversed", "drum forward"),
}
#: valued faults: name -> (the command's text for the value when it starts, the command when it ends)
_VALUED: dict[str, tuple[Callable[[float], str], str]] = {
    "home-switch": (lambda v: "homeswitch stuck" if v else "homeswitch broken", "homeswitch ok"),
    "cell-gain": (lambda v: f"cell gain {v:g}", "cell gain 1"),
    "cell-offset": (lambda v: f"cell offset {v:g}", "cell offset 0"),
    "coupling-slip": (lambda v: f"coupling slip {v / 100.0:g}", "coupling slip 0"),
    "steps-lost": (lambda v: f"steps lost {v / 100.0:g}", "steps lost 0"),
    "hx711-dout-noise": (lambda v: f"hx711 dout-noise {v:g}", "hx711 dout-noise 0"),
}

#: faults the harness does not model, and why
_REFUSED: dict[str, str] = {}


class HilFaults:
    """Injects :mod:`rigctl.core.faults` faults into the harnesses of one HIL rig.

    Parameters
    ----------
    send_mega : ``send_mega(command)`` writes one stdin command to the Mega's harness.
    send_uno : the same for the Uno's (None when the rig runs the Mega alone: ``taxel-ohm`` refused).
    taxel_ohm : the taxels' source impedance to restore when ``taxel-ohm`` ends, Ohm.
    calibration_offset : ``calibration_offset()`` is the calibration record's EEPROM address (``eeprom-corrupt``
        flips a byte of its scale; None: refused).
    calibration_record : ``calibration_record(x)`` is the record (bytes) of the board's calibration with its scale
        ``x`` times the true one, its checksum valid (``calibration-scale``; None: refused).

    Attributes
    ----------
    active : the names of the faults active now.
    """

    def __init__(self, send_mega: Callable[[str], object], send_uno: Callable[[str], object] | None,
                 taxel_ohm: float, *, calibration_offset: Callable[[], int] | None = None,
                 calibration_record: Callable[[float], bytes] | None = None) -> None:
        self.send_mega, self.send_uno, self.taxel_ohm = send_mega, send_uno, float(taxel_ohm)
        self.calibration_offset = calibration_offset
        self.calibration_record = calibration_record
        self.active: set[str] = set()

    def arm(self, specs: Sequence[FaultSpec], t0_s: float, *, power_on: bool = False) -> FaultSchedule:
        """A schedule of ``specs`` from the Mega's simulated ``t0_s``; ``power_on``: the ``FAULT@0`` ones applied now
        and the Mega powered on again with them (:class:`rigctl.core.faults.FaultInjector`)."""
        schedule = self.schedule(specs)
        self.start(schedule, t0_s, power_on=power_on)
        return schedule

    def schedule(self, specs: Sequence[FaultSpec]) -> FaultSchedule:
        """A schedule of ``specs`` applied here, not yet armed (:meth:`start`)."""
        return FaultSchedule(specs, self.apply_fault)

    def start(self, schedule: FaultSchedule, t0_s: float, *, power_on: bool = False) -> None:
        """Arm ``schedule`` from the Mega's simulated ``t0_s``; ``power_on``: its ``FAULT@0`` ones applied now and
        the Mega powered on again with them."""
        schedule.start(t0_s)
        if power_on:
            schedule.due(t0_s)
            self.send_mega("poweron")

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why the harness cannot model ``spec`` (None when it can)."""
        if spec.name in _REFUSED:
            return _REFUSED[spec.name]
        if spec.name == "taxel-ohm" and self.send_uno is None:
            return "this HIL rig runs the Mega alone (no taxels)"
        if spec.name in ("eeprom-corrupt", "calibration-scale") and self.calibration_offset is None:
            return "this HIL rig does not know where its Mega keeps the calibration"
        if spec.name == "calibration-scale" and self.calibration_record is None:
            return "this HIL rig cannot write its Mega's calibration"
        if spec.name == "taxel-link-drop" and self.send_uno is None:
            return "this HIL rig runs the Mega alone (no taxel link)"
        return None

    def apply_fault(self, spec: FaultSpec, active: bool) -> None:
        """Start (``active``) or end ``spec`` now. ValueError for a fault :meth:`fault_refusal` refuses."""
        name = spec.name
        log.warning("injected fault %s (HIL): %s", spec, "starts" if active else "ends")
        (self.active.add if active else self.active.discard)(name)
        if name in _MEGA_COMMANDS:
            command = _MEGA_COMMANDS[name][0 if active else 1]
            if command:
                self.send_mega(command)
        elif name in _VALUED:
            on, off = _VALUED[name]
            self.send_mega(on(float(spec.value or 0.0)) if active else off)
        elif name == "taxel-link-drop" and self.send_uno is not None:
            self.send_uno("link down" if active else "link up")
        elif name == "calibration-scale" and self.calibration_offset is not None and self.calibration_record:
            # a wrong calibration saved (its checksum valid), then a power cycle: the firmware boots with it
            record = self.calibration_record(float(spec.value or 1.0))
            self.send_mega(f"eeprom-write {self.calibration_offset()}:{record.hex()}")
        elif name == "contact-stiffness":  # the plate swapped for one of this stiffness (the rig's own at the end)
            self.send_mega(f"spring-k {float(spec.value or 0):g}" if active else "spring-k default")
        elif name == "eeprom-corrupt" and self.calibration_offset is not None:
            # a byte of the scale (past the magic word) flipped and a brown-out reset in the same step
            self.send_mega(f"eeprom-corrupt {self.calibration_offset() + 2}")
        elif name == "slip":
            self.send_mega(f"drum slip {(spec.value or 0.0) / 100.0:g}" if active else "drum ok")
        elif name == "taxel-ohm" and self.send_uno is not None:
            ohm = spec.value if active and spec.value is not None else self.taxel_ohm
            self.send_uno(f"taxel_ohm -1 {float(ohm)}")
        else:
            raise ValueError(f"fault {spec} cannot be injected on the HIL rig")
