"""Fixtures of the drum-controller conformance suite: the same tests against both drum controllers we ship.

Backends (the ``controller`` fixture, one instance per test module, parametrized):

- ``sim``: the virtual Mega (:class:`rigctl.simulation.virtual_mega.VirtualMega`, pymodbus' RTU server on a real
  pty) inside the simulated rig (:class:`rigctl.simulation.rig.SimulatedRig`, real-time physics clock);
- ``hil``: the Mega firmware image (``arduino/mega_drum``) under simavr (:class:`rigctl.simulation.hil.HilRig`, the
  Mega alone: the Uno is not needed and would double the CPU), marked ``hil``.

Both are driven through the host's :class:`rigctl.devices.drum.DrumClient` on the real pymodbus serial client
(fixture ``drum``); the tests reach past it (a plain pymodbus master, raw bytes) only for requests the DrumClient
refuses to send, so that the controller's own refusal is what is tested.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.errors import DrumError, ModbusExceptionError
from rigctl.devices.wire import DrumState, HoldingRegister as HR
from rigctl.rigs import drum_answer_timeout_s

from ..conftest import skip_or_fail


@dataclass
class Controller:
    """One drum controller under test, as the suite sees it.

    Attributes
    ----------
    name : "sim" or "hil"
    port : the Modbus RTU port (500000 8N1, device id 1)
    place_mass : ``g -> None``, an external force of ``g`` g on the load cell (0 removes it)
    actuator_mm : ``() -> mm``, where the actuator physically is (the physics model, or the harness's step count)
    load_g : ``() -> g``, the force physically on the load cell (the model's reading, or the harness's spring)
    drum_travel_mm : ``() -> mm``, the drum's surface travel so far (the model, or the STEP pulses on the pin)
    clock_s : ``() -> s``, the controller's own clock, read without a request: the rig's one clock, which the host
        shares with the boards (the model's or simavr's simulated time: docs/architecture.md "Time on a simulated
        rig"; a starved host pauses it)
    power_up_holding, power_up_inputs : the holding and input registers read right after power-up, before any
        test wrote anything
    reset : ``cause -> None``, reset the MCU while the mechanics stay as they are (a reset under load): "external"
        (reset pin), "brownout" or "poweron"
    set_estop : ``opened -> None``, open (pressed, broken wire) or close the e-stop contact
    set_polarity : ``sign -> None``, mount the load cell the right way (+1) or reversed (-1)
    break_home_switch : ``broken -> None``, the home switch never closes (a broken wire) or works again
    reverse_actuator : ``reversed -> None``, swap the actuator motor's coil pair (it turns the other way) or mend it
    corrupt_eeprom : ``() -> None``, flip a bit of the stored calibration record (its checksum fails at the next boot)
    hang : ``() -> None``, make the controller's main loop hang (the firmware's test image, the virtual Mega's hook)
    drivers_enabled : ``() -> bool``, the stepper drivers' EN as the hardware sees it (the harness's pin, the virtual
        Mega's output)
    mechanics_s : ``() -> s``, the time of the mechanics that :attr:`actuator_mm` reports (the physics model's, which
        falls behind the host's clock when its thread is starved; the harness's simulated time), to time motion on
    actuator_at : ``() -> (s, mm)``, :attr:`mechanics_s` and :attr:`actuator_mm` of one state of the mechanics (two
        calls may see two: a harness report between them, a physics step), to time motion by
    """

    name: str
    port: str
    place_mass: Callable[[float], None]
    actuator_mm: Callable[[], float]
    load_g: Callable[[], float]
    drum_travel_mm: Callable[[], float]
    clock_s: Callable[[], float] = time.monotonic
    reset: Callable[[str], None] = lambda cause: None
    set_estop: Callable[[bool], None] = lambda opened: None
    set_polarity: Callable[[int], None] = lambda sign: None
    break_home_switch: Callable[[bool], None] = lambda broken: None
    reverse_actuator: Callable[[bool], None] = lambda reversed_: None
    corrupt_eeprom: Callable[[], None] = lambda: None
    hang: Callable[[], None] = lambda: None
    drivers_enabled: Callable[[], bool] = lambda: True
    mechanics_s: Callable[[], float] = time.monotonic
    actuator_at: Callable[[], tuple[float, float]] = lambda: (time.monotonic(), 0.0)
    power_up_holding: list[int] = field(default_factory=list)
    power_up_inputs: list[int] = field(default_factory=list)
    rig: Any = None


def _open_client(ctl: Controller) -> DrumClient:
    """The host's DrumClient on ``ctl``, with the answer timeout ``open_rig`` gives a rig of its kind, on the rig's
    clock (found by the port: its waits, deadlines and answer timeout in the controller's time)."""
    return DrumClient(ctl.port, timeout_s=drum_answer_timeout_s(ctl.name), retries=2, poll_s=0.02).open()


def _read_power_up(ctl: Controller) -> None:
    drum = _open_client(ctl)
    try:
        deadline = ctl.clock_s() + 10.0
        while True:  # the firmware boots and tares its load cell on the first HX711 reading
            try:
                ctl.power_up_inputs = drum.read_inputs(0, wire.N_INPUT)
                break
            except DrumError:
                if ctl.clock_s() > deadline:
                    raise
        ctl.power_up_holding = drum.read_holdings(0, wire.N_HOLDING)
    finally:
        drum.close()


_SIM_CAUSES = {"external": wire.ResetCause.EXTERNAL, "brownout": wire.ResetCause.BROWN_OUT,
               "poweron": wire.ResetCause.POWER_ON}


def _start_sim(config=None, image: str = ""):
    from rigctl.simulation.rig import SimulatedRig

    rig = SimulatedRig(config, seed=3).start()
    model, mega = rig.model, rig.mega
    mech = model.config.mechanics
    counts_per_g = abs(mech.loadcell_counts_per_g)

    def set_polarity(sign: int) -> None:
        mech.loadcell_counts_per_g = counts_per_g * (-1 if sign < 0 else 1)

    return rig, Controller("sim", rig.drum_port, rig.place_mass, actuator_mm=lambda: model.actuator_mm,
                           load_g=lambda: model.force_g, drum_travel_mm=lambda: model.position_mm,
                           reset=lambda cause: mega.reset(_SIM_CAUSES[cause]), set_estop=mega.set_estop,
                           set_polarity=set_polarity, break_home_switch=mega.break_home_switch,
                           corrupt_eeprom=mega.corrupt_eeprom, hang=mega.hang_loop,
                           reverse_actuator=lambda r: setattr(model, "actuator_sign", -1 if r else 1),
                           drivers_enabled=lambda: mega.drivers_enabled, mechanics_s=lambda: model.time_s,
                           actuator_at=lambda: _model_actuator_at(model), clock_s=rig.clock.now, rig=rig)


def _model_actuator_at(model) -> tuple[float, float]:
    """The physics model's time and actuator position of one state: read again while a step came between (each
    property takes the model's lock, which a step holds throughout)."""
    while True:
        t, mm = model.time_s, model.actuator_mm
        if model.time_s == t:
            return t, mm


def _start_hil(config=None, image: str = "mega_drum"):
    from rigctl import firmware
    from rigctl.simulation import hil

    try:
        firmware.build()
    except firmware.FirmwareBuildError as exc:
        skip_or_fail(f"the firmware or the simavr harness cannot be built here: {exc}", str(exc))
    rig = hil.HilRig(config, live=False, with_uno=False, mega_image=image).start()
    return rig, Controller("hil", rig.drum_port, rig.bump, actuator_mm=lambda: rig.next_telemetry().act_mm,
                           load_g=lambda: rig.next_telemetry().force_g,
                           drum_travel_mm=lambda: rig.next_telemetry().drum_steps * rig.mm_per_step,
                           clock_s=rig.clock.now, reset=rig.reset_mega, set_estop=rig.set_estop,
                           set_polarity=rig.set_loadcell_polarity, break_home_switch=rig.break_home_switch,
                           corrupt_eeprom=rig.corrupt_eeprom, hang=rig.hang_loop,
                           reverse_actuator=rig.reverse_actuator, drivers_enabled=lambda: rig.next_telemetry().drivers_enabled,
                           mechanics_s=lambda: rig.next_telemetry().t_s, actuator_at=lambda: _report_actuator_at(rig),
                           rig=rig)


def _report_actuator_at(rig) -> tuple[float, float]:
    """The time and actuator position of one report of the Mega's harness (now or later)."""
    tel = rig.next_telemetry()
    return tel.t_s, tel.act_mm


@pytest.fixture(scope="module", params=["sim", pytest.param("hil", marks=pytest.mark.hil)])
def controller(request):
    """A freshly powered-up drum controller of each backend, shared by one test module. A module sets
    ``MEGA_IMAGE = "mega_drum_test"`` to run the firmware's test image (a hang input for the watchdog test) under
    simavr instead of the shipped one."""
    image = getattr(request.module, "MEGA_IMAGE", "mega_drum")
    rig, ctl = (_start_sim if request.param == "sim" else _start_hil)(image=image)
    try:
        _read_power_up(ctl)
        yield ctl
    finally:
        rig.close()


def home(drum: DrumClient) -> None:
    """HOME a NOT_HOMED controller (after power-up or a reset), as a rig does when it opens; wait for IDLE and for the
    HX711 rate the controller times at boot (until then it refuses PRESS and RUN)."""
    # first the HX711 rate the controller times at boot (spec 2.9: PRESS and RUN wait for it; a wrong rate faults)
    if drum.wait_hx711_rate(timeout_s=10.0).state == DrumState.NOT_HOMED:
        drum.home()
        drum.wait_state(DrumState.IDLE, timeout_s=30.0)


def restore(drum: DrumClient, ctl: Controller) -> None:
    """Bring the controller back to a clean, homed IDLE: no external force and no injected fault, stopped, fault
    cleared, the spec's default in every holding register (calibration too, not saved), actuator home, drum at rest.
    Raises if it cannot."""
    ctl.place_mass(0)
    ctl.set_estop(False)
    ctl.set_polarity(1)
    ctl.break_home_switch(False)
    ctl.reverse_actuator(False)
    drum.stop()
    clock = drum.clock  # the controller's (the drum fixture's client)
    deadline = clock.now() + 5.0
    while drum.read_status().state == DrumState.FAULT:
        try:
            drum.clear_fault()  # refused while the load cell still reads the removed force (next reading: 12.5 ms)
        except ModbusExceptionError:
            if clock.now() > deadline:
                raise
            drum.clock.sleep(0.05)
    defaults = [wire.holding_range(a)[2] for a in range(wire.N_HOLDING)]  # reserved addresses: 0
    # the contact's stiffness stored with the calibration stays (spec 2.12: the factory's, the scale check's reference)
    stiffness = wire.HoldingRegister.CALIBRATION_STIFFNESS_G_PER_MM
    defaults[stiffness] = ctl.power_up_holding[stiffness]
    drum.write_holdings(0, defaults)
    home(drum)
    drum.wait_released(timeout_s=15.0)
    deadline = clock.now() + 10.0
    while abs(drum.read_status().speed_mm_s) > 0:  # the drum decelerates to rest
        assert clock.now() < deadline, "the drum does not come to rest"
        drum.clock.sleep(0.02)


#: WATCHDOG_MS during the tests of other behaviour (the register's maximum): a test host starved for a second on a
#: loaded machine must not trip the watchdog there; the watchdog tests write their own
QUIET_WATCHDOG_MS = wire.HOLDING_RANGE[HR.WATCHDOG_MS][1]


@pytest.fixture
def drum(controller) -> DrumClient:
    """The host's DrumClient on ``controller``, homed (WATCHDOG_MS at :data:`QUIET_WATCHDOG_MS`), which is left homed
    and IDLE with default registers afterwards."""
    client = _open_client(controller)
    try:
        home(client)
        client.write_holding(HR.WATCHDOG_MS, QUIET_WATCHDOG_MS)
        yield client
        restore(client, controller)
    finally:
        client.close()
