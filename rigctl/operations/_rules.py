"""The host's safety rules, once: the rig's and the run's states, the events every face sends, and the allowed
transitions with their actions (:data:`TRANSITIONS`); anything else raises :class:`Refused`.

The model is bluesky's run engine (``RunEngine._TRANSITIONS``: one small table of allowed state changes behind one
lock). A state is a :class:`SafetyState`: whether a face holds the rig open (``link``), whether it moves under a
command (``motion``), whether a fault is latched (``latch``), whether the e-stop is pressed (``estop``) and the
run's state (``run``, one word of :data:`RUN_STATES`). :func:`decide` takes a state and an :class:`Event` and
returns the :class:`Transition` the table allows (its new state and its actions, in words) or raises; it keeps no
state of its own. :class:`SafetyTable` holds one state behind one lock and fires events at it (the property test's
model, and the rig owner's: :class:`rigctl.operations.RigControl` asks :func:`decide` before it moves anything).

``rigctl safety table`` prints :func:`table_markdown`; docs/safety.md holds it verbatim (a test compares them).
The rules, from ISO 13850 / IEC 60204-1 (docs/safety.md): acknowledging is not starting, opening is not starting,
a restart is not starting, and STOP means one thing on every face: the run pauses, resumable by one start.
"""

from __future__ import annotations

import dataclasses
import enum
import threading
from collections.abc import Callable, Iterable

__all__ = ["Event", "Refused", "RUN_STATES", "RUN_ENDED", "SafetyState", "SafetyTable", "Transition",
           "TRANSITIONS", "decide", "table_markdown"]

#: every state a protocol run can be in, on every face (the GUI, ``rigctl serve``, Python, the CLI, LSL markers):
#: ``ready`` (made, not started), ``queued`` (waits for the rig), ``running``, ``pausing`` (the trial in progress
#: ends first, or the rig still backs off), ``paused`` (at rest: after a pause, STOP, a latch; resumable by one
#: start), ``latched`` (a latched fault holds it: acknowledge, then start), ``aborting``, ``done`` (every planned
#: trial complete), ``stopped`` (ended early: aborted, a lost link; its session resumable), ``failed`` (an error),
#: ``aborted`` (taken off a queue before it started)
RUN_STATES = ("ready", "queued", "running", "pausing", "paused", "latched", "aborting", "done", "stopped", "failed",
              "aborted")
#: the run states of a run that has ended
RUN_ENDED = ("done", "stopped", "failed", "aborted")


class Event(enum.StrEnum):
    """What a face (or the rig itself) tells the owner: the events of :data:`TRANSITIONS`."""

    OPEN = "open"                      # a face opens the rig (the GUI's connect, acquire, doctor, serve, open_rig)
    CLOSE = "close"                    # the face closes it (the owner stops the rig safely first)
    FACE_LOST = "face lost"            # the face went silent: its dead man's switch, or the controller's watchdog
    FAULT = "fault"                    # the controller latched a fault, or the host saw one (a stall)
    ESTOP_PRESSED = "e-stop pressed"
    ESTOP_RELEASED = "e-stop released"
    CONTROLLER_RESET = "controller reset"  # the controller's RESET, BOOT_COUNT changed, or NOT_HOMED unasked
    ACKNOWLEDGE = "acknowledge"        # an operator, with a reason (the fault dialog, POST /ack, --ack, --resume)
    START = "start"                    # the start: Resume, POST /runs/{id}/resume, /queue/release, press, run, Home
    STOP = "STOP"                      # every face's STOP (the button, Esc, POST /stop, Ctrl-C, the dead man's)
    PAUSE = "pause"                    # after the trial in progress
    ABORT = "abort"                    # the run ends (finished trials kept, resumable)


class Refused(RuntimeError):
    """An event the table does not allow in this state (``event``, ``state``), with why in words."""

    def __init__(self, event: Event, state: "SafetyState", why: str) -> None:
        super().__init__(f"{event.value} refused: {why}")
        self.event, self.state, self.why = event, state, why


@dataclasses.dataclass(frozen=True)
class SafetyState:
    """The host's view of one rig and its run. ``link``: a face holds it open; ``motion``: it moves under a command
    (the force loop presses or the drum turns); ``latch``: a latched fault holds it (the controller's or the
    host's); ``estop``: the e-stop is pressed; ``run``: a word of :data:`RUN_STATES`, or "none"."""

    link: bool = False
    motion: bool = False
    latch: bool = False
    estop: bool = False
    run: str = "none"

    def __post_init__(self) -> None:
        if self.run != "none" and self.run not in RUN_STATES:
            raise ValueError(f"unknown run state {self.run!r}: one of {', '.join(RUN_STATES)}")


