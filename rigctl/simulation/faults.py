"""Fault injection on the model rigs (in-process and simulated on ptys): :class:`ModelFaults`.

What the :class:`rigctl.core.faults.FaultInjector` of the rigs built on :class:`rigctl.simulation.model.RigModel` and
:class:`rigctl.simulation.controller.MegaController` applies: each ``--inject`` fault acts where the real one would, on the
model (the load cell's sign, the actuator's direction, a blocked or slipping drum, the HX711's rate), on the controller's
inputs (the e-stop contact, a reset) or on a link (the drum controller's port, the taxel board's). What the host
and the controller make of it is theirs: the controller latches its faults, the host's safety policy
(:mod:`rigctl.acquisition.safety`) pauses the run. The firmware under simavr (``--hil``) implements the same
hook with its harness.

``hx711-sck-broken`` and ``hx711-frozen`` act on the HX711 (the controller's reads, the model's conversions),
``contact-stiffness`` swaps the plate (the model's spring), ``eeprom-corrupt`` flips a bit of the controller's stored
calibration and browns it out.

The bill of materials' own faults (docs/safety.md, "FMEA") act on the model's physics: ``cell-gain`` and
``cell-offset`` on the load cell's signal, ``coupling-slip`` and ``steps-lost`` on the actuator's travel,
``hx711-dout-noise`` on the bits read, ``home-switch`` on the switch as its wire reads (the controller is given the
model's :attr:`~rigctl.simulation.model.RigModel.home_switch_closed`), ``driver-enable-stuck`` on the drivers'
enable, ``calibration-scale`` saves a wrong calibration (its checksum valid) and powers the controller on again.

``taxel-ohm`` sets the source impedance of the taxel board's analog front end
(:class:`rigctl.simulation.mux_rc.MuxFrontEnd`: the anti-alias RC and the mux the firmware discharges before each
input; the firmware's own ADC under simavr with ``--hil``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rigctl.core.drum import ResetCause
from rigctl.core.faults import FaultSpec
from rigctl.devices import wire
from rigctl.simulation.controller import MegaController
from rigctl.simulation.model import RigModel

__all__ = ["ModelFaults", "model_fault_refusal"]

log = logging.getLogger(__name__)


def model_fault_refusal(spec: FaultSpec) -> str | None:
    """Why no model rig can inject ``spec`` (None: they can)."""
    return None


def _save_wrong_calibration(controller: MegaController, scale: float) -> None:
    """The controller's stored calibration record rewritten with its load-cell scale ``scale`` times the one in force,
    its checksum valid (``calibration-scale``)."""
    with controller._lock:
        rec = controller.eeprom.valid_calibration() or {
            "scale_x100": controller.scale_x100,
            "actuator_steps_per_mm": controller.holding_register(wire.HoldingRegister.ACTUATOR_STEPS_PER_MM)}
        controller.eeprom.save(int(round(int(rec["scale_x100"]) * scale)), int(rec["actuator_steps_per_mm"]),
                               rec.get("zero_raw"), int(rec.get("stiffness_g_per_mm", 0)))


class ModelFaults:
    """Injects :mod:`rigctl.core.faults` faults into a model rig.

    Parameters
    ----------
    controller, model : the rig's drum controller logic and physics.
    drum_link : ``drum_link(up)`` cuts (False) or restores (True) the host's link to the drum controller (the
        pty's bridge; in-process: :attr:`host_silent`, which the transport honours); None: ``host-silence`` refused.
    taxel_link : ``taxel_link(up)`` drops or restores the taxel board's link; None: ``taxel-link-drop`` refused.

    Attributes
    ----------
    host_silent : True while ``host-silence`` is active (the in-process transport then answers nothing).
    active : the names of the faults active now.
    started_s : each fault's name -> the model's time (s) it first started (the advice walker judges the first latch
        after it: issue 75 item 4).
    """

    def __init__(self, controller: MegaController, model: RigModel, *,
                 drum_link: Callable[[bool], None] | None = None,
                 taxel_link: Callable[[bool], None] | None = None) -> None:
        self.controller, self.model = controller, model
        self.drum_link, self.taxel_link = drum_link, taxel_link
        self.host_silent = False
        self.active: set[str] = set()
        self.started_s: dict[str, float] = {}
        self._stiffness_g_per_mm = model.config.mechanics.contact_stiffness_g_per_mm  # the rig's own plate

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why this rig cannot model ``spec`` (None when it can)."""
        why = model_fault_refusal(spec)
        if why:
            return why
        if spec.name == "host-silence" and self.drum_link is None:
            return "this rig's drum link cannot be cut"
        if spec.name == "taxel-link-drop" and self.taxel_link is None:
            return "this rig's taxel link cannot be cut"
        return None

    def apply_fault(self, spec: FaultSpec, active: bool) -> None:
        """Start (``active``) or end ``spec`` now."""
        name = spec.name
        log.warning("injected fault %s: %s", spec, "starts" if active else "ends")
        if active:
            self.active.add(name)
            self.started_s.setdefault(name, float(self.model.time_s))
        else:
            self.active.discard(name)
        c, m = self.controller, self.model
        if name == "estop":
            c.set_estop(active)
        elif name == "reset":
            c.reset(ResetCause.EXTERNAL)
        elif name == "hx711-10sps":
            m.set_hx711_rate(10.0)
            c.reset(ResetCause.POWER_ON)  # the board comes up with the RATE pin low: the boot measures 10 SPS
        elif name == "reversed-cell":
            m.loadcell_sign = -1 if active else 1
        elif name == "reversed-actuator":
            m.actuator_sign = -1 if active else 1
        elif name == "reversed-drum":
            m.drum_sign = -1 if active else 1
        elif name == "stall":
            m.drum_blocked = active
        elif name == "slip":
            m.drum_slip = (spec.value or 0.0) / 100.0 if active else 0.0
        elif name == "host-silence" and self.drum_link is not None:
            self.host_silent = active
            self.drum_link(not active)
        elif name == "taxel-ohm":  # the taxel board's front end (rigctl.simulation.mux_rc); ideal again at the end
            m.front_end.source_ohm = float(spec.value or 0.0) if active else 0.0
        elif name == "hx711-sck-broken":  # DOUT held low: every read 0, as fast as the firmware polls
            c.break_hx711_sck(active)
        elif name == "hx711-frozen":
            m.freeze_hx711(active)
        elif name == "contact-stiffness":  # a plate swap (the rig's own plate again at the end)
            m.set_contact_stiffness(spec.value if active and spec.value else self._stiffness_g_per_mm)
        elif name == "home-switch":  # the switch as its wire reads, for the controller (its own reading: the model's)
            m.home_switch_stuck = bool(spec.value) if active else None
            if not getattr(c, "_reads_model_home_switch", False):
                c._home_switch = lambda: m.home_switch_closed  # type: ignore[method-assign]
                c._reads_model_home_switch = True  # type: ignore[attr-defined]
        elif name == "cell-gain":
            m.loadcell_gain = float(spec.value or 1.0) if active else 1.0
        elif name == "cell-offset":
            m.loadcell_offset_g = float(spec.value or 0.0) if active else 0.0
        elif name == "coupling-slip":
            m.actuator_slip = (spec.value or 0.0) / 100.0 if active else 0.0
        elif name == "steps-lost":
            m.actuator_lost = (spec.value or 0.0) / 100.0 if active else 0.0
        elif name == "hx711-dout-noise":
            m.hx711_dout_noise = float(spec.value or 0.0) if active else 0.0
        elif name == "driver-enable-stuck":
            m.driver_enable_stuck = active
        elif name == "calibration-scale":  # a wrong calibration saved, its checksum valid; then a power cycle
            _save_wrong_calibration(c, float(spec.value or 1.0))
            c.reset(ResetCause.POWER_ON)
        elif name == "eeprom-corrupt":  # a brown-out while the EEPROM is written: the record fails its checksum
            c.corrupt_eeprom()
            c.reset(ResetCause.BROWN_OUT)
        elif name == "taxel-link-drop" and self.taxel_link is not None:
            self.taxel_link(not active)
        else:  # refused before the schedule was armed (fault_refusal)
            raise ValueError(f"fault {spec} cannot be injected on this rig")
