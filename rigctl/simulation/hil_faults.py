"""Fault injection on the firmware under simavr (``--hil``): :class:`HilFaults`, the harness's side of
:class:`rigctl.core.faults.FaultInjector` for :class:`rigctl.simulation.hil.HilRig`.

Each fault acts where the real one would, through the harness's stdin commands (arduino/simavr/rigctl_simavr.c): the
e-stop contact, the reset pin, the load cell's sign, the actuator motor's coil pair, the host's USB link to the Mega,
the taxels' source impedance. The schedule runs on the Mega's simulated time (its ``TEL`` reports). Commands are sent
without waiting for the harness's acknowledgement: they are applied from the thread that reads the harness's reports.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rigctl.core.faults import FaultSpec

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
}

#: faults the harness does not model, and why
_REFUSED: dict[str, str] = {
    "hx711-10sps": "the harness's HX711 rate is fixed when it starts (use a rig config with mechanics.hx711_rate_sps "
                   "= 10)",
    "taxel-link-drop": "the Uno's link cannot be cut in the harness (use --sim)",
    "reversed-drum": "the taxels rendered for the Uno follow the Mega's drum steps, not a drum turning backwards "
                     "(use --sim)",
    **{name: "not modelled by the harness yet (issue 55)"
       for name in ("hx711-sck-broken", "hx711-frozen", "contact-stiffness", "eeprom-corrupt")},
}


class HilFaults:
    """Injects :mod:`rigctl.core.faults` faults into the harnesses of one HIL rig.

    Parameters
    ----------
    send_mega : ``send_mega(command)`` writes one stdin command to the Mega's harness.
    send_uno : the same for the Uno's (None when the rig runs the Mega alone: ``taxel-ohm`` refused).
    taxel_ohm : the taxels' source impedance to restore when ``taxel-ohm`` ends, Ohm.

    Attributes
    ----------
    active : the names of the faults active now.
    """

    def __init__(self, send_mega: Callable[[str], None], send_uno: Callable[[str], None] | None,
                 taxel_ohm: float) -> None:
        self.send_mega, self.send_uno, self.taxel_ohm = send_mega, send_uno, float(taxel_ohm)
        self.active: set[str] = set()

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why the harness cannot model ``spec`` (None when it can)."""
        if spec.name in _REFUSED:
            return _REFUSED[spec.name]
        if spec.name == "taxel-ohm" and self.send_uno is None:
            return "this HIL rig runs the Mega alone (no taxels)"
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
        elif name == "slip":
            self.send_mega(f"drum slip {(spec.value or 0.0) / 100.0:g}" if active else "drum ok")
        elif name == "taxel-ohm" and self.send_uno is not None:
            ohm = spec.value if active and spec.value is not None else self.taxel_ohm
            self.send_uno(f"taxel_ohm -1 {float(ohm)}")
        else:
            raise ValueError(f"fault {spec} cannot be injected on the HIL rig")
