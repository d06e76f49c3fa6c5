"""Fault campaign (issue 55 item 7): random single faults at random moments of a run, on the model rig (the
controller logic in-process, simulated time) or the real firmware under simavr (``--rig hil``), judged on the truth
log: the true force stays <= 1.1 x FORCE_LIMIT (1650 g), the actuator takes no step towards the sensor after a
latch, no trial is recorded without contact (rigctl.simulation.campaign).

Each case (seed S+i for i < N; ``rigctl.simulation.campaign.draw_case``) opens its own rig with the drawn contact
stiffness and HX711 rate (a 10 SPS rig with the rig config's force_loop for 10 SPS, as a lab sets one up; the
HX711_RATE its controller latches at power-up is cleared at open by that config: Rig._resolve_by_config), and
the host (rigctl's own Rig: every check and wait of a real run) runs one script: HOME, a first press (the contact probe)
to the first force, the force held, a trial, the release, a pause, a second press (the approach) and a second trial,
the release. The fault is armed when the script reaches the drawn moment (FAULT@0, before the HOME at open, for
``power-on``). Whatever the host meets (a latch, a timeout, a refusal) ends the script as a run ends: the host then
stays connected, polling, and asks once more to press (a latched rig refuses); nothing acknowledges.

One list of faults on every rig (rigctl.simulation.campaign.CAMPAIGN_FAULTS; ``--faults NAME,...`` narrows it): the
same seed draws the same case on ``--rig model`` and ``--rig hil``. A fault of the list the rig cannot model is an
error before any case runs (exit 2), never a redraw. A case that did not run (its rig did not open, or its truth log
is empty) is ``not_run``: the campaign then exits 1 as for a violation.

The latches judged are the controller's own: on the model rig its state after each control period, under simavr the
harness's report of the state byte in the MCU's RAM (to 0.1 ms), never the host's poll; the simavr truth rows carry
the largest force and the furthest actuator position since the row before (no peak lost between rows).

``--as-built`` (the default): the rig as docs/hardware builds it, the actuator driver's current limit set so that
its motor stalls where the spring carries AS_BUILT_STALL_G (1550 g, < 1.1 x FORCE_LIMIT); ``--firmware-only``: no stall,
the firmware's channels alone.

Under simavr the cores run as fast as the CPU and the host allow (HilRig(paced=False): the rig's one clock,
rigctl.core.shared_clock), unless ``--paced``.

``--walk-advice`` (model rig): after each case an operator follows the latched fault's advice literally, three
rounds of "do what it says, acknowledge, start" (AdviceWalk: a coil pair swapped, A+/A- swapped, the setpoint lowered,
the rig power-cycled where the advice says so; a check finds nothing), judged on the same truth: the advice is never
worse than the fault (issue 75 item 4).

Usage: python benchmarks/bench_fault_campaign.py --cases N --seed S [--rig model|hil] [--faults NAME,...] [--paced]
                                                 [--firmware-only] [--walk-advice] [--json] [--jobs J]
       python benchmarks/bench_fault_campaign.py --replay SEED [--rig model|hil] [--faults ...] [--truth-log FILE]

The JSON: ``cases``, ``violations`` (each with its ``seed``: ``--replay SEED`` runs that case again), ``not_run``
(cases that did not run) and ``not_run_cases`` (their seeds and why), ``results`` (one object a case: ``seed``,
``fault``, ``value``, ``moment``, ``outcome``, ``latched``: the controller's fault bits at the run's end by name,
``true_force_max_g``), ``worst_true_force_g`` (and ``worst_seed``), ``outcomes`` (how the scripts ended), ``faults``
(cases per fault, with the worst true force of each and how many ended with each fault bit latched: ``none``, or
``unknown`` where the status could not be read; a drawn fault that ended with only CONTACT_STIFFNESS latched at the
first probe may never have acted),
``sim_s_per_wall_s`` (simulated seconds per wall second), ``cases_per_minute``, ``cpu_s``.
Exits 1 if a case broke an invariant or did not run, 2 for a usage error (a fault the rig cannot model).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.acquisition.rig import Rig
from rigctl.acquisition.rigconfig import update_rig_config
from rigctl.core.faults import FAULTS, VALUE_RANGES, WORD_VALUES, FaultSpec
from rigctl.core.trial import PlannedTrial
from rigctl.devices import wire
from rigctl.devices.drum import default_force_loop
from rigctl.rigs import make_backend, open_rig
from rigctl.simulation.campaign import (
    CAMPAIGN_FAULTS,
    COLUMNS,
    CONTACT_G,
    Case,
    ModelTruth,
    check_invariants,
    draw_case,
    read_truth_log,
)
from rigctl.simulation.model import MechanicsConfig, RigConfig

#: each step's expected length, s: the fault starts at the drawn fraction of it after the step begins
STEP_S = {"home": 2.0, "settled": 1.0, "running": 1.5, "retract": 1.0, "between": 1.0, "approach": 1.5}
#: a trial's length, s, and how long the host stays connected after the script ends (polling), s
TRIAL_S = 0.4
AFTER_S = 2.0


def _probe_s(rate_sps: int) -> float:
    return wire.probe_time_s(rate_sps)


#: the actuator driver's stall as built (docs/hardware: its current limit), g of spring force: above FORCE_LIMIT_G and
#: the largest setpoint (1500 g), 100 g under 1.1 x FORCE_LIMIT_G for the contact's ripple (the drum's runout: 1653 g
#: was measured on a stall at 1600 g) and the stall's spread
AS_BUILT_STALL_G = 1550.0


def _probe_spec(name: str) -> FaultSpec:
    value = next(iter(WORD_VALUES[name].values())) if name in WORD_VALUES else VALUE_RANGES.get(name, (1.0, 1.0))[1]
    return FaultSpec(name, 1.0, math.inf, value)


def refusals(rig: str, faults: list[str]) -> dict[str, str]:
    """The faults of ``faults`` rig ``rig`` cannot model, each with why (the campaign's rig: the model rig's
    ModelFaults, the firmware's harness with both boards and its calibration known)."""
    if rig == "model":
        from rigctl.simulation.faults import model_fault_refusal

        why = {n: model_fault_refusal(_probe_spec(n)) for n in faults}
    else:
        from rigctl.simulation.hil_faults import HilFaults

        harness = HilFaults(lambda c: None, lambda c: None, 47_000.0, calibration_offset=lambda: 0,
                            calibration_record=lambda x: b"")
        why = {n: harness.fault_refusal(_probe_spec(n)) for n in faults}
    return {n: w for n, w in why.items() if w}


class Script:
    """The host's run on an open rig, arming the case's fault at its moment; records the trials it recorded and
    how it ended."""

    def __init__(self, rig: Any, case: Case, clock_t0: float):
        self.rig, self.case, self.t0 = rig, case, clock_t0
        self.trials: list[tuple[float, float, float]] = []
        self.outcome = "completed"
        #: the controller's fault bits at the end of the run, by name ([]: none; None: the status could not be read)
        self.latched: list[str] | None = None

    def now(self) -> float:
        return float(self.rig.drum.clock.now()) - self.t0

    def arm(self, moment: str, length_s: float) -> None:
        if self.case.moment == moment:
            self.rig.backend.inject_faults([self.case.spec(max(1e-3, self.case.moment_fraction * length_s))])

    def hold(self, s: float) -> None:
        """The host stays connected ``s`` seconds (its status reads feed the controller's watchdog)."""
        clock, end = self.rig.drum.clock, self.rig.drum.clock.now() + s
        while clock.now() < end:
            self.rig.drum.read_status()
            clock.sleep(0.05)

    def trial(self, i: int, force_g: float) -> None:
        start = self.now()
        self.rig.record_trial(PlannedTrial(i, "A", self.case.speed_mm_s, force_g, TRIAL_S))
        self.trials.append((start, self.now(), self.case.speed_mm_s))

    def run(self) -> None:
        c, rig = self.case, self.rig
        try:
            self.arm("home", STEP_S["home"])
            rig.drum.home()
            rig.drum.wait_state([wire.DrumState.IDLE], timeout_s=30.0)
            rig.drum.tare()
            self.arm("probe", _probe_s(c.hx711_rate_sps))
            rig.press(c.forces_g[0])
            self.arm("settled", STEP_S["settled"])
            self.hold(STEP_S["settled"])
            self.arm("running", STEP_S["running"])
            self.trial(0, c.forces_g[0])
            self.arm("retract", STEP_S["retract"])
            rig.release()
            self.arm("between", STEP_S["between"])
            self.hold(STEP_S["between"])
            self.arm("approach", STEP_S["approach"])
            rig.press(c.forces_g[1])
            self.trial(1, c.forces_g[1])
            rig.release()
        except Exception as exc:  # noqa: BLE001 - any way a run ends: a latch, a timeout, a refusal
            self.outcome = type(exc).__name__
        # after the run: the host stays connected and asks once more to press (a latched rig refuses)
        try:
            self.hold(AFTER_S / 2)
            rig.press(c.forces_g[1], timeout_s=5.0)
        except Exception:  # noqa: BLE001 - refused or failed: what the truth shows is judged
            pass
        try:
            self.hold(AFTER_S / 2)
        except Exception:  # noqa: BLE001
            pass
        try:
            self.latched = [str(b.name) for b in wire.Fault if b and b in self.rig.drum.read_status().faults]
        except Exception:  # noqa: BLE001 - the link is the case's fault: unknown
            self.latched = None


#: rounds of "do what the advice says, acknowledge, start" an operator makes after a latch (``--walk-advice``)
WALK_ROUNDS = 3
#: the reason the advice walker gives each acknowledgement
WALK_REASON = "did what the fault's advice says"
#: a tared reading this far from 0 g with nothing touching the sensor is "far from 0 g" in ACTUATOR_DIRECTION's advice
AT_REST_FAR_G = 50.0


class AdviceWalk:
    """The operator who follows each latched fault's advice literally on the model rig (issue 75 item 4,
    ``--walk-advice``), :data:`WALK_ROUNDS` times: reads the controller's fault bits, does what their advice
    (:func:`rigctl.core.drum.fault_advice`) tells a person to do on the rig (:meth:`actions`), acknowledges
    (:meth:`rigctl.acquisition.rig.Rig.acknowledge`, which refuses while the condition persists) and starts again: a
    press to the setpoint the advice leaves (HOME and TARE first: :attr:`Rig.home_pending`), the force held, the
    release. A check the advice asks for ("check its wiring") finds nothing: the fault is a single hidden one and
    stays. ``steps``: what the walker did, in order (the case's ``advice_walk``)."""

    def __init__(self, rig: Any, case: Case, script: Script) -> None:
        self.rig, self.case, self.script = rig, case, script
        self.force_g = float(case.forces_g[1])
        self.steps: list[str] = []
        self.watch = False  # the lead screw to be watched at the next start (ACTUATOR_DIRECTION's advice)
        self.recalibrate = False  # the load cell to be recalibrated with the reference mass (LOADCELL_SCALE's advice)
        #: the parts the walk left wired the wrong way that were right when it began (a coil pair or A+/A- swapped on
        #: a part that was not the fault): advice worse than the fault
        self.miswired: list[str] = []
        #: each round's latch as the walker read it: (the model's time, s; the controller's fault bits; the rig's
        #: latch causes, rigctl.acquisition.safety.CAUSES keys)
        self.rounds: list[tuple[float, int, tuple[str, ...]]] = []

    def actions(self, faults: int) -> list[str]:
        """What the advice of ``faults`` (the controller's fault bits) has the operator do before acknowledging, done
        on the model rig, by its words: ACTUATOR_DIRECTION's and LOADCELL_REVERSED's "with nothing touching the
        sensor, read FORCE_G: far from 0 g ... recalibrate ... change no wire. Else press the load cell by hand 3 times
        ... If they all fall ... swap A+ and A- ..." and ACTUATOR_DIRECTION's "If they all rise ... watch the lead
        screw while the start's HOME creeps" (the doctor's hand presses: :meth:`_hand_presses`; the watch:
        :meth:`watch_the_screw`), FORCE_LIMIT's "lower
        the force setpoint" (by a fifth), HX711_RATE's "accept 10 SPS ... set_hx711_rate" (the rate the board
        measured), HX711_STUCK's
        "Power-cycle the rig" (the controller powers on again, the HX711 with it); every other advice is a check,
        which finds nothing (the fault is a single hidden one)."""
        from rigctl.core.drum import FAULT_WORDS, Fault, ResetCause

        engine = self.rig.backend.engine
        model, done = engine.model, []
        for bit in Fault:
            if not faults & int(bit) or bit not in FAULT_WORDS:
                continue
            advice = FAULT_WORDS[bit].advice
            if "with nothing touching the sensor" in advice.lower():  # "read FORCE_G: far from 0 g ... no wire"
                at_rest_g = float(self.rig.drum.read_status().force_g)
                if model.contact_force_g < CONTACT_G and abs(at_rest_g) > AT_REST_FAR_G:  # what the operator sees
                    done.append(f"{bit.name}: FORCE_G {at_rest_g:+.0f} g with nothing touching: recalibration "
                                "asked, no wire changed")
                    continue
            if "by hand" in advice and "watch the lead screw" in advice:
                if self._hand_presses(str(bit.name), done) == "rise":  # the cell right: the screw watched, no wire yet
                    self.watch = True
                    done[-1] += ", the screw to be watched at the start"
            elif "by hand" in advice and "swap A+ and A-" in advice:  # LOADCELL_REVERSED: "If they all fall ... swap"
                if self._hand_presses(str(bit.name), done) == "rise":
                    done[-1] += ", changed no wire (recalibration asked)"
            elif "recalibrate with the reference mass" in advice:
                self.recalibrate = True
                done.append(f"{bit.name}: checked the cell, found nothing; recalibration with the reference mass "
                            "after the acknowledgement")
            elif "set_hx711_rate" in advice:  # HX711_RATE: "accept 10 SPS ... DrumClient.set_hx711_rate(10)"
                measured = float(self.rig.drum.read_status().hx711_rate_sps)
                sps = min((10, 80), key=lambda r: abs(r - measured))
                self.rig.drum.set_hx711_rate(sps)
                done.append(f"{bit.name}: the board's rate accepted: set_hx711_rate({sps})")
            elif "lower the force setpoint" in advice:
                self.force_g = max(100.0, 0.8 * self.force_g)
                done.append(f"{bit.name}: setpoint lowered to {self.force_g:.0f} g")
            elif "Power-cycle" in advice:
                model.freeze_hx711(False)
                engine.controller.reset(ResetCause.POWER_ON)
                done.append(f"{bit.name}: power-cycled")
            else:
                done.append(f"{bit.name}: checked, found nothing")
        return done

    def _hand_presses(self, name: str, done: list[str]) -> str:
        """The advice's hand press, repeated as it says (:data:`rigctl.core.drum.HAND_PRESS_STEP`; the doctor's:
        :func:`rigctl.acquisition.doctor.drum_checks.hand_presses_g`), and what they say
        (:func:`rigctl.core.drum.hand_press_verdict`): ``"fall"`` swaps A+ and A-, ``"rise"`` and ``"unclear"``
        change no wire; what they read is the last step of ``done`` either way."""
        from rigctl.acquisition.doctor import DoctorContext
        from rigctl.acquisition.doctor.drum_checks import HAND_PRESS_G, hand_presses_g
        from rigctl.core.drum import hand_press_verdict

        changes = hand_presses_g(DoctorContext("inprocess", rig=self.rig))
        if changes is None:
            done.append(f"{name}: hand presses read nothing")
            return "unclear"
        read = ", ".join(f"{c:+.0f}" for c in changes)
        verdict = hand_press_verdict(changes, HAND_PRESS_G)
        if verdict == "fall":
            model = self.rig.backend.engine.model
            model.loadcell_sign = -model.loadcell_sign
            done.append(f"{name}: hand presses {read} g, all fell: swapped A+ and A-")
        elif verdict == "rise":
            done.append(f"{name}: hand presses {read} g, all rose")
        else:
            done.append(f"{name}: hand presses {read} g, they disagree: changed no wire")
        return verdict

    def watch_the_screw(self) -> str:
        """The operator's eyes on the lead screw during the start's HOME (ACTUATOR_DIRECTION's advice): a motor wired
        the wrong way (the model's ``actuator_sign``, what a person sees the screw do) gets a coil pair swapped; a
        right one is left alone."""
        model = self.rig.backend.engine.model
        self.watch = False
        if model.actuator_sign < 0:
            model.actuator_sign = -model.actuator_sign
            return "saw the screw close the gap: swapped a coil pair of the actuator"
        return "saw the screw turn the right way: changed no wire"

    def recalibrate_with_the_reference_mass(self) -> str:
        """LOADCELL_SCALE's advice: the load cell calibrated with the 500 g reference mass (HOME first), which stores
        the contact's stiffness with the verified scale (:func:`rigctl.acquisition.calibration.calibrate_loadcell`;
        the model rig rests the mass itself)."""
        from rigctl.acquisition import calibration

        self.recalibrate = False
        try:
            self.rig.home_if_pending()
            place, remove = calibration.simulated_mass(self.rig)
            result = calibration.calibrate_loadcell(self.rig.drum, 500.0, place_mass=place, remove_mass=remove,
                                                    config_file=False)
        except Exception as exc:  # noqa: BLE001 - the operator's calibration ended: the next start says what holds
            return f"recalibration ended: {type(exc).__name__}"
        return (f"recalibrated with the 500 g reference mass: {result.counts_per_g:.1f} counts/g, "
                f"{result.contact_stiffness_g_per_mm:.0f} g/mm stored")

    def run(self) -> None:
        """The rounds; :attr:`miswired` set at the end."""
        model = self.rig.backend.engine.model
        before = {"actuator": model.actuator_sign, "load cell": model.loadcell_sign}
        try:
            self._rounds()
        finally:
            after = {"actuator": model.actuator_sign, "load cell": model.loadcell_sign}
            self.miswired = [part for part in before if before[part] > 0 > after[part]]

    def _rounds(self) -> None:
        from rigctl.core.drum import DrumState

        rig = self.rig
        for _ in range(WALK_ROUNDS):
            try:
                st = rig.drum.read_status()
            except Exception as exc:  # noqa: BLE001 - the walk ends where the host cannot go on
                self.steps.append(f"status: {type(exc).__name__}")
                return
            if st.state != DrumState.FAULT and rig.safety.latch is None:
                return
            latch = rig.safety.latch
            self.rounds.append((float(rig.backend.engine.model.time_s), int(st.faults),
                                latch.causes if latch is not None else ()))
            self.steps.extend(self.actions(int(st.faults)))
            try:
                rig.acknowledge(WALK_REASON, by="advice walker")
            except Exception as exc:  # noqa: BLE001 - refused (the condition persists): the operator tries again
                self.steps.append(f"acknowledge refused: {type(exc).__name__}")
                self.script.hold(0.5)
                continue
            self.steps.append("acknowledged")
            if self.recalibrate:
                self.steps.append(self.recalibrate_with_the_reference_mass())
            try:
                rig.press(self.force_g, timeout_s=10.0)
                self.script.hold(1.0)
                rig.release()
                self.steps.append(f"pressed {self.force_g:.0f} g and released")
            except Exception as exc:  # noqa: BLE001 - the start ended as a run does: a latch, a timeout
                self.steps.append(f"start ended: {type(exc).__name__}")
            if self.watch:
                self.steps.append(self.watch_the_screw())
            self.script.hold(0.5)


def _rig_files(case: Case, folder: Path, as_built: bool = True) -> tuple[RigConfig, Path]:
    cfg = RigConfig(mechanics=MechanicsConfig(contact_stiffness_g_per_mm=case.stiffness_g_per_mm,
                                              hx711_rate_sps=float(case.hx711_rate_sps),
                                              actuator_stall_g=AS_BUILT_STALL_G if as_built else 0.0))
    host = folder / f"rig-{case.seed}.json"
    if case.hx711_rate_sps != 80:  # the lab's rig config for its 10 SPS board
        update_rig_config(host, force_loop=default_force_loop(case.hx711_rate_sps).to_dict())
    return cfg, host


def run_model_case(case: Case, folder: Path, as_built: bool = True, walk_advice: bool = False) -> dict[str, Any]:
    """One case on the in-process model rig; its result (see :func:`result`); ``walk_advice``: then the operator
    follows the latched fault's advice (:class:`AdviceWalk`), judged on the same truth."""
    cfg, host = _rig_files(case, folder, as_built)
    power_on = [case.spec(0.0)] if case.moment == "power-on" else []
    t_wall = time.perf_counter()
    backend = make_backend("inprocess", config=cfg, seed=case.seed)
    truth = ModelTruth(backend.engine)  # type: ignore[attr-defined]
    if power_on:  # armed before the rig opens: in place before the rig opens, as a miswired rig is
        backend.inject_faults(power_on)  # type: ignore[attr-defined]
    script, open_error, walk = None, None, None
    try:
        rig = Rig.connect(backend, host_config_path=str(host), refuse_fault=False)
    except Exception as exc:  # noqa: BLE001 - the rig did not open: the case did not run
        open_error = f"{type(exc).__name__}: {exc}"
    else:
        with rig:
            script = Script(rig, case, 0.0)  # the engine's clock is the model's: the truth rows' times
            script.run()
            if walk_advice:
                walk = AdviceWalk(rig, case, script)
                walk.run()
    out = result(case, truth.array(), truth.latch_spans, script, open_error, time.perf_counter() - t_wall)
    if walk is not None:
        out["advice_walk"], out["advice_miswired"], out["advice_rounds"] = walk.steps, walk.miswired, walk.rounds
        out["fault_started_s"] = backend.engine.faults.started_s.get(case.fault)  # type: ignore[attr-defined]
    return out


#: the faults of the taxel streamer (the Uno): their hil cases run both boards; every other case the Mega alone
#: (HilRig(with_uno=False, index_frames=True): rigctl.simulation.hil_index_taxels)
HIL_UNO_FAULTS = frozenset({"taxel-link-drop", "taxel-ohm"})


def run_hil_case(case: Case, folder: Path, truth_log: Path | None = None, paced: bool = False,
                 as_built: bool = True) -> dict[str, Any]:
    """One case on the firmware under simavr (the Mega alone, both boards for the Uno's faults: HIL_UNO_FAULTS), its
    truth log written by the harness and its latches the
    controller's own (HilRig.latch_spans: the harness reads the state byte in the MCU's RAM); the cores run as fast as
    the CPU and the host allow (the rig's one clock, HilRig(paced=False)) unless ``paced``."""
    cfg, host = _rig_files(case, folder, as_built)
    log = truth_log or folder / f"truth-{case.seed}.csv"
    power_on = [case.spec(0.0)] if case.moment == "power-on" else []
    t_wall = time.perf_counter()
    script, open_error, latches = None, None, []
    # the Mega alone, its trials recorded on frames marked at its index pulses, unless the fault is the Uno's
    # (HIL_UNO_FAULTS): the simulated Uno cost more than the Mega beside it and none of the Mega's faults reaches it
    alone = {} if case.fault in HIL_UNO_FAULTS else {"with_uno": False, "index_frames": True}
    try:
        rig = open_rig("hil", config=cfg, seed=case.seed, host_config_path=host, inject=power_on, truth_log=log,
                       refuse_fault=False, paced=paced, **alone)
    except Exception as exc:  # noqa: BLE001
        open_error = f"{type(exc).__name__}: {exc}"
    else:
        with rig:
            sim = rig.backend.sim  # type: ignore[attr-defined]
            t0 = sim.truth.t0_s if sim.truth is not None and sim.truth.t0_s is not None else rig.drum.clock.now()
            script = Script(rig, case, float(t0))  # the truth log's clock: the trials' spans on it
            script.run()
            latches = sim.latch_spans
    rows = read_truth_log(log) if log.exists() else np.empty((0, len(COLUMNS)))
    return result(case, rows, latches, script, open_error, time.perf_counter() - t_wall)


#: faults that, wired so from power-on, make the rig refuse to open, and the words of that refusal: the behaviour under
#: test, judged on the truth like any other case (the rig's boards ran while the host tried), not a case that did not
#: run (an open that failed for another reason still is one)
OPEN_REFUSALS = {"host-silence": "no answer from the drum controller",
                 "taxel-link-drop": "no ready banner"}  # (the Uno's link cut from power-on: fresh hil seed 734043)


def refused_at_open(case: Case, open_error: str | None) -> bool:
    """Whether ``open_error`` is the refusal the case's power-on fault is expected to cause (:data:`OPEN_REFUSALS`)."""
    words = OPEN_REFUSALS.get(case.fault)
    return bool(open_error and case.moment == "power-on" and words and words in open_error)


def result(case: Case, truth: np.ndarray, latches: list[tuple[float, float | None]], script: Script | None, open_error: str | None,
           wall_s: float) -> dict[str, Any]:
    trials = script.trials if script is not None else []
    violations = check_invariants(truth, latches=latches, trials=trials)
    refused = refused_at_open(case, open_error)
    not_run = None if (open_error is None or refused) and len(truth) else (
        f"open: {open_error}" if open_error and not refused else "the truth log is empty")
    return {"seed": case.seed, "case": case.describe(), "fault": case.fault, "value": case.value,
            "moment": case.moment, "not_run": not_run,
            "outcome": "not_run" if not_run else "refused at open" if refused else (script.outcome if script else "?"),
            "trials_recorded": len(trials), "latches": latches, "latched": script.latched if script else None,
            "true_force_max_g": round(float(truth[:, 1].max()), 1) if len(truth) else 0.0,
            "sim_s": round(float(truth[-1, 0] - truth[0, 0]), 3) if len(truth) else 0.0, "wall_s": round(wall_s, 3),
            "violations": [{"kind": v.kind, "time_s": round(v.time_s, 3), "detail": v.detail} for v in violations]}


def run_case(seed: int, rig: str, folder: Path, truth_log: Path | None = None, paced: bool = False,
             faults: list[str] | None = None, as_built: bool = True, draw: str = "v3",
             walk_advice: bool = False) -> dict[str, Any]:
    """The case of ``seed`` (drawn from ``faults``, default CAMPAIGN_FAULTS: the same on every rig; ``draw``: see
    rigctl.simulation.campaign.draw_case) on ``rig``; ``walk_advice`` (model rig): the advice followed after it."""
    case = draw_case(seed, faults, draw)
    if rig == "model":
        return run_model_case(case, folder, as_built, walk_advice)
    return run_hil_case(case, folder, truth_log, paced, as_built)


def _run_chunk(seeds: list[int], rig: str, paced: bool = False, faults: list[str] | None = None,
               as_built: bool = True, walk_advice: bool = False, draw: str = "v3") -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="rigctl-campaign-") as tmp:
        return [run_case(s, rig, Path(tmp), paced=paced, faults=faults, as_built=as_built, draw=draw,
                         walk_advice=walk_advice) for s in seeds]


