"""The fault campaign's cases and invariants (issue 55 item 7): random single faults at random moments of a run, and
what the ground truth must show whatever the fault.

A case (:class:`Case`, :func:`draw_case`) is one seed's draw: one fault of :data:`rigctl.core.faults.FAULTS` (a
value for the valued ones: a plate swap's stiffness, a slip, a taxel impedance), the moment of the run it starts in
(:data:`MOMENTS`: wired so from power-on, or during the HOME, the first press's contact probe, a later press's
approach, the settled force, a running trial, the retract, the pause between trials) and where in that moment
(``moment_fraction``), how long it lasts, the rig's contact stiffness (log-uniform from 0.25 kg/mm to
:data:`LOOP_STIFFNESS_SHARE` of what its force loop holds at the drawn rate, draw v3; a plate swap, the
``contact-stiffness`` fault, over the whole range a rig config accepts, 0.1-5 kg/mm), its HX711's rate (10 or 80
SPS) and the trials' forces (250-1500 g). The same seed draws the same case on every machine (numpy's PCG64), so a
violation is replayed from its seed.

The invariants (:func:`check_invariants`) are judged on the truth log's columns :data:`COLUMNS` (of
:data:`rigctl.simulation.truth.TRUTH_COLUMNS`: the physical model's contact force and actuator position, not what
the firmware read; :func:`read_truth_log` takes them from a truth log file):

- ``over-force``: the true force stays <= 1.1 x FORCE_LIMIT_G (:data:`FORCE_BOUND_G`, 1650 g);
- ``step-after-latch``: once the controller latched a fault, the actuator's motor takes no step towards the sensor
  (:data:`LATCH_STEP_MM` of slack for the step in flight, :data:`LATCH_GRACE_S` after the latch) beyond its
  back-off's proof steps (:data:`LATCH_PROOF_MM` in all, spec 2.11). Judged on ``motor_mm``, the motion the motor's
  own steps made (a swapped coil pair's back-off towards the sensor is one), not on the screw's: a slipping
  coupling wound up before the latch catches up while the motor holds and moves the screw with no step, which no
  action of the controller after the latch causes or prevents (docs/safety.md, "What the campaign's step-after-latch
  judges"); its force is judged by ``over-force``;
- ``trial-without-contact``: a trial the host recorded had the sensor in contact the whole time the drum ran for
  it (true force >= :data:`CONTACT_G`).

:class:`ModelTruth` records the truth rows (and the controller's first latch) of an in-process model rig after each
of its control periods (and each span its controller held a latched fault); the firmware under simavr writes them
itself (``HilRig(truth_log=...)``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

from rigctl.core.faults import FAULTS, INSTANT_FAULTS, FaultSpec
from rigctl.core.parts import Part
from rigctl.devices import wire

__all__ = ["CAMPAIGN_FAULTS", "CAMPAIGN_FAULTS_V1", "Case", "BrokenPart", "FAULT_PARTS",
           "COLUMNS", "read_truth_log", "MOMENTS", "FORCE_BOUND_G", "CONTACT_G", "LATCH_STEP_MM", "LATCH_GRACE_S",
           "LATCH_PROOF_MM", "LOOP_STIFFNESS_SHARE", "loop_stiffness_max_g_per_mm", "draw_case",
           "check_invariants", "ModelTruth", "Violation"]

#: the truth log's columns the invariants judge, in this order
COLUMNS = ("time_s", "true_force_g", "actuator_mm", "drum_speed_mm_s", "motor_mm")
#: the moments a fault can start in, in the order a run passes them (``power-on``: FAULT@0, before the rig opens)
MOMENTS = ("power-on", "home", "probe", "settled", "running", "retract", "between", "approach")
#: the bound on the true force any single fault must keep, g: 1.1 x FORCE_LIMIT_G (docs/safety.md)
FORCE_BOUND_G = 1.1 * wire.HOLDING_RANGE[wire.HoldingRegister.FORCE_LIMIT_G][2]
#: a recorded trial's true force below this while its drum runs is no contact, g
CONTACT_G = 5.0
#: the actuator's travel towards the sensor after a latch that counts as a step, mm (a microstep is ~0.3 um; the
#: slack covers the truth log's rounding and the step the driver was making)
LATCH_STEP_MM = 0.01
#: the truth rows within this long after the latch are not judged, s (the latch's own control period)
LATCH_GRACE_S = 0.005
#: the travel towards the sensor a back-off's proof may take blind after a latch, mm (spec 2.11: at most
#: BACKOFF_PROOF_TRIES steps of BACKOFF_PROOF_UM, each <= BACKOFF_PROOF_G of spring force: a reversed motor's proof steps
#: on a soft contact, which shows a step's force only after several; fresh seed 741098 judged 15 um of them a step).
#: The truth cannot tell a proof step from any other motion: this much travel towards the sensor after a latch is
#: allowed whatever moved it, more is a step after the latch (firmware 1.4's proof step at full speed for a period,
#: 45-70 um on a reversed motor, stays one)
LATCH_PROOF_MM = wire.BACKOFF_PROOF_TRIES * wire.BACKOFF_PROOF_UM * 1e-3
#: the range of each valued fault's drawn value (contact-stiffness: the plate swapped for one of 0.1-5 kg/mm, the
#: whole range a rig config accepts, rigctl.core.drum.CONTACT_STIFFNESS_MAX_G_PER_MM; home-switch: 0 open, 1 closed)
_VALUE_DRAWS: dict[str, tuple[float, float, bool]] = {  # name -> (low, high, log-uniform)
    "contact-stiffness": (100.0, wire.CONTACT_STIFFNESS_MAX_G_PER_MM, True), "slip": (5.0, 60.0, False), "taxel-ohm": (47e3, 2e6, True),
    "cell-gain": (0.3, 3.0, True), "cell-offset": (-1000.0, 1000.0, False), "coupling-slip": (5.0, 60.0, False),
    "steps-lost": (5.0, 60.0, False), "hx711-dout-noise": (1e-4, 0.05, True), "calibration-scale": (0.3, 3.0, True)}
#: faults whose drawn value is one of two words (0 or 1: rigctl.core.faults.WORD_VALUES)
_WORD_DRAWS = frozenset({"home-switch"})
#: the one list of faults the campaign draws from, on every rig (issue 80: the same seed is the same case on the model
#: rig and under simavr; a rig that cannot model one of them is an error, never a redraw)
CAMPAIGN_FAULTS: tuple[str, ...] = tuple(sorted(FAULTS))


class BrokenPart(NamedTuple):
    """What a campaign fault (an FMEA row) really breaks (issue 75 item 4): ``part`` (the :class:`Part` an advice must
    send the operator to; None: no part of the rig), ``unjudged`` (``""``: the advice walker judges the latched
    fault's advice against ``part``; else why it does not: the operator's act, the environment's, latches nothing)."""

    part: Part | None
    unjudged: str = ""


#: each campaign fault's broken part, beside the list (one table; tests/simulation/test_sim_advice_walk.py judges it:
#: the advice of the fault it latches names the part, and no less likely part before it, rigctl.core.parts.PARTS)
FAULT_PARTS: dict[str, BrokenPart] = {
    "calibration-scale": BrokenPart(Part.CALIBRATION),
    "cell-gain": BrokenPart(Part.LOADCELL_WIRING),  # the likeliest of the row's causes: a joint in an excitation lead
    "cell-offset": BrokenPart(Part.LOADCELL_ZERO),
    "contact-stiffness": BrokenPart(Part.PLATE),
    "coupling-slip": BrokenPart(Part.COUPLING),
    "driver-enable-stuck": BrokenPart(Part.DRIVER, "latches nothing: the firmware never steps with the drivers off "
                                                   "(STATUS_FLAGS reads the EN line back; the e-stop's contact in the "
                                                   "motor supply bounds it)"),
    "eeprom-corrupt": BrokenPart(Part.CONTROLLER_POWER),
    "estop": BrokenPart(None, "the operator's act (or its wire broken): ESTOP's advice names the e-stop"),
    "home-switch": BrokenPart(Part.HOME_SWITCH),
    "host-silence": BrokenPart(Part.HOST_LINK, "the environment's: the host or its link is silent, so no face reads "
                                               "the latch until it is back (WATCHDOG's advice names them)"),
    "hx711-10sps": BrokenPart(Part.HX711_RATE_PIN),
    "hx711-dout-noise": BrokenPart(Part.HX711_WIRES),
    "hx711-frozen": BrokenPart(Part.HX711_CHIP),
    "hx711-sck-broken": BrokenPart(Part.HX711_WIRES),
    "reset": BrokenPart(Part.CONTROLLER_POWER),
    "reversed-actuator": BrokenPart(Part.ACTUATOR_COILS),
    "reversed-cell": BrokenPart(Part.LOADCELL_WIRING),
    "reversed-drum": BrokenPart(Part.DRUM_COILS, "latches nothing: the speed marks pass either way (rigctl doctor's "
                                                 "drum-direction check names the drum's coil pair)"),
    "slip": BrokenPart(Part.DRUM_DRIVE),
    "stall": BrokenPart(Part.DRUM_BLOCKED),
    "steps-lost": BrokenPart(Part.LEAD_SCREW),
    "taxel-link-drop": BrokenPart(None, "latches nothing: the taxel board's link, not the force path (the host's "
                                        "stream checks retry, then end the run resumably)"),
    "taxel-ohm": BrokenPart(None, "latches nothing: the taxels' source impedance, not the force path"),
}

#: the campaign's draw before the bill of materials' faults were added (issue 75): its list of faults and its plate
#: swaps' stiffness (0.25-6 kg/mm); the seeds of the cases fixed then draw their old cases from it (``draw="v1"``)
#: the rig's own contact drawn up to the stiffest a rig config accepts (v1: up to 6 kg/mm, from before that bound)
_STIFFNESS_MAX = wire.CONTACT_STIFFNESS_MAX_G_PER_MM
#: v3: the rig's own contact drawn up to this share of what its force loop holds at the drawn HX711 rate with the
#: default gains (:func:`loop_stiffness_max_g_per_mm`; the controller measures the HX711's period, a few % off the
#: nominal, and the probe's stiffness a few % off the contact's): a stiffer rig latches CONTACT_STIFFNESS at its first
#: probe, before its drawn fault can act (v2 drew up to 5 kg/mm: 20 % of 4,000 model cases ended so, docs/safety.md).
#: Stiffer contacts are the ``contact-stiffness`` fault's, over a rig config's whole range
LOOP_STIFFNESS_SHARE = 0.8


def loop_stiffness_max_g_per_mm(hx711_rate_sps: int) -> float:
    """The stiffest contact the force loop holds with its default gains at ``hx711_rate_sps`` (10 or 80), g/mm:
    LOOP_PHASE_RAD / (Kp x HX711_DELAY_PERIODS x the HX711's nominal period) (docs/wire-protocol.md 2.10; the
    controller's ``ctl_stiffness_max``, which uses the period it measures). KeyError for another rate."""
    from rigctl.devices.drum import default_force_loop

    loop = default_force_loop(hx711_rate_sps)
    kp = {80: loop.kp_80sps_mm_s_per_g, 10: loop.kp_10sps_mm_s_per_g}[int(hx711_rate_sps)]
    return wire.LOOP_PHASE_RAD / (kp * wire.HX711_DELAY_PERIODS / float(hx711_rate_sps))
_VALUE_DRAWS_V1 = {**_VALUE_DRAWS, "contact-stiffness": (250.0, 6000.0, True)}
CAMPAIGN_FAULTS_V1: tuple[str, ...] = (
    "contact-stiffness", "eeprom-corrupt", "estop", "host-silence", "hx711-10sps", "hx711-frozen", "hx711-sck-broken",
    "reset", "reversed-actuator", "reversed-cell", "reversed-drum", "slip", "stall", "taxel-link-drop", "taxel-ohm")


@dataclass(frozen=True)
class Case:
    """One drawn case (see the module docstring). ``at_s`` of the fault is set when the run reaches ``moment``:
    ``moment_fraction`` x that step's expected length after its start (0 for ``power-on``)."""

    seed: int
    fault: str  #: a name of FAULTS
    value: float | None  #: the valued fault's value (g/mm, %, Ohm), else None
    moment: str  #: one of MOMENTS
    moment_fraction: float  #: where in the moment, 0-1
    duration_s: float  #: how long the fault lasts (inf: to the end; 0: an instant fault)
    stiffness_g_per_mm: float  #: the rig's contact stiffness
    hx711_rate_sps: int  #: 10 or 80
    forces_g: tuple[float, float]  #: the two trials' force setpoints
    speed_mm_s: float  #: the trials' drum speed

    def spec(self, at_s: float) -> FaultSpec:
        """The fault starting ``at_s`` s after its schedule is armed."""
        return FaultSpec(self.fault, float(at_s), 0.0 if self.fault in INSTANT_FAULTS else self.duration_s,
                         self.value)

    def describe(self) -> str:
        value = "" if self.value is None else str(self.spec(0.0)).split("@")[0][len(self.fault):]
        dur = "" if self.fault in INSTANT_FAULTS or math.isinf(self.duration_s) else f" for {self.duration_s:.2f} s"
        return (f"{self.fault}{value} at {self.moment} ({self.moment_fraction:.2f}){dur}; contact "
                f"{self.stiffness_g_per_mm:.0f} g/mm, HX711 {self.hx711_rate_sps} SPS, forces "
                f"{self.forces_g[0]:.0f}/{self.forces_g[1]:.0f} g at {self.speed_mm_s:.0f} mm/s")

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["duration_s"] = None if math.isinf(self.duration_s) else self.duration_s
        out["forces_g"] = list(self.forces_g)
        return out


def draw_case(seed: int, faults: Sequence[str] | None = None, draw: str = "v3") -> Case:
    """The case of ``seed`` (an int >= 0), its fault from ``faults`` (default :data:`CAMPAIGN_FAULTS`, the same on
    every rig; ``--faults`` narrows it): the one at ``seed`` modulo their number (sorted), so consecutive seeds draw
    every fault in turn; its value, moment, rig and forces drawn from the seed; ``draw="v1"``: the draw of before issue
    75 (the fault drawn at random too; default faults
    :data:`CAMPAIGN_FAULTS_V1`, plate swaps of 0.25-6 kg/mm), which the cases fixed then are replayed with; ``"v2"``:
    the rig's own contact drawn over a rig config's whole range (0.25-5 kg/mm), above what its force loop holds in a
    fifth of the cases; ``"v3"`` (the default): the same seeds, the rig's own contact within
    :data:`LOOP_STIFFNESS_SHARE` of what its force loop holds at the drawn rate (the plate swaps of
    ``contact-stiffness`` still over the whole range). Raises ValueError for an empty ``faults`` or an unknown
    ``draw``."""
    if draw not in ("v1", "v2", "v3"):
        raise ValueError(f"draw must be v1, v2 or v3, got {draw!r}")
    value_draws = _VALUE_DRAWS_V1 if draw == "v1" else _VALUE_DRAWS
    names = sorted(faults if faults is not None else CAMPAIGN_FAULTS_V1 if draw == "v1" else CAMPAIGN_FAULTS)
    if not names:
        raise ValueError("no fault to draw from")
    rng = np.random.default_rng([int(seed), 55])
    drawn = int(rng.integers(len(names)))
    # v2: the fault by the seed's place in the list, so any len(names) consecutive seeds draw every fault once (a
    # campaign of N >= len(names) cases draws them all, whatever its first seed); the rest of the case as drawn
    fault = names[drawn] if draw == "v1" else names[int(seed) % len(names)]
    value = None
    if fault in value_draws:
        low, high, log = value_draws[fault]
        value = float(math.exp(rng.uniform(math.log(low), math.log(high))) if log else rng.uniform(low, high))
        value = float(f"{value:.4g}")
    elif fault in _WORD_DRAWS:
        value = 1.0 if rng.uniform() < 0.5 else 0.0
    moment = MOMENTS[int(rng.integers(len(MOMENTS)))]
    fraction = float(rng.uniform(0.0, 1.0))
    duration = math.inf if rng.uniform() < 0.5 else float(rng.uniform(0.2, 4.0))
    if fault in INSTANT_FAULTS:
        duration = 0.0
    share = float(rng.uniform())  # where in the rig's range its contact lies (log-uniform): one draw in every version
    rate = int(rng.choice([10, 80]))
    high = {"v1": 6000.0, "v2": _STIFFNESS_MAX}.get(draw) or min(
        _STIFFNESS_MAX, LOOP_STIFFNESS_SHARE * loop_stiffness_max_g_per_mm(rate))
    stiffness = float(math.exp(math.log(250.0) + share * (math.log(high) - math.log(250.0))))
    forces = (float(rng.uniform(250.0, 1500.0)), float(rng.uniform(250.0, 1500.0)))
    speed = float(rng.choice([40.0, 80.0, 120.0]))
    return Case(int(seed), fault, value, moment, fraction, duration, round(stiffness, 1), rate,
                (round(forces[0], 1), round(forces[1], 1)), speed)


@dataclass(frozen=True)
class Violation:
    """An invariant the truth broke: ``kind`` (over-force, step-after-latch, trial-without-contact), at ``time_s``
    (truth log time), in words."""

    kind: str
    time_s: float
    detail: str


def check_invariants(truth: np.ndarray, *, latches: Sequence[tuple[float, float | None]] = (),
                     trials: Sequence[tuple[float, float, float]] = ()) -> list[Violation]:
    """The invariants on the truth rows ``truth`` ((n, 5): :data:`COLUMNS`, time ascending).

    Parameters
    ----------
    latches : each time the controller held a latched fault: ``(start_s, end_s)`` on the truth log's clock (``end_s``
        None: to the end; it ends when an acknowledgement cleared it).
    trials : the trials the host recorded: ``(start_s, end_s, speed_mm_s)`` on the truth log's clock (the span of the
        host's call); the rows in it where the drum turns at more than half the trial's speed are the trial's.
    """
    out: list[Violation] = []
    if len(truth) == 0:
        return out
    t, force, drum, act = truth[:, 0], truth[:, 1], truth[:, 3], truth[:, 4]  # act: the motor's own travel
    i = int(np.argmax(force))
    if force[i] > FORCE_BOUND_G:
        out.append(Violation("over-force", float(t[i]), f"true force {force[i]:.0f} g > {FORCE_BOUND_G:.0f} g"))
    for latch_s, end_s in latches:
        before = np.nonzero(t <= latch_s + LATCH_GRACE_S)[0]  # where the latch's own control period left it
        at_latch = float(act[before[-1]]) if len(before) else float(act[0])
        after = np.nonzero((t > latch_s + LATCH_GRACE_S) & (t <= (math.inf if end_s is None else end_s)))[0]
        if len(after):
            j = after[int(np.argmax(act[after]))]
            if act[j] > at_latch + max(LATCH_STEP_MM, LATCH_PROOF_MM):
                out.append(Violation("step-after-latch", float(t[j]), f"the actuator's motor stepped {act[j] - at_latch:.3f} mm "
                                     f"towards the sensor {t[j] - latch_s:.2f} s after the latch at {latch_s:.2f} s"))
                break
    for start, end, speed in trials:
        rows = np.nonzero((t >= start) & (t <= end) & (np.abs(drum) > 0.5 * speed))[0]
        if len(rows) and float(np.min(force[rows])) < CONTACT_G:
            k = rows[int(np.argmin(force[rows]))]
            out.append(Violation("trial-without-contact", float(t[k]), f"a recorded trial's true force fell to "
                                 f"{force[k]:.0f} g while the drum ran ({start:.2f}-{end:.2f} s)"))
    return out


def read_truth_log(path: str | os.PathLike[str]) -> np.ndarray:
    """The :data:`COLUMNS` of a truth log CSV (:class:`rigctl.simulation.truth.TruthLog`), (n, 5) float64, picked by
    the header's names. Raises ValueError for a file without them."""
    with open(path, encoding="ascii") as f:
        header = f.readline().strip().split(",")
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise ValueError(f"{path} is no truth log: no column {', '.join(missing)}")
    rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, usecols=[header.index(c) for c in COLUMNS])
    return rows.reshape(-1, len(COLUMNS))


