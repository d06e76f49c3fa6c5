"""Fault injection on the firmware under simavr (``--hil``): :class:`HilFaults`, the harness's side of
:class:`rigctl.core.faults.FaultInjector` for :class:`rigctl.simulation.hil.HilRig`.

Each fault acts where the real one would, through the harness's stdin commands (arduino/simavr/rigctl_simavr.c): the
e-stop contact, the reset pin, the load cell's sign, the actuator motor's coil pair, the host's USB link to the Mega,
the taxels' source impedance, the HX711's SCK wire and its output (frozen), the contact's stiffness (a plate swap),
the EEPROM (a brown-out while writing it). The schedule runs on the Mega's simulated time (its ``TEL`` reports). Commands are sent
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
}

#: faults the harness does not model, and why
_REFUSED: dict[str, str] = {
    "hx711-10sps": "the harness's HX711 rate is fixed when it starts (use a rig config with mechanics.hx711_rate_sps "
                   "= 10)",
    "taxel-link-drop": "the Uno's link cannot be cut in the harness (use --sim)",
    "reversed-drum": "the taxels rendered for the Uno follow the Mega's drum steps, not a drum turning backwards "
                     "(use --sim)",
}


class HilFaults:
    """Injects :mod:`rigctl.core.faults` faults into the harnesses of one HIL rig.

    Parameters
    ----------
    send_mega : ``send_mega(command)`` writes one stdin command to the Mega's harness.
    send_uno : the same for the Uno's (None when the rig runs the Mega alone: ``taxel-ohm`` refused).
    taxel_ohm : the taxels' source impedance to restore when ``taxel-ohm`` ends, Ohm.
    calibration_offset : ``calibration_offset()`` is the calibration record's EEPROM address (``eeprom-corrupt``
        flips a byte of its scale; None: refused).

    Attributes
    ----------
    active : the names of the faults active now.
    """

    def __init__(self, send_mega: Callable[[str], object], send_uno: Callable[[str], object] | None,
                 taxel_ohm: float, *, calibration_offset: Callable[[], int] | None = None) -> None:
        self.send_mega, self.send_uno, self.taxel_ohm = send_mega, send_uno, float(taxel_ohm)
        self.calibration_offset = calibration_offset
        self.active: set[str] = set()

    def arm(self, specs: Sequence[FaultSpec], t0_s: float, *, power_on: bool = False) -> FaultSchedule:
        """A schedule of ``specs`` from the Mega's simulated ``t0_s``; ``power_on``: the ``FAULT@0`` ones applied now
        and the Mega powered on again with them (:class:`rigctl.core.faults.FaultInjector`)."""
        schedule = FaultSchedule(specs, self.apply_fault)
        schedule.start(t0_s)
        if power_on:
            schedule.due(t0_s)
            self.send_mega("poweron")
        return schedule

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why the harness cannot model ``spec`` (None when it can)."""
        if spec.name in _REFUSED:
            return _REFUSED[spec.name]
        if spec.name == "taxel-ohm" and self.send_uno is None:
            return "this HIL rig runs the Mega alone (no taxels)"
        if spec.name == "eeprom-corrupt" and self.calibration_offset is None:
            return "this HIL rig does not know where its Mega keeps the calibration"
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
