"""Fault injection on the simulated rigs: the ``--inject FAULT@T[+D]`` spec, its schedule and the hook a rig implements.

One spec per fault, ``FAULT@T[+D]``: ``FAULT`` (a name of :data:`FAULTS`, ``taxel-ohm=N`` with its value) starts
``T`` s after the rig's clock was armed (:meth:`FaultSchedule.start`: when the rig is open, i.e. when ``rigctl
acquire``'s run starts) and ends ``D`` s later (no ``+D``: it stays to the end; ``estop@3`` presses the e-stop and
never releases it, ``reset@3`` is an instant). Times are the rig's own clock: simulated time on the in-process rig,
the physics clock of the simulated rig on ptys, the firmware's clock under simavr.

``FAULT@0`` (:attr:`FaultSpec.at_power_on`) means the rig is wired that way from power-on: :func:`rigctl.rigs.open_rig`
arms the schedule before the rig opens with ``inject_faults(specs, power_on=True)``, which applies the ``@0`` ones
at once and powers the drum controller on again with them (a miswired rig, a corrupt EEPROM found at boot); every
fault time of that run then counts from the power-on.

A rig backend that can inject faults implements :class:`FaultInjector` (the model rigs through
``rigctl.simulation.faults.ModelFaults``; the firmware under simavr through its harness): ``fault_refusal(spec)``
says in one line why it cannot model a fault (None when it can), ``inject_faults(specs)`` arms a
:class:`FaultSchedule` on the rig's clock, whose :meth:`FaultSchedule.due` the clock calls with its time to start
and end what is due. :func:`rigctl.rigs.open_rig` (``inject=``) checks every spec against the backend before
anything opens and arms the schedule once the rig is open.

Faults (docs/safety.md has what the rig does with each and what clears it):
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

__all__ = ["FAULTS", "FaultSpec", "FaultSpecError", "FaultSchedule", "FaultInjector", "parse_fault", "parse_faults",
           "check_faults"]

#: every fault ``--inject`` knows: name -> what it does on a rig (one line)
FAULTS: dict[str, str] = {
    "estop": "the e-stop is pressed at T and released at T+D (its contact opens: drivers off at once, ESTOP latched)",
    "reset": "the drum controller resets at T (under load or in motion it latches RESET itself: FAULT, drivers off; "
             "else NOT_HOMED); D is not used",
    "reversed-cell": "the load cell reads reversed (negative under load) from T to T+D",
    "reversed-actuator": "the actuator moves the wrong way (away from the sensor when the loop presses) from T to T+D",
    "host-silence": "the host's link to the drum controller is cut (USB pulled) from T to T+D: nothing reaches it",
    "reversed-drum": "the drum turns backwards (a swapped coil pair of its motor) from T to T+D",
    "stall": "the drum is blocked (its stepper loses every step: the index and speed marks stop passing) from T to T+D",
    "slip": "slip=N%: the drum turns N % less than its steps say (a slipping coupling; the speed marks come late) "
            "from T to T+D",
    "hx711-10sps": "the HX711 comes up at 10 samples/s (its RATE pin low): the drum controller resets at T and "
                   "measures the wrong rate at boot",
    "taxel-ohm": "taxel-ohm=N: every taxel's source impedance is N Ohm from T to T+D (the multiplexer's crosstalk)",
    "taxel-link-drop": "the taxel board's link drops (no frame arrives) from T to T+D",
    "hx711-sck-broken": "the HX711's SCK wire is broken from T to T+D (never clocked: DOUT stays low after a "
                        "conversion and every read the controller makes returns 0)",
    "hx711-frozen": "the HX711's output freezes at its raw value at T (the same 24 bits every conversion, at its "
                    "rate) until T+D",
    "contact-stiffness": "contact-stiffness=G_PER_MM: the plate is swapped at T for one whose contact stiffness is "
                         "G_PER_MM g/mm (1 to 5000, the stiffest a rig config accepts; the rig's own again at T+D)",
    "eeprom-corrupt": "the drum controller browns out at T while writing its EEPROM: the stored calibration fails "
                      "its checksum and the controller resets (with @0: corrupt from power-on); D is not used",
    "home-switch": "home-switch=closed|open: the actuator's home switch reads closed wherever the actuator is (its "
                   "wire shorted to the frame) or never closes (a broken wire) from T to T+D",
    "cell-gain": "cell-gain=X: the load cell gives X times the signal its calibration says (creep, an excitation "
                 "lead's joint, a cell of another range; 0.3-3) from T to T+D",
    "cell-offset": "cell-offset=G: the load cell's zero moves by G g (a mount changed since calibration, a cable "
                   "pulled; -5000 to 5000) from T to T+D",
    "coupling-slip": "coupling-slip=N%: the actuator's coupling slips N % of the motor's steps and catches up at once "
                     "when the motor holds still (the screw jumps) from T to T+D",
    "steps-lost": "steps-lost=N%: the actuator's motor loses N % of its steps for good (a weak driver, a binding "
                  "screw) from T to T+D",
    "hx711-dout-noise": "hx711-dout-noise=P: each bit the controller reads on the HX711's DOUT wire flips with "
                        "probability P (interference on the wire; 0-1) from T to T+D",
    "driver-enable-stuck": "the stepper drivers' EN input is stuck active (a shorted wire): they drive whatever the "
                           "controller's EN output says, from T to T+D",
    "calibration-scale": "calibration-scale=X: a wrong calibration is saved at T (the load-cell scale X times the "
                         "true one, its checksum valid; 0.3-3) and the controller powered on again with it; D is not "
                         "used",
}
__doc__ = (__doc__ or "") + "\n".join(f"- ``{name}``: {what}" for name, what in FAULTS.items()) + "\n"

#: faults that happen at one instant (their duration is not used)
INSTANT_FAULTS = frozenset({"reset", "hx711-10sps", "eeprom-corrupt", "calibration-scale"})
#: faults that take a value (``name=value``)
VALUED_FAULTS = frozenset({"taxel-ohm", "slip", "contact-stiffness", "home-switch", "cell-gain", "cell-offset",
                           "coupling-slip", "steps-lost", "hx711-dout-noise", "calibration-scale"})
#: faults whose value is a percentage (``slip=20%``; the ``%`` may be left out), 0-100
PERCENT_FAULTS = frozenset({"slip", "coupling-slip", "steps-lost"})
#: faults whose value is a word: name -> {word: the value it stands for}
WORD_VALUES: dict[str, dict[str, float]] = {"home-switch": {"open": 0.0, "closed": 1.0}}
#: the range of each valued fault's value (the others: 0 to 1e9): a contact stiffness in g/mm must be > 0
VALUE_RANGES: dict[str, tuple[float, float]] = {
    "slip": (0.0, 100.0), "contact-stiffness": (1.0, 5000.0), "coupling-slip": (0.0, 100.0), "steps-lost": (0.0, 100.0),
    "cell-gain": (0.3, 3.0), "cell-offset": (-5000.0, 5000.0), "hx711-dout-noise": (0.0, 1.0),
    "calibration-scale": (0.3, 3.0), "home-switch": (0.0, 1.0)}

_SPEC = re.compile(r"^(?P<name>[a-z0-9-]+)(=(?P<value>[^@]+))?@(?P<at>[^+]+)(\+(?P<dur>.+))?$")


class FaultSpecError(ValueError):
    """A malformed ``--inject`` spec, or a fault the rig cannot model (one line naming why)."""


@dataclass(frozen=True)
class FaultSpec:
    """One injected fault: ``name`` (a key of :data:`FAULTS`), ``at_s`` (start, s after the schedule starts, >= 0),
    ``duration_s`` (s; ``math.inf``: to the end; 0 for an instant fault), ``value`` (``taxel-ohm``'s Ohm,
    ``slip``'s percent, else None)."""

    name: str
    at_s: float
    duration_s: float = math.inf
    value: float | None = None

    @property
    def at_power_on(self) -> bool:
        """``FAULT@0``: the rig is wired that way from power-on (in place before the controller boots and homes)."""
        return self.at_s == 0.0

    @property
    def end_s(self) -> float:
        """When the fault ends, s after the schedule starts (inf: never)."""
        return self.at_s + self.duration_s

    def __str__(self) -> str:
        words = {v: w for w, v in WORD_VALUES.get(self.name, {}).items()}
        value = ("" if self.value is None else f"={words[self.value]}" if self.value in words
                 else f"={self.value:g}{'%' if self.name in PERCENT_FAULTS else ''}")
        dur = "" if math.isinf(self.duration_s) or self.name in INSTANT_FAULTS else f"+{self.duration_s:g}"
        return f"{self.name}{value}@{self.at_s:g}{dur}"


def _seconds(text: str, what: str, spec: str) -> float:
    try:
        value = float(text.strip().removesuffix("s"))
    except ValueError:
        raise FaultSpecError(f"--inject {spec}: {what} {text!r} is not a number of seconds") from None
    if not math.isfinite(value) or value < 0 or value > 1e6:
        raise FaultSpecError(f"--inject {spec}: {what} must be 0 to 1e6 s, got {text}")
    return value


def parse_fault(spec: str) -> FaultSpec:
    """Parse ``FAULT[=VALUE]@T[+D]`` (e.g. ``estop@3+2``, ``taxel-ohm=47000@0``, ``slip=20%@5+2``, ``reset@5``,
    ``contact-stiffness=5000@4``, ``hx711-frozen@2``, ``eeprom-corrupt@0``).

    Raises FaultSpecError (a ValueError) naming what is wrong: the form, an unknown fault (with the known ones), a
    missing or unexpected value, a time that is not a number of seconds in 0..1e6."""
    text = str(spec).strip()
    m = _SPEC.match(text.lower())
    if m is None:
        raise FaultSpecError(f"--inject {text}: expected FAULT@T[+D] (e.g. estop@3+2: the e-stop pressed 3 s after the "
                             "run starts, released 2 s later)")
    name = m["name"]
    if name not in FAULTS:
        raise FaultSpecError(f"--inject {text}: unknown fault {name!r}; one of {', '.join(FAULTS)}")
    value: float | None = None
    if name in VALUED_FAULTS:
        if m["value"] is None:
            raise FaultSpecError(f"--inject {text}: {name} needs a value ({name}=N@T)")
        low, top = VALUE_RANGES.get(name, (0.0, 1e9))
        words = WORD_VALUES.get(name)
        if words is not None:
            if m["value"] not in words:
                raise FaultSpecError(f"--inject {text}: {name}'s value must be one of {', '.join(words)}")
            value = words[m["value"]]
        else:
            try:
                value = float(m["value"].removesuffix("%") if name in PERCENT_FAULTS else m["value"])
            except ValueError:
                raise FaultSpecError(f"--inject {text}: {name}'s value {m['value']!r} is not a number") from None
        if not (math.isfinite(value) and low <= value <= top):
            raise FaultSpecError(f"--inject {text}: {name}'s value must be {low:g} to {top:g}, got {m['value']}")
    elif m["value"] is not None:
        raise FaultSpecError(f"--inject {text}: {name} takes no value")
    at = _seconds(m["at"], "the start", text)
    if name in INSTANT_FAULTS:
        duration = 0.0
    else:
        duration = math.inf if m["dur"] is None else _seconds(m["dur"], "the duration", text)
    return FaultSpec(name, at, duration, value)


def parse_faults(specs: Iterable[str]) -> tuple[FaultSpec, ...]:
    """Every spec of a repeatable ``--inject`` option parsed, in order (FaultSpecError for the first bad one)."""
    return tuple(parse_fault(s) for s in specs)


@runtime_checkable
class FaultInjector(Protocol):
    """The hook a rig backend implements to inject faults (the model rigs: ``InProcessBackend`` and
    ``PtyRigBackend`` on a ``SimulatedRig``, through ``rigctl.simulation.faults.ModelFaults``; the firmware under
    simavr: its harness). :func:`rigctl.rigs.open_rig` asks :meth:`fault_refusal` of every spec before the rig
    opens and calls :meth:`inject_faults` once it is open."""

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why this rig cannot model ``spec`` (one line), or None when it can."""
        ...

    def inject_faults(self, specs: Sequence[FaultSpec], *, power_on: bool = False) -> "FaultSchedule":
        """Arm ``specs`` on the rig's own clock from now (its time 0); the rig applies each start and end as its
        clock passes them (:meth:`FaultSchedule.due`). ``power_on``: the ``FAULT@0`` specs are applied now and the
        drum controller is powered on again (it boots wired that way: :func:`rigctl.rigs.open_rig` arms such a
        schedule before the rig opens). Returns the schedule."""
        ...


def check_faults(backend: object, specs: Iterable[FaultSpec], *, kind: str) -> None:
    """Raise FaultSpecError when ``backend`` cannot inject one of ``specs``: it is no :class:`FaultInjector` (the
    hardware rig), or its ``fault_refusal`` names why."""
    specs = tuple(specs)
    if not specs:
        return
    if not isinstance(backend, FaultInjector):
        raise FaultSpecError(f"--inject: the {kind} rig cannot inject faults (only the simulated rigs: --sim, "
                             "--inprocess, --hil)")
    for spec in specs:
        why = backend.fault_refusal(spec)
        if why:
            raise FaultSpecError(f"--inject {spec}: not on the {kind} rig: {why}")


class FaultSchedule:
    """The injected faults on one clock: :meth:`start` arms it at the clock's time ``t0``; :meth:`due` (called with
    the clock's time as it advances) applies every start and end that came due since the last call, in time order,
    to ``apply(spec, active)`` (start: True, end: False). Thread-safe; ``applied`` lists ``(time_s, spec, active)``
    for tests and logs."""

    def __init__(self, specs: Iterable[FaultSpec], apply: Callable[[FaultSpec, bool], None]):
        self.specs = tuple(specs)
        self.apply = apply
        self._t0: float | None = None
        self._edges: list[tuple[float, int, FaultSpec, bool]] = []
        for i, spec in enumerate(self.specs):
            self._edges.append((spec.at_s, i, spec, True))
            if spec.name not in INSTANT_FAULTS and math.isfinite(spec.end_s):
                self._edges.append((spec.end_s, i, spec, False))
        self._edges.sort(key=lambda e: (e[0], e[1], not e[3]))
        self._lock = threading.Lock()
        self.applied: list[tuple[float, FaultSpec, bool]] = []

    @property
    def armed(self) -> bool:
        return self._t0 is not None

    @property
    def pending(self) -> int:
        """Starts and ends not applied yet."""
        with self._lock:
            return len(self._edges)

    def start(self, t0_s: float) -> None:
        """Arm the schedule: its times count from the clock's ``t0_s`` (the first call wins)."""
        with self._lock:
            if self._t0 is None:
                self._t0 = float(t0_s)

    def due(self, now_s: float) -> None:
        """Apply every start and end due by the clock's ``now_s`` (nothing before :meth:`start`)."""
        with self._lock:
            if self._t0 is None or not self._edges:
                return
            t = float(now_s) - self._t0
            ready = []
            while self._edges and self._edges[0][0] <= t + 1e-9:
                ready.append(self._edges.pop(0))
        for at, _, spec, active in ready:
            self.apply(spec, active)
            self.applied.append((at, spec, active))