@dataclasses.dataclass(frozen=True)
class Transition:
    """What the table does for ``event`` in ``before``: the state ``after`` and the ``actions`` (in words, in
    order)."""

    event: Event
    before: SafetyState
    after: SafetyState
    actions: tuple[str, ...]


#: a row's guard: None when the event is allowed in the state, else why it is refused (in words)
Guard = Callable[[SafetyState], "str | None"]
#: a row's effect: the state after
Effect = Callable[[SafetyState], SafetyState]

_ACTIVE = ("running", "pausing")  # a run that records (or ends its trial)
_HELD = ("paused", "latched")     # a run at rest that one start resumes


def _pause_run(s: SafetyState) -> str:
    """A recording run pauses (resumable by one start); any other run keeps its state."""
    return "paused" if s.run in _ACTIVE else s.run


def _needs_open(s: SafetyState) -> str | None:
    return None if s.link else "no face holds the rig open"


def _never(_s: SafetyState) -> str | None:
    return None


def _start_refusal(s: SafetyState) -> str | None:
    if not s.link:
        return "no face holds the rig open"
    if s.estop:
        return "the e-stop is pressed"
    if s.latch:
        return "a latched fault holds the rig: acknowledge it first (acknowledging is not starting)"
    if s.run in ("aborting",):
        return "the run is aborting"
    return None


def _ack_refusal(s: SafetyState) -> str | None:
    if not s.link:
        return "no face holds the rig open"
    if not s.latch:
        return "nothing is latched: no fault to acknowledge"
    if s.estop:
        return "the e-stop is still pressed: release it first"
    return None


def _run_refusal(states: Iterable[str], what: str) -> Guard:
    allowed = tuple(states)

    def guard(s: SafetyState) -> str | None:
        if s.run not in allowed:
            return f"{what} needs a run that is {' or '.join(allowed)} (it is {s.run})"
        return None
    return guard


def _stopped(s: SafetyState, **changes: object) -> SafetyState:
    """At rest, the run paused: what STOP, a latch, a lost face and a close all do to the motion and the run."""
    return dataclasses.replace(s, motion=False, run=_pause_run(s), **changes)  # type: ignore[arg-type]


#: event -> (guard, effect, actions): the host's rules. Rows in the order docs/safety.md lists them.
TRANSITIONS: dict[Event, tuple[Guard, Effect, tuple[str, ...]]] = {
    Event.OPEN: (
        lambda s: "a face holds the rig open already (a second opener is refused)" if s.link else None,
        lambda s: dataclasses.replace(s, link=True),
        ("read the controller and leave it as it is (no HOME, no press, no turn)",
         "keep every latch the controller or the queue file holds; a run found paused stays paused")),
    Event.CLOSE: (
        _needs_open,
        lambda s: _stopped(s, link=False),
        ("STOP (drum to rest, actuator backed off)", "a recording run pauses (kept, resumable)")),
    Event.FACE_LOST: (
        _needs_open,
        lambda s: _stopped(s, link=False),
        ("STOP by the dead man's switch (or the controller's watchdog latches WATCHDOG)",
         "a recording run pauses (kept, resumable)")),
    Event.FAULT: (
        _never,
        lambda s: _stopped(s, latch=True),
        ("the controller stops (drum to rest, actuator backed off where its way is proven)",
         "latch it: every start refused until an acknowledgement", "a recording run pauses")),
    Event.ESTOP_PRESSED: (
        _never,
        lambda s: _stopped(s, latch=True, estop=True),
        ("the drivers drop at once (a stop of category 0: the sensor may stay pressed)", "latch `estop`",
         "a recording run pauses")),
    Event.ESTOP_RELEASED: (
        lambda s: None if s.estop else "the e-stop is not pressed",
        lambda s: dataclasses.replace(s, estop=False),
        ("nothing moves; the latch stays until acknowledged",)),
    Event.CONTROLLER_RESET: (
        _never,
        lambda s: _stopped(s, latch=True),
        ("the controller comes up NOT_HOMED, drivers off; away from home it latches RESET itself (firmware 1.5)",
         "latch `reset` for every face until acknowledged",
         "a recording run pauses")),
    Event.ACKNOWLEDGE: (
        _ack_refusal,
        lambda s: dataclasses.replace(s, latch=False, run="paused" if s.run == "latched" else s.run),
        ("CLEAR_FAULT on the controller, log who and why", "nothing moves (no HOME, no press, no turn)",
         "a run stays paused until its start")),
    Event.START: (
        _start_refusal,
        lambda s: dataclasses.replace(s, motion=True, run="running" if s.run in _HELD + ("ready", "queued")
                                      else s.run),
        ("HOME and TARE first when pending (after an open, an acknowledgement or a reset)",
         "press, then turn; a paused run goes on (the trial STOP cut short recorded again)")),
    Event.STOP: (
        _never,
        lambda s: _stopped(s),
        ("drum to rest, actuator backed off (never refused)",
         "a recording run pauses: the trial in progress discarded, one start resumes it")),
    Event.PAUSE: (
        _run_refusal(_ACTIVE, "pause"),
        lambda s: _stopped(s),
        ("the trial in progress ends, then the sensor is released", "the run pauses: one start resumes it")),
    Event.ABORT: (
        _run_refusal(("ready", "queued", "running", "pausing", "paused", "latched"), "abort"),
        lambda s: dataclasses.replace(s, motion=False, run="stopped"),
        ("STOP", "the run ends: finished trials kept, its session resumable")),
}


