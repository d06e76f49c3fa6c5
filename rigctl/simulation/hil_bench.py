"""A bench of the drum controller's real firmware under simavr, for the fault rows of docs/safety.md (issue 75): one
HIL Mega (no Uno) with a truth log (the harness's spring: the true force, not the HX711's reading), its Modbus client,
the harness's fault hooks, and the waits an operator's steps take, all on the Mega's simulated time.

Used by the firmware tests (``tests/firmware``) and ``benchmarks/bench_issue75_rows.py`` (the issue's table re-run on
the firmware as it stands)."""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path

from rigctl.core.faults import parse_fault
from rigctl.devices import wire
from rigctl.devices.drum import DrumClient, DrumStatus
from rigctl.simulation import hil
from rigctl.simulation.model import MechanicsConfig, RigConfig

__all__ = ["HilBench", "HilBenchError"]

_HR, _State, _Fault = wire.HoldingRegister, wire.DrumState, wire.Fault


class HilBenchError(RuntimeError):
    """The firmware did not do what a step of the bench waited for (a press that did not settle, a RESET not
    latched)."""


class HilBench:
    """One HIL Mega (no Uno) with a truth log, its drum client, and the fault hooks of the harness.

    ``sps``: the HX711's rate (10 or 80); ``k``: the contact's stiffness, g/mm (1 mm from home); ``counts_per_g``:
    the load cell's scale; ``calibrated``: the factory calibration stored in EEPROM (else the defaults);
    ``stall_g``: the actuator driver's stall force, g (0: off, the firmware alone; docs/hardware sizes it: the rig as
    built); ``answer_timeout_s``: the drum client's answer timeout, s (``rigctl.rigs.drum_answer_timeout_s("hil")``).
    The truth log goes to ``folder``. Raises :class:`rigctl.simulation.hil.HilError` when simavr or the
    firmware cannot be started."""

    def __init__(self, folder: Path, *, sps: int, k: float, answer_timeout_s: float, counts_per_g: float = 420.0,
                 calibrated: bool = True, stall_g: float = 0.0) -> None:
        mech = MechanicsConfig(contact_stiffness_g_per_mm=k, hx711_rate_sps=float(sps), contact_gap_mm=1.0,
                               loadcell_counts_per_g=counts_per_g, actuator_stall_g=stall_g)
        self.truth_path = Path(folder) / f"truth-{sps}-{k:g}.csv"
        self.rig = hil.HilRig(RigConfig(mechanics=mech), live=False, with_uno=False, tel_ms=5.0,
                              truth_log=self.truth_path, factory_calibrated=calibrated).start()
        self.rig.truth_start()
        self.drum = DrumClient(self.rig.drum_port, timeout_s=answer_timeout_s, clock=self.rig.clock).open()
        self.sps = sps
        self.drum.write_holding(_HR.WATCHDOG_MS, 10000)
        self.boot()

    def boot(self) -> None:
        """After a power-up or reset: the HX711's rate measured, the host's rate and watchdog written."""
        self.drum.wait_hx711_rate(timeout_s=20)
        if self.sps == 10:
            self.drum.set_hx711_rate(10)
            if _Fault.HX711_RATE in self.drum.read_status().faults:
                self.drum.clear_fault()
        self.drum.write_holding(_HR.WATCHDOG_MS, 10000)

    def close(self) -> None:
        """The client and the harness closed (the truth log flushed)."""
        self.drum.close()
        self.rig.close()

    def send(self, command: str) -> None:
        """A line to the Mega harness (``reset``, ...)."""
        self.rig._running(self.rig._mega, "Mega").send(command)

    def reset_under_load(self) -> None:
        """The MCU reset while the actuator is away from home: the controller latches RESET itself (firmware 1.5,
        issue 76: its warm-boot record), then the host's boot and the operator's CLEAR_FAULT (nothing moves).
        HilBenchError: RESET not latched within 5 s."""
        self.send("reset")
        self.sim_wait(0.05)
        st = self.wait(lambda s: _Fault.RESET in s.faults, 5)
        if st.state != _State.FAULT or _Fault.RESET not in st.faults:
            raise HilBenchError(f"a reset under load latched no RESET: {st}")
        self.boot()
        if _Fault.RESET in self.drum.read_status().faults:
            self.drum.clear_fault()

    def inject(self, spec: str) -> None:
        """The fault ``spec`` (``FAULT[=VALUE]@T[+D]``, :func:`rigctl.core.faults.parse_fault`) applied now."""
        self.rig.faults.apply_fault(parse_fault(spec), True)

    def sim_wait(self, seconds: float) -> None:
        """``seconds`` of the Mega's simulated time pass, the status polled (the watchdog fed)."""
        end = self.rig.next_telemetry().t_s + seconds
        while self.rig.next_telemetry().t_s < end:
            self.drum.read_status()

    def wait(self, done: Callable[[DrumStatus], bool], seconds: float) -> DrumStatus:
        """Poll the status until ``done(status)`` or ``seconds`` of simulated time; the last status."""
        end = self.rig.next_telemetry().t_s + seconds
        st = self.drum.read_status()
        while not done(st) and self.rig.next_telemetry().t_s < end:
            st = self.drum.read_status()
        return st

    def true_force_g(self) -> float:
        """The harness's spring force now, g."""
        return self.rig.next_telemetry().force_g

    def wait_true_force(self, g: float, seconds: float = 30.0) -> None:
        """Poll until the true force reaches ``g`` grams. HilBenchError: not within ``seconds`` of simulated time."""
        end = self.rig.next_telemetry().t_s + seconds
        while self.true_force_g() < g:
            if self.rig.next_telemetry().t_s >= end:
                raise HilBenchError(f"the true force never reached {g} g")
            self.drum.read_status()

    def peak_g(self) -> float:
        """The largest true force in the truth log so far, g (the log writes whole rows, flushed)."""
        with open(self.truth_path) as f:
            return max((float(r["true_force_g"]) for r in csv.DictReader(f)), default=0.0)

    def press_settled(self, force_g: float) -> None:
        """PRESS at ``force_g`` and wait for FORCE_SETTLED. HilBenchError: a fault, or not settled in 60 s."""
        self.drum.set_force(force_g)
        self.drum.press()
        st = self.wait(lambda s: s.state in (_State.FORCE_SETTLED, _State.FAULT), 60)
        if st.state != _State.FORCE_SETTLED:
            raise HilBenchError(f"{st.state!r} {st.faults!r} at {st.force_g} g")