class ModelTruth:
    """The truth rows of an in-process model rig (:class:`rigctl.simulation.inprocess.InProcessEngine`): after each
    control period of its controller (<= its ``max_step_ms``, ending at each HX711 conversion) one row of the model's
    contact force, actuator position, drum speed and actuator motor position (:data:`COLUMNS`), and the first moment
    its controller was in FAULT.

    Parameters
    ----------
    engine : the engine (``engine.model``, ``engine.controller``); its controller's ``control_period`` is wrapped.
    """

    def __init__(self, engine: Any) -> None:
        self.engine = engine
        self.t0_s = 0.0
        self.rows: list[tuple[float, float, float, float, float]] = []
        #: each time the controller was in FAULT: [start_s, end_s or None]
        self.latches: list[list[float | None]] = []
        controller, model = engine.controller, engine.model
        step: Callable[[int], None] = controller.control_period
        fault_state = int(wire.DrumState.FAULT)

        def control_period(n_ms: int) -> None:
            step(n_ms)
            t = model.time_s - self.t0_s
            self.rows.append((t, model.contact_force_g, model.actuator_mm, model.drum_speed_mm_s,
                              model.actuator_motor_mm))
            faulted = int(controller.state) == fault_state
            if faulted and (not self.latches or self.latches[-1][1] is not None):
                self.latches.append([t, None])
            elif not faulted and self.latches and self.latches[-1][1] is None:
                self.latches[-1][1] = t

        controller.control_period = control_period

    @property
    def latch_spans(self) -> list[tuple[float, float | None]]:
        """:attr:`latches` as ``(start_s, end_s)`` tuples (for :func:`check_invariants`)."""
        return [(float(a or 0.0), b) for a, b in self.latches]

    def start(self) -> None:
        """Time 0 now (the run's start: the fault schedule's); rows before it keep negative times."""
        self.t0_s = float(self.engine.model.time_s)

    def array(self) -> np.ndarray:
        """The rows so far, (n, 5) float64 (:data:`COLUMNS`)."""
        return np.asarray(self.rows, dtype=float).reshape(-1, len(COLUMNS))