def decide(state: SafetyState, event: Event | str, table: dict[Event, tuple[Guard, Effect, tuple[str, ...]]]
           | None = None) -> Transition:
    """The transition the table allows for ``event`` in ``state`` (pure: nothing kept). Raises :class:`Refused`
    (why, in words) for an event the table refuses in this state, ValueError for an unknown event. ``table``:
    :data:`TRANSITIONS` (tests pass a mutated copy)."""
    event = Event(event)
    guard, effect, actions = (table or TRANSITIONS)[event]
    why = guard(state)
    if why is not None:
        raise Refused(event, state, why)
    return Transition(event, state, effect(state), actions)


class SafetyTable:
    """One rig's state behind one lock: :meth:`fire` an event, read :attr:`state`. ``table``: the rules
    (default :data:`TRANSITIONS`)."""

    def __init__(self, state: SafetyState | None = None, *,
                 table: dict[Event, tuple[Guard, Effect, tuple[str, ...]]] | None = None) -> None:
        self._lock = threading.Lock()
        self._state = state or SafetyState()
        self._table = table or TRANSITIONS

    @property
    def state(self) -> SafetyState:
        with self._lock:
            return self._state

    def fire(self, event: Event | str) -> Transition:
        """Apply ``event`` (:func:`decide`); the state changes only when the table allows it. Refused."""
        with self._lock:
            t = decide(self._state, event, self._table)
            self._state = t.after
            return t


# ------------------------------------------------------------------------------------------------------ markdown
#: the states each row is shown for in the table: (link, motion, latch, estop, run)
_WHEN = {
    Event.OPEN: "no face holds the rig",
    Event.CLOSE: "a face holds it",
    Event.FACE_LOST: "a face holds it",
    Event.FAULT: "any",
    Event.ESTOP_PRESSED: "any",
    Event.ESTOP_RELEASED: "the e-stop pressed",
    Event.CONTROLLER_RESET: "any",
    Event.ACKNOWLEDGE: "open, latched, the e-stop released",
    Event.START: "open, nothing latched, the e-stop released, the run not aborting",
    Event.STOP: "any",
    Event.PAUSE: "a run running or pausing",
    Event.ABORT: "a run not ended",
}
_THEN = {
    Event.OPEN: "open; motion, latch and run unchanged",
    Event.CLOSE: "closed, at rest; a running run paused",
    Event.FACE_LOST: "closed, at rest; a running run paused",
    Event.FAULT: "latched, at rest; a running run paused",
    Event.ESTOP_PRESSED: "latched, e-stop pressed, at rest; a running run paused",
    Event.ESTOP_RELEASED: "e-stop released; still latched",
    Event.CONTROLLER_RESET: "latched, at rest; a running run paused",
    Event.ACKNOWLEDGE: "not latched; motion unchanged (at rest); the run paused",
    Event.START: "moving; a paused, ready or queued run running",
    Event.STOP: "at rest; a running run paused",
    Event.PAUSE: "at rest; the run paused",
    Event.ABORT: "at rest; the run stopped (resumable)",
}


def table_markdown() -> str:
    """The table as markdown (``rigctl safety table``; docs/safety.md holds it verbatim): one row an event, when it
    is allowed (anything else is refused), the state after, the actions."""
    lines = ["| event | allowed when (else refused) | then | actions |", "|---|---|---|---|"]
    for event, (_guard, _effect, actions) in TRANSITIONS.items():
        lines.append(f"| {event.value} | {_WHEN[event]} | {_THEN[event]} | {'; '.join(actions)} |")
    states = ", ".join(f"`{s}`" for s in RUN_STATES)
    lines += ["", f"Run states (every face's one vocabulary): {states}."]
    return "\n".join(lines) + "\n"
