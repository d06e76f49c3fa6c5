"""The rig's monitor: one thread, owned by :class:`rigctl.operations.RigControl`, that reads the drum controller's
status, keeps its watchdog fed while the faces that command motion are alive, and tells subscribers what changed.

Faces (the GUI, the CLI, the server) never poll the controller or feed its watchdog themselves: they
:meth:`RigMonitor.subscribe` to its :class:`RigEvent` s (called from the monitor's thread, or the publisher's: a face
hands them on to its own thread, the GUI through a queued Qt signal) and read :attr:`RigMonitor.latest` and
:attr:`RigMonitor.history`. The stream is one for every face: the poll's state, fault, link and dead-man events, the
safety latch (``latch``: a fault latched, an acknowledgement) and the run on the rig (``progress``, ``run``: its trial
events), which :class:`rigctl.operations.RigControl` and :class:`rigctl.operations.ProtocolRun` publish. Subscribing
does not start the poll: :attr:`rigctl.operations.RigControl.monitor` does (the GUI, ``rigctl serve``);
``rigctl acquire`` only listens (its run reads the controller itself, on the rig's own clock).

**Dead man's switch.** A face that can freeze while the rig moves (the GUI: its event loop) registers a
:class:`Heartbeat` and beats it from the thread that must stay alive (the GUI: a QTimer on the GUI thread every ~0.1
s). When a heartbeat is older than its ``timeout_s`` (0.5 s) while the rig moves under a command (the drum runs or
the force loop presses the sensor), the monitor stops the rig (the owner's STOP: drum to rest, actuator backed off,
a run paused; again every 0.5 s while it keeps moving) and publishes a ``deadman`` event saying why (a face that
wakes shows it). If a STOP is not acknowledged, no status read feeds the controller's watchdog until the face
answers again: the controller's own watchdog (WATCHDOG_MS) stops the rig. The monitor judges the age of a heartbeat
on its own clock less its own lateness: when the whole process was starved (the monitor woke late too), a heartbeat
is not blamed for it. A face that owns its run in its own process (``rigctl acquire``, ``rigctl serve``) registers
no heartbeat: the process is the heartbeat (a dead process stops polling and the controller's watchdog trips).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from rigctl.core.drum import DrumState, DrumStatus, describe_faults
from rigctl.core.errors import describe_error
from rigctl.core.interfaces import DrumMonitor
from rigctl.core.progress import ProgressEvent
from rigctl.core.shared_clock import pause_on

if TYPE_CHECKING:
    from rigctl.acquisition.runner import TrialEvent
    from rigctl.acquisition.safety import Acknowledgement, Latch

__all__ = ["EVENT_KINDS", "DEADMAN_TIMEOUT_S", "Heartbeat", "RigEvent", "RigMonitor", "StatusHistory", "commanded"]

log = logging.getLogger(__name__)

#: what a :class:`RigEvent` can be: every status read (``status``), a new controller state (``state``), latched
#: fault bits set or cleared (``faults``), the drum link lost or back (``link``), the dead man's switch stopping the
#: rig (``deadman``), and what other parts publish through :meth:`RigMonitor.publish`: the safety latch tripped or
#: acknowledged (``latch``), a run's progress (``progress``) and its trial events (``run``), what the handheld rig's
#: operator is told (``prompt``: ``fields["cue"]`` "plate" or "go") and a scan's live prediction (``prediction``)
EVENT_KINDS = ("status", "state", "faults", "link", "deadman", "latch", "progress", "run", "prompt", "prediction")
#: how long a face's heartbeat may be silent while the rig moves before the rig is stopped, s (issue 35)
DEADMAN_TIMEOUT_S = 0.5
#: the states in which the rig moves: the force loop presses the sensor, or the drum turns
_MOVING_STATES = (DrumState.SEEKING_FORCE, DrumState.FORCE_SETTLED, DrumState.RUNNING)
#: a drum turning faster than this counts as moving whatever its state says, mm/s
_MOVING_SPEED_MM_S = 0.5
#: after a failed read the monitor waits this long before reading again, s
_RETRY_S = 0.5
#: while a face stays silent and the rig still moves under a command, STOP is sent again this often, s
_RESTOP_S = 0.5


@dataclass(frozen=True)
class RigEvent:
    """What the monitor (or a part publishing through it) tells its subscribers.

    Attributes
    ----------
    kind : one of :data:`EVENT_KINDS`.
    message : the event in words (empty for ``status``).
    time_s : ``time.monotonic()`` when it happened, s.
    status : the controller status it comes from (None for a lost link and published events).
    progress : the run's :class:`rigctl.core.progress.ProgressEvent` (``progress``), else None.
    trial : the run's :class:`rigctl.acquisition.runner.TrialEvent` (``run``), else None.
    latch : the :class:`rigctl.acquisition.safety.Latch` tripped or the
        :class:`rigctl.acquisition.safety.Acknowledgement` that cleared one (``latch``), else None.
    fields : the details of a ``prompt`` (cue, texture, profile, trial_id, start/end speeds) or a ``prediction``
        (trial_id, truth, profile, predicted, correct, variant), JSON-able; else None.
    """

    kind: str
    message: str
    time_s: float
    status: DrumStatus | None = None
    progress: ProgressEvent | None = None
    trial: TrialEvent | None = None
    latch: Latch | Acknowledgement | None = None
    fields: dict[str, Any] | None = None


def commanded(status: DrumStatus) -> bool:
    """True when ``status`` says the rig moves under a command: the force loop presses the sensor or the drum runs
    (state SEEKING_FORCE, FORCE_SETTLED or RUNNING, or a speed target above 0). A drum coasting to rest after a STOP
    and an actuator backing off are not."""
    return DrumState(int(status.state)) in _MOVING_STATES or status.speed_target_mm_s > 0


class StatusHistory:
    """The last ``capacity`` status reads as rows of ``n_fields`` float64 columns in a fixed-size ring (thread-safe, no
    growth). The monitor's columns: time (s since the monitor started), force (g), active force setpoint (g), speed
    (mm/s), speed target (mm/s)."""

    def __init__(self, capacity: int, n_fields: int = 5) -> None:
        self._buf = np.full((capacity, n_fields), np.nan)
        self._n = 0
        self._lock = threading.Lock()

    def append(self, row: tuple[float, ...]) -> None:
        with self._lock:
            self._buf[self._n % len(self._buf)] = row
            self._n += 1

    def snapshot(self) -> np.ndarray:
        """Rows in time order, oldest first: ``(n, n_fields)`` float64 (a copy)."""
        with self._lock:
            cap = len(self._buf)
            if self._n <= cap:
                return self._buf[: self._n].copy()
            i = self._n % cap
            return np.concatenate([self._buf[i:], self._buf[:i]])

    def clear(self) -> None:
        with self._lock:
            self._n = 0


class Heartbeat:
    """A face's proof of life (:meth:`RigMonitor.heartbeat`): :meth:`beat` it from the thread that must stay alive,
    :meth:`close` it when the face goes away. ``name`` says whose it is in the ``deadman`` event."""

    def __init__(self, monitor: "RigMonitor", name: str, timeout_s: float) -> None:
        self.monitor, self.name, self.timeout_s = monitor, name, float(timeout_s)
        self.last_s = time.monotonic()

    def beat(self) -> None:
        """I am alive (cheap: one clock read)."""
        self.last_s = time.monotonic()

    def close(self) -> None:
        """Stop watching this face (it went away in order)."""
        self.monitor._forget(self)


class RigMonitor:
    """Polls ``drum.read_status()`` every ``period_s`` in a thread (which also feeds the controller's watchdog), keeps
    :attr:`history` (``history_s`` of reads), and publishes :class:`RigEvent` s; runs the dead man's switch (module
    docstring), calling ``stop(reason)`` (the owner's STOP; never raising) when a heartbeat goes silent while the rig
    moves. ``drum`` None: a rig without a drum (the handheld rig): nothing is polled, nothing moves by itself; the
    stream carries what other parts publish.

    Attributes
    ----------
    latest : the newest :class:`DrumStatus` (None before the first read).
    ok : the last read succeeded; ``error`` why it did not.
    reads, failures : counts of status reads.
    history : :class:`StatusHistory`.
    deadman : the reason of the last dead-man stop (None: never tripped).
    """

    def __init__(self, drum: DrumMonitor | None, stop: Callable[[str], object], *, period_s: float = 0.1,
                 history_s: float = 60.0) -> None:
        self._drum, self._stop, self.period_s = drum, stop, float(period_s)
        self.history = StatusHistory(int(history_s / period_s) + 1)
        self.latest: DrumStatus | None = None
        self.ok = False
        self.error: str | None = None
        self.reads = 0
        self.failures = 0
        self.deadman: str | None = None
        self._subscribers: list[Callable[[RigEvent], object]] = []
        self._heartbeats: list[Heartbeat] = []
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self._latest_s = float("nan")  # when :attr:`latest` was read (monotonic s)
        self._tripped: set[str] = set()  # heartbeats silent right now (tripped once, until they beat again)
        self._stopped_s = -1e9  # when the dead man's switch last sent STOP (monotonic s)
        self._starve = False  # a STOP was not acknowledged: no read feeds the watchdog while the face is silent

    # ------------------------------------------------------------------------------------------------- life
    def start(self) -> "RigMonitor":
        """Start the monitor's thread (once; later calls do nothing). Returns self."""
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="rig-monitor", daemon=True)
                self._thread.start()
        return self

    def age_s(self) -> float:
        """How long ago :attr:`latest` was read, s (NaN before the first read)."""
        return time.monotonic() - self._latest_s

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the thread and wait for it (``timeout_s``)."""
        self._halt.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)

    # ------------------------------------------------------------------------------------------------- faces
    def subscribe(self, fn: Callable[[RigEvent], object]) -> Callable[[], None]:
        """Call ``fn(event)`` for every :class:`RigEvent` (in the monitor's thread, or the publisher's: keep it short,
        hand it on). Returns the function that unsubscribes."""
        with self._lock:
            self._subscribers.append(fn)

        def unsubscribe() -> None:
            with self._lock:
                if fn in self._subscribers:
                    self._subscribers.remove(fn)

        return unsubscribe

    def publish(self, event: RigEvent) -> None:
        """Hand ``event`` to every subscriber (a subscriber's error is logged, never raised)."""
        with self._lock:
            subscribers = list(self._subscribers)
        for fn in subscribers:
            try:
                fn(event)
            except Exception:  # noqa: BLE001 - one face's bug never stops the monitor or the others
                log.exception("a rig event subscriber failed on %s", event.kind)

    def heartbeat(self, name: str, timeout_s: float = DEADMAN_TIMEOUT_S) -> Heartbeat:
        """Register a face's heartbeat (module docstring); beat it at least every ``timeout_s`` / 3."""
        hb = Heartbeat(self, name, timeout_s)
        with self._lock:
            self._heartbeats.append(hb)
        return hb

    def _forget(self, hb: Heartbeat) -> None:
        with self._lock:
            if hb in self._heartbeats:
                self._heartbeats.remove(hb)
            self._tripped.discard(hb.name)

    # ------------------------------------------------------------------------------------------------- the thread
    def _emit(self, kind: str, message: str, status: DrumStatus | None = None) -> None:
        self.publish(RigEvent(kind, message, time.monotonic(), status))

    def _silent(self, now: float, late_s: float) -> list[tuple[Heartbeat, float]]:
        """The heartbeats older than their timeout (ages less the monitor's own lateness ``late_s``), with ages."""
        with self._lock:
            beats = list(self._heartbeats)
        return [(hb, age) for hb in beats if (age := now - hb.last_s) - late_s > hb.timeout_s]

    def _run(self) -> None:
        due = time.monotonic()
        while not self._halt.is_set():
            now = time.monotonic()
            late_s = max(0.0, now - due)  # the process (this thread) was starved that long: no face is blamed for it
            silent = self._silent(now, late_s)
            if silent:
                self._dead_faces(silent, now)
            else:
                if self._tripped:
                    self._tripped.clear()
                    self._starve = False
                    self._emit("deadman", "the face answers again; the rig stays stopped until it is commanded")
                self._poll(now)
            due = max(due + self.period_s, time.monotonic())
            self._wait(max(0.0, due - time.monotonic()) if self.ok else _RETRY_S)
            due = min(due, time.monotonic())  # (a wait the rig's clock ended early: the next period from now)

    def _wait(self, wait_s: float) -> None:
        """Until the next poll: ``wait_s`` of wall time, and on a simulated rig's shared clock no longer than
        ``wait_s`` of the rig's time either (a world run faster than real time, up to 10x, is polled every period of its
        own time: the controller's 1 s watchdog fed well within it; a world slower than real time is polled every
        period of wall time, for the dead man's switch)."""
        pause_on(getattr(self._drum, "clock", None), self._halt, wait_s)

    def _dead_faces(self, silent: list[tuple[Heartbeat, float]], now: float) -> None:
        """A face is silent: see what the rig does (one read) and STOP it when it moves under a command (again every
        :data:`_RESTOP_S` while it keeps moving). When a STOP did not get through, nothing feeds the controller's
        watchdog until the face answers: the controller stops the rig itself."""
        if self._starve:
            return
        self._poll(now)
        st = self.latest
        if st is None or not commanded(st) or now - self._stopped_s < _RESTOP_S:
            return
        self._stopped_s = now
        hb, age = silent[0]
        what = "turned" if abs(st.speed_mm_s) > _MOVING_SPEED_MM_S else "pressed the sensor"
        reason = (f"the {hb.name} did not answer for {age:.2f} s while the rig {what}: the rig was stopped (dead "
                  f"man's switch, limit {hb.timeout_s:g} s)")
        self.deadman = reason
        self._tripped.add(hb.name)
        log.warning("%s", reason)  # the faces show the event; the log keeps it
        try:
            acknowledged = self._stop(reason)
        except Exception:  # noqa: BLE001 - the controller's watchdog is the backstop
            log.exception("the dead man's switch could not stop the rig")
            acknowledged = False
        if acknowledged is False:
            self._starve = True
            reason += "; the STOP was not acknowledged: the controller's watchdog stops the rig"
        self._emit("deadman", reason, st)

    def _poll(self, now: float) -> None:
        if self._drum is None:  # a rig without a drum (the handheld rig): nothing to read, nothing moves by itself
            return
        try:
            st = self._drum.read_status()
        except Exception as exc:  # noqa: BLE001 - any failure means the link is down; shown, then retried
            self._fail(exc)
            return
        self._record(st, now)

    def _fail(self, exc: Exception) -> None:
        self.failures += 1
        self.error = describe_error(exc)
        if self.ok or self.reads == 0 and self.failures == 1:
            self._emit("link", f"drum controller not answering: {self.error}")
        self.ok = False

    def _record(self, st: DrumStatus, now: float) -> None:
        prev, was_ok = self.latest, self.ok
        self.latest, self.ok, self.error, self._latest_s = st, True, None, now
        self.reads += 1
        self.history.append((now - self._t0, st.force_g, st.force_setpoint_active_g, st.speed_mm_s,
                             st.speed_target_mm_s))
        if not was_ok and self.reads > 1:
            self._emit("link", "drum controller answering again", st)
        if prev is None or int(prev.state) != int(st.state):
            self._emit("state", f"drum controller {DrumState(int(st.state)).name}", st)
        if prev is None and int(st.faults) or prev is not None and int(prev.faults) != int(st.faults):
            self._emit("faults", describe_faults(int(st.faults)) if int(st.faults) else "faults cleared", st)
        self._emit("status", "", st)