def campaign(n: int, seed: int, rig: str, jobs: int = 1, paced: bool = False, faults: list[str] | None = None,
             as_built: bool = True, walk_advice: bool = False, draw: str = "v3") -> dict[str, Any]:
    seeds = list(range(seed, seed + n))
    t_wall, cpu0 = time.perf_counter(), os.times()
    if jobs > 1:
        chunks = [seeds[i::jobs] for i in range(jobs)]
        with ProcessPoolExecutor(jobs) as pool:
            results = [r for part in pool.map(_run_chunk, chunks, [rig] * jobs, [paced] * jobs, [faults] * jobs,
                                              [as_built] * jobs, [walk_advice] * jobs, [draw] * jobs) for r in part]
    else:
        results = _run_chunk(seeds, rig, paced, faults, as_built, walk_advice, draw)
    wall = time.perf_counter() - t_wall
    cpu1 = os.times()
    results.sort(key=lambda r: r["seed"])
    worst = max(results, key=lambda r: r["true_force_max_g"]) if results else None
    per_fault: dict[str, dict[str, Any]] = {}
    outcomes: dict[str, int] = {}
    for r in results:
        f = per_fault.setdefault(r["fault"], {"cases": 0, "worst_true_force_g": 0.0, "latched": {}})
        f["cases"] += 1
        f["worst_true_force_g"] = max(f["worst_true_force_g"], r["true_force_max_g"])
        for name in r.get("latched") or ["none" if r.get("latched") == [] else "unknown"]:
            f["latched"][name] = f["latched"].get(name, 0) + 1
        outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
    sim = sum(r["sim_s"] for r in results)
    not_run = [{"seed": r["seed"], "case": r["case"], "why": r["not_run"]} for r in results if r["not_run"]]
    return {"rig": rig, "seed": seed, "cases": len(results), "jobs": jobs, "paced": paced if rig == "hil" else None,
            "as_built": as_built, "draw": draw, "faults_drawn_from": sorted(faults or CAMPAIGN_FAULTS),
            "violations": [{"seed": r["seed"], "case": r["case"], **v} for r in results for v in r["violations"]],
            "not_run": len(not_run), "not_run_cases": not_run,
            "results": [{k: r[k] for k in ("seed", "fault", "value", "moment", "outcome", "latched", "true_force_max_g",
                                            "advice_walk", "advice_miswired") if k in r} for r in results],
            "worst_true_force_g": worst["true_force_max_g"] if worst else 0.0,
            "worst_seed": worst["seed"] if worst else None, "outcomes": outcomes, "faults": per_fault,
            "sim_s": round(sim, 1), "wall_s": round(wall, 1),
            "cpu_s": round((cpu1.user - cpu0.user) + (cpu1.children_user - cpu0.children_user)
                           + (cpu1.system - cpu0.system) + (cpu1.children_system - cpu0.children_system), 1),
            "sim_s_per_wall_s": round(sim / wall, 2) if wall > 0 else None,
            "cases_per_minute": round(60.0 * len(results) / wall, 1) if wall > 0 else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rig", choices=("model", "hil"), default="model")
    ap.add_argument("--jobs", type=int, default=1, help="cases run in this many processes side by side")
    ap.add_argument("--paced", action="store_true", help="--rig hil: the cores no faster than the wall clock")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--faults", default=None, metavar="NAME,...",
                    help="draw only these faults (names of rigctl.core.faults.FAULTS; default the campaign's list)")
    ap.add_argument("--draw", choices=("v1", "v2", "v3"), default="v3",
                    help="v1: the campaign's draw before issue 75 (15 faults, plates of 0.25-6 kg/mm): the seeds of "
                         "the cases fixed then (tests/simulation/test_sim_fault_campaign.py FIXED); v2: the rig's own "
                         "contact up to 5 kg/mm, stiffer than its force loop holds in a fifth of the cases (the "
                         "campaigns until firmware 1.9); v3 (default): the rig's contact within what its loop holds")
    ap.add_argument("--firmware-only", action="store_true",
                    help="no driver stall (the rig as built has one: --as-built, the default): the firmware alone")
    ap.add_argument("--walk-advice", action="store_true",
                    help="--rig model: after each case the operator follows the latched fault's advice literally "
                         f"({WALK_ROUNDS} rounds of do what it says, acknowledge, start), judged on the same truth")
    ap.add_argument("--replay", type=int, default=None, metavar="SEED", help="run the case of SEED alone")
    ap.add_argument("--truth-log", type=Path, default=None, help="with --replay --rig hil: keep its truth log here")
    args = ap.parse_args(argv)
    if args.cases < 1 or args.jobs < 1 or args.seed < 0:
        ap.error("--cases and --jobs must be >= 1, --seed >= 0")
    faults = None
    if args.faults is not None:
        faults = sorted({f.strip() for f in args.faults.split(",") if f.strip()})
        unknown = [f for f in faults if f not in FAULTS]
        if unknown or not faults:
            ap.error(f"--faults: unknown fault {', '.join(unknown) or '(none given)'}; one of {', '.join(FAULTS)}")
    if args.draw == "v1" and args.replay is None:
        ap.error("--draw v1 replays a case fixed before issue 75 (with --replay SEED)")
    refused = refusals(args.rig, faults or list(CAMPAIGN_FAULTS))
    if refused:
        ap.error(f"the {args.rig} rig cannot model " + "; ".join(f"{n}: {w}" for n, w in refused.items()))
    if args.walk_advice and args.rig != "model":
        ap.error("--walk-advice runs on the model rig (--rig model): the walker rewires the model's parts")
    as_built = not args.firmware_only
    if args.replay is not None:
        with tempfile.TemporaryDirectory(prefix="rigctl-campaign-") as tmp:
            out = run_case(args.replay, args.rig, Path(tmp), args.truth_log, args.paced, faults, as_built, args.draw,
                           args.walk_advice)
        print(json.dumps(out, indent=1))
        return 1 if out["violations"] or out["not_run"] else 0
    out = campaign(args.cases, args.seed, args.rig, args.jobs, args.paced, faults, as_built, args.walk_advice,
                   args.draw)
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(f"{out['cases']} cases on the {args.rig} rig (seeds {args.seed}-{args.seed + args.cases - 1}): "
              f"{len(out['violations'])} violations, worst true force {out['worst_true_force_g']:.0f} g (seed "
              f"{out['worst_seed']}), {out['cases_per_minute']} cases/min, {out['sim_s_per_wall_s']} sim s per wall s")
        for v in out["violations"]:
            print(f"  seed {v['seed']}: {v['kind']} at {v['time_s']:.2f} s: {v['detail']} [{v['case']}]")
        for c in out["not_run_cases"]:
            print(f"  seed {c['seed']}: did not run: {c['why']} [{c['case']}]")
    return 1 if out["violations"] or out["not_run"] else 0


if __name__ == "__main__":
    sys.exit(main())
