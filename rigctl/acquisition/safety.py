"""The rig's one safety policy: which conditions latch, what the rig does then, and what clears them.

Every face (CLI, GUI, server, Python protocols) reaches the rig through :class:`rigctl.acquisition.rig.Rig` (held by
:class:`rigctl.operations.RigControl`), whose :class:`SafetyLatch` this is; none decides what a fault means.

- **Latched** (:func:`latch_for`): every fault the drum controller latches (e-stop, over-force, reversed load cell,
  host watchdog, load cell silent, actuator end of travel, HOME failure, wrong HX711 rate, a drum that slips or
  stalls: its speed marks late), an unexpected reset of the controller (NOT_HOMED or a new BOOT_COUNT), a stalled
  drum; a drum link lost mid-press latches WATCHDOG in the
  controller (seen when the link is back; meanwhile the run ends after a bounded wait, resumable). The rig stops motion
  (STOP), the latch holds (:attr:`SafetyLatch.latch`) and every motion the host asks for (press, run, home) is
  refused with :class:`LatchedFault` until an operator acknowledges it (:meth:`rigctl.acquisition.rig.Rig.acknowledge`:
  the condition must be gone: the e-stop released; then CLEAR_FAULT, HOME and TARE). Releasing the e-stop never
  restarts anything. A run pauses (``on_latch="wait"``: GUI, server) or ends resumably (``"end"``: ``rigctl
  acquire``, whose ``--resume`` is the acknowledgement); the latch and its acknowledgement go into the session's event
  log.
- **Recoverable** (everything else: a dropped frame, a CRC error, a late or lost Modbus answer, a trial that lost
  frames, a force that did not settle): the trial is recorded again (the protocol's ``retries``).

docs/safety.md holds the table: fault -> what the rig does -> what clears it.
"""

from __future__ import annotations

import datetime as _dt
import getpass
import logging
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from rigctl.core.drum import CRUSH_NOTE, FAULT_WORDS, DrumError, DrumFault, DrumReset, Fault, describe_faults

__all__ = ["Latch", "Acknowledgement", "LatchedFault", "DrumStall", "SafetyLatch", "latch_for", "latch_from_faults",
           "CAUSES", "operator_name"]

log = logging.getLogger(__name__)

#: what a crush-class cause's remedy adds (rigctl.core.drum.CRUSH_FAULTS)
_CRUSH = f" ({CRUSH_NOTE})"

#: every latch cause: (label, what the operator does before acknowledging)
CAUSES: dict[str, tuple[str, str]] = {
    "estop": ("e-stop", "release the e-stop"),
    "force-limit": ("force limit exceeded", "check the plate and the sensor, lower the force setpoint" + _CRUSH),
    "reversed-cell": ("load cell reversed", "mount the load cell the right way (or fix the sign of its scale)" + _CRUSH),
    "watchdog": ("host watchdog expired", "make sure the host program and its USB link are alive"),
    "loadcell-timeout": ("load cell not responding", "check the HX711's wiring"),
    "actuator-direction": ("actuator turning the wrong way or load cell reversed",
                           "press the load cell by hand and read FORCE_G: if it rises, swap one coil pair of the "
                           "actuator motor; if it falls, the cell is reversed: swap A+/A- at the HX711, not the "
                           "motor's coils (rigctl doctor --check actuator-direction)" + _CRUSH),
    "actuator-travel": ("actuator end of travel", "mount a plate, check the gap between drum and sensor (and that "
                                                  "the actuator turns the right way: a reversed motor drives into its "
                                                  "rear stop while its steps count on)"),
    "home-failed": ("HOME failed", "check the home switch and its wire"),
    "hx711-rate": ("wrong HX711 rate", "set the HX711's RATE pin (or the rig config's force_loop) to match"),
    "reset": ("unexpected controller reset", "check the controller's power and reset line"),
    "stall": ("drum stalled or slipping", "free the drum (nothing may block it), check its coupling, the stepper and "
              "its driver's current"),
    "contact-stiffness": ("contact too stiff", "use a softer sensor mount or pad, or store slower force-loop gains (the "
                          "rig config's force_loop)" + _CRUSH),
}

#: the cause of each controller fault bit (the first that is set names the latch)
_FAULT_CAUSES: tuple[tuple[Fault, str], ...] = (
    (Fault.ESTOP, "estop"), (Fault.FORCE_LIMIT, "force-limit"), (Fault.LOADCELL_REVERSED, "reversed-cell"),
    (Fault.WATCHDOG, "watchdog"), (Fault.LOADCELL_TIMEOUT, "loadcell-timeout"),
    (Fault.ACTUATOR_DIRECTION, "actuator-direction"), (Fault.ACTUATOR_TRAVEL, "actuator-travel"),
    (Fault.HOME_NOT_FOUND, "home-failed"), (Fault.HX711_RATE, "hx711-rate"),
    (Fault.DRUM_SLIP, "stall"), (Fault.CONTACT_STIFFNESS, "contact-stiffness"),
)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def operator_name() -> str:
    """Who is at this terminal (the login name; ``"operator"`` when it cannot be told)."""
    try:
        return getpass.getuser()
    except (OSError, KeyError, ImportError):  # no login name (a container without a passwd entry)
        return "operator"


@dataclass(frozen=True)
class Latch:
    """A latched condition: ``cause`` (a key of :data:`CAUSES`), ``detail`` (what was seen, in words), ``faults``
    (the controller's fault bits, 0 for host-detected causes), ``at_utc`` (ISO 8601 UTC)."""

    cause: str
    detail: str
    faults: int = 0
    at_utc: str = field(default_factory=_utc_now)

    @property
    def label(self) -> str:
        return CAUSES.get(self.cause, (self.cause, ""))[0]

    @property
    def remedy(self) -> str:
        """What the operator does before acknowledging."""
        return CAUSES.get(self.cause, ("", "remove the cause"))[1]

    def describe(self) -> str:
        """One line: the cause, what was seen, what to do."""
        return f"{self.label}: {self.detail}; {self.remedy}, then acknowledge"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Acknowledgement:
    """An operator's acknowledgement of :attr:`latch`: ``reason`` (their words), ``by`` (who), ``at_utc``."""

    latch: Latch
    reason: str
    by: str
    at_utc: str = field(default_factory=_utc_now)

    def to_dict(self) -> dict[str, Any]:
        return {"clears": self.latch.to_dict(), "reason": self.reason, "by": self.by, "at_utc": self.at_utc}


class LatchedFault(RuntimeError):
    """The rig holds a latched fault (:attr:`latch`): motion is refused until an operator acknowledges it."""

    def __init__(self, latch: Latch, what: str = "") -> None:
        self.latch = latch
        super().__init__(f"{what + ': ' if what else ''}{latch.describe()}")


class DrumStall(DrumError):
    """The drum does not turn although it is told to (blocked, a stepper that lost its steps): latched."""


def latch_from_faults(faults: int, detail: str = "") -> Latch:
    """The latch of the controller's fault bits ``faults`` (its cause: the first set bit of :data:`_FAULT_CAUSES`)."""
    bits = Fault(int(faults))
    cause = next((c for bit, c in _FAULT_CAUSES if bit in bits), "reset")
    words = detail or (FAULT_WORDS[bits].meaning if bits in FAULT_WORDS else describe_faults(int(bits)))
    return Latch(cause, words, int(bits))


def latch_for(exc: BaseException) -> Latch | None:
    """The latch a failure stands for (None: a recoverable failure, retried)."""
    if isinstance(exc, LatchedFault):
        return exc.latch
    if isinstance(exc, DrumFault):
        return latch_from_faults(exc.faults, str(exc))
    if isinstance(exc, DrumReset):
        return Latch("reset", str(exc))
    if isinstance(exc, DrumStall):
        return Latch("stall", str(exc))
    return None


class SafetyLatch:
    """The rig's latch (one per :class:`rigctl.acquisition.rig.Rig`). Thread-safe.

    Attributes
    ----------
    latch : the condition latched now, or None.
    history : every latch and acknowledgement since the rig opened, in order.
    listeners : callables receiving each :class:`Latch` when it trips and each :class:`Acknowledgement` (the run
        engine writes them into the session's event log; faces show them).
    """

    def __init__(self) -> None:
        self.latch: Latch | None = None
        self.history: list[Latch | Acknowledgement] = []
        self.listeners: list[Callable[[Latch | Acknowledgement], Any]] = []
        self._lock = threading.Lock()
        self.cleared = threading.Condition(self._lock)

    @property
    def latched(self) -> bool:
        return self.latch is not None

    def trip(self, latch: Latch) -> Latch:
        """Latch ``latch`` (a latch already held stays: the first cause is the one to clear); returns the one held."""
        with self._lock:
            if self.latch is not None:
                return self.latch
            self.latch = latch
            self.history.append(latch)
        log.error("LATCHED: %s", latch.describe())
        self._tell(latch)
        return latch

    def refuse(self, what: str) -> None:
        """Raise :class:`LatchedFault` when latched (``what``: the motion refused)."""
        latch = self.latch
        if latch is not None:
            raise LatchedFault(latch, f"{what} refused")

    def clear(self, reason: str, by: str) -> Acknowledgement:
        """Record the acknowledgement of the latch held and clear it (the rig has made the controller safe and ready
        first: :meth:`rigctl.acquisition.rig.Rig.acknowledge`). ValueError when nothing is latched or no reason."""
        reason, by = str(reason).strip(), str(by).strip()
        if not reason or not by:
            raise ValueError("an acknowledgement needs a reason and who gives it")
        with self._lock:
            if self.latch is None:
                raise ValueError("nothing is latched: no fault to acknowledge")
            ack = Acknowledgement(self.latch, reason, by)
            self.latch = None
            self.history.append(ack)
            self.cleared.notify_all()
        log.warning("acknowledged by %s (%s): %s", by, reason, ack.latch.label)
        self._tell(ack)
        return ack

    def wait_cleared(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` (wall time) for the latch to clear; True when clear."""
        with self._lock:
            return self.cleared.wait_for(lambda: self.latch is None, timeout_s)

    def _tell(self, item: Latch | Acknowledgement) -> None:
        for fn in list(self.listeners):
            try:
                fn(item)
            except Exception:  # noqa: BLE001 - a face's listener never breaks the latch
                log.exception("safety listener failed")
