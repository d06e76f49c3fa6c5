"""One clock for a simulated rig: the host and the simulated boards on the boards' simulated time
(docs/architecture.md, "Time on a simulated rig").

The simulated world (the model boards' physics thread, or the simavr harnesses) owns the time; the host reads it
(:meth:`SharedClock.now`) for its timeouts, waits and receive stamps, and *grants* the world how far it may run: the
world never runs past :attr:`SharedClock.horizon_s`. The host's grant is

- a bounded lead (:data:`LEAD_S`) past the world's time at the host's last sign of life: its last read or write
  (:meth:`SharedClock.touch`), and a heartbeat thread of the host's process (:data:`HEARTBEAT_S`), at the host's own
  priority: a host process that gets no CPU grants nothing, and the world pauses :data:`LEAD_S` after it;
- the waits of the host (:meth:`SharedClock.sleep`, :meth:`SharedClock.wait_for`): a waiting host looks at the
  world's time at each of its steps, and each look is a sign of life; but the world runs no further than
  :data:`LEAD_S` past the deadline of a wait that has not yet returned (a waiter whose time has come but who has not
  run yet holds the world, the way a wire would let a board run only so far ahead of a host that has yet to read).

A sign of life that is not a wait (a read, a write, the heartbeat) moves the grant on no faster than the wall clock
(:meth:`SharedClock.touch`): only a waiting host lets the world run ahead of real time. A host thread that
computes between two feeds of the controller's watchdog (a trial written, an analysis, a GIL it waits for) while
another thread of its process keeps reading (a taxel stream) or beating then sees at most its own wall time go by
in the world, as on a bench, not ten times that (an unpaced world run on the heartbeat's grants latched WATCHDOG in
``rigctl acquire quick_check`` beside four CPU hogs at its second trial).

A grant is never taken back (the world may have used it), so a wait grants nothing in advance: a host blocked for
the whole of a 2 s answer timeout is a host that keeps looking, and one starved meanwhile grants nothing.

So a starved host pauses the whole simulated world: nothing it does looks late to the boards (the firmware's
watchdog judges simulated time), and a timeout of the host judges simulated time too, so nothing the boards do looks
late to the host. The world may be paced to the wall clock besides (a person watching) or run as fast as the CPU
allows (tests, the fault campaign): that is the world's choice, not the clock's.

No dependency but the standard library (``rigctl.core``).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from rigctl.core.port_clock import HostSide, open_beside

__all__ = ["SharedClock", "LEAD_S", "HEARTBEAT_S", "KERNEL_HOP_MAX_S", "clock_of_port", "attach_port_clock", "release_port_clock",
           "is_port_clock", "note_found", "on_its_way_until", "port_keys", "on_a_kernel_hop", "host_stamp",
           "pause_on"]

#: how far the simulated world may run past the host's last sign of life or the deadline of a wait it has not yet
#: returned from, s. Short against every deadline of the host on a simulated rig (the shortest WATCHDOG_MS, 100 ms;
#: the answer timeouts, >= 0.5 s; a taxel read period, 25 ms, plus this), long against the heartbeat (so a host that
#: gets its CPU never holds a paced world back) and against a USB-serial link's own buffering latency (the 16 ms
#: latency timer of an FTDI bridge)
LEAD_S = 0.05
#: the longest the kernel is taken to hold a hop's bytes between a host and a simulated board (a pty hands them on
#: through a kernel worker), s of wall time: a board waits for a write the host stamped (:meth:`SharedClock.note_write`)
#: at most this long, and a stamp older than that is not a frame on its way (a host whose write failed, or that
#: dropped a reply unseen, and then went silent is silent to the watchdog): the virtual Mega
#: (rigctl.simulation.virtual_mega) and the simavr harnesses (rigctl.simulation.hil_clock). 30 s: on this 2-core
#: machine (Linux 6.18) a pty hop's tail is set by the scheduling group its processes share: with autogroups (on by
#: default) a session is one group, and the kernel worker that hands a pty's bytes on (outside every group) sat
#: runnable for seconds while one busy group's threads ran (traced: woken at once, run 2.3 s later). A plain 8-byte
#: hop beside two CPU hogs and 40 Python threads that sleep 1-5 ms at a time, all in one session, took up to
#: 7.4-26.6 s; each process in a session of its own, at most 3 ms (benchmarks/bench_pty_hop.py). The test suite
#: gives each of its workers a session of its own (tests/conftest.py); a person runs rigctl in a session shared
#: with whatever else they started there, and a bench's USB-serial driver hands its bytes on through the same kernel
#: worker. Inside the conformance tests, all in one session beside two hogs, a Modbus reply sat 29.5 s in the kernel
#: (the server had written it, its event loop idle, no byte at the bridge's end), and at 10 s the host's answer wait
#: gave up on it (DrumTimeout "3 timeouts, 1 stale responses", three of six loaded CI runs); at 2 s, requests and
#: answers held longer ran the host's answer timeouts out and a speed the host had sent reached the Uno's encoder
#: 4.4 s late
KERNEL_HOP_MAX_S = 30.0
#: the longest a host's wait for an answer goes on past its deadline while the answer is known to be on its way,
#: s of wall time (:meth:`SharedClock.wait_for`'s ``in_flight``): the kernel's longest hop
IN_FLIGHT_MAX_S = KERNEL_HOP_MAX_S
#: how often a wait whose world stands for an answer on its way (:attr:`SharedClock.stands_while_in_flight`)
#: looks for it, s of wall time
FLIGHT_LOOK_S = 0.002
#: period of the heartbeat of the host's process, s (wall clock)
HEARTBEAT_S = 0.005
#: the shortest wall-clock step of a host wait that looks at the world's time, s
WAIT_STEP_S = 0.0005
#: the longest wall-clock step of a host wait, s (each look grants the world LEAD_S more: an unpaced world is held
#: back by a waiting host only beyond LEAD_S / MAX_WAIT_STEP_S = 10x real time)
MAX_WAIT_STEP_S = 0.005


#: the ports of the simulated rigs of this process and their clocks (:meth:`SharedClock.own_port`)
_PORTS: dict[str, "SharedClock"] = {}
_PORTS_LOCK = threading.Lock()


#: each path :func:`port_keys` resolved -> (what the path's link pointed at then, None: not a link; its keys)
_KEYS: dict[str, tuple[str | None, frozenset[str]]] = {}


def _link_target(path: str) -> str | None:
    try:
        return os.readlink(path)
    except OSError:  # not a link (or gone)
        return None


def port_keys(path: str | os.PathLike[str]) -> frozenset[str]:
    """The names a port goes by: ``path`` as given and the device behind it (``os.path.realpath``). Looked at on every
    step of a simulated world (a board asks whether the host's bytes are on their way), so remembered per path and
    checked with one ``readlink``: a link moved to another device (a board unplugged and plugged back in on a new
    pty) is resolved again. Thread-safe (a lost race resolves twice)."""
    name = os.fspath(path)
    target = _link_target(name)
    known = _KEYS.get(name)
    if known is not None and known[0] == target:
        return known[1]
    keys = {name}
    try:
        keys.add(os.path.realpath(name))
    except OSError:
        pass
    frozen = frozenset(keys)
    _KEYS[name] = (target, frozen)
    return frozen


def clock_of_port(path: str | os.PathLike[str]) -> "SharedClock | None":
    """The shared clock of the simulated rig whose board answers on ``path``: of this process (its link or its
    device), or of another process through the clock file beside its link (:func:`attach_port_clock`:
    give it back with :func:`release_port_clock` when done), or None (a real port: the wall clock)."""
    with _PORTS_LOCK:
        for key in port_keys(path):
            clock = _PORTS.get(key)
            if clock is not None:
                return clock
    return attach_port_clock(path)


def _stamp(stamps: dict[str, float], path: str | os.PathLike[str]) -> None:
    """``stamps[path] = time.monotonic()`` (the path as the host opened it: a board looks it up by each of its own
    names, :func:`_stamp_at`)."""
    stamps[os.fspath(path)] = time.monotonic()


def _stamp_at(stamps: dict[str, float], path: str | os.PathLike[str]) -> float:
    """The latest of ``stamps`` under any of ``path``'s keys (:func:`port_keys`: its link and the device behind it),
    0.0 if none."""
    return max((stamps.get(key, 0.0) for key in port_keys(path)), default=0.0)


class SharedClock:
    """The clock the host and a simulated rig's boards share (module doc). Also a
    :class:`rigctl.core.drum.Clock` (``now``, ``sleep``).

    Parameters
    ----------
    world_now : callable
        The world's simulated time, s (monotonic; thread-safe to call).
    lead_s : float
        :data:`LEAD_S`.
    heartbeat_s : float or None
        Period of the host heartbeat, s (None: no heartbeat; only reads, writes and waits grant time).
    on_grant : callable or None
        Called with the new horizon (s) each time it moves on (the world's wake-up: a pipe write, a shared-memory
        store); from the host's threads.
    on_stamp : callable or None
        Called with ``(path, written, n_bytes)`` at each :meth:`note_write` (``written`` True, ``n_bytes`` the
        write's length) and :meth:`note_read` (False, 0): a rig of another process is told through its clock file
        (:meth:`rigctl.core.port_clock.HostSide.stamp`), the simavr harnesses through theirs
        (:meth:`rigctl.simulation.hil_clock.HilClockFile.stamp`: they count the bytes).
    world_notifies : bool
        The world calls :meth:`moved` after each step it takes (a waiting host then wakes on it); else the host's
        waits poll the world's time every :data:`WAIT_STEP_S`.

    Attributes
    ----------
    horizon_s : float
        How far the world may run, s (never moves back).
    """

    def __init__(self, world_now: Callable[[], float], *, lead_s: float = LEAD_S,
                 heartbeat_s: float | None = HEARTBEAT_S, on_grant: Callable[[float], None] | None = None,
                 world_notifies: bool = False, on_stamp: Callable[[str, bool, int], None] | None = None) -> None:
        self._world_now = world_now
        self.lead_s = float(lead_s)
        self.heartbeat_s = heartbeat_s
        self.on_grant = on_grant
        self.on_stamp = on_stamp
        self._lock = threading.Lock()
        self.world_notifies = world_notifies
        self._moved = threading.Condition(threading.Lock())
        self._alive_s = -math.inf  # the world's time at the host's last sign of life
        self._alive_wall = time.monotonic()  # when a sign of life that is not a wait last moved it on (wall clock)
        self._waits: dict[int, float] = {}  # deadlines of the host's waits not yet returned, s
        self._looking = 0  # how many of them look at something besides the time (a ``ready``) after each step
        self._next_wait = 0
        self.horizon_s = self.lead_s
        self._stop = threading.Event()
        self._heart: threading.Thread | None = None
        #: ``in_flight(path)``: whether a request the host wrote to the board's port ``path`` or its answer is on
        #: its way (set by the simulated rig whose board answers there: rigctl.simulation.virtual_mega); None: never
        #: known (:meth:`wait_for`'s ``in_flight``)
        self.in_flight: Callable[[str], bool] | None = None
        #: whether the world stands while an answer a wait has passed its deadline for is on its way (``in_flight``),
        #: rather than running on: True where the boards cannot judge bytes on their way (firmware under simavr, whose
        #: watchdog counts its own time: a reply the kernel held for seconds while the world ran on latched WATCHDOG
        #: in a host that polled all along, rigctl.simulation.hil_clock); False where they can (the virtual Mega's
        #: watchdog: a world that stood would lag a live sample source for good)
        self.stands_while_in_flight = False
        self._written: dict[str, float] = {}  # a port's path -> when the host last began to write to it (wall)
        self._written_before: dict[str, tuple[float, float]] = {}  # and (the stamp it replaced, its own): write_failed
        self._read: dict[str, float] = {}  # a port's path -> when the host last found bytes to read on it (wall)

    # ------------------------------------------------------------------ lifecycle (the heartbeat)
    def start(self) -> "SharedClock":
        """Start the heartbeat (idempotent); the host's process is alive from now, and ``on_grant`` is told the
        horizon (the first :attr:`horizon_s` is :attr:`lead_s` before any grant moved it: a world at time 0 was never
        told it, and waited on a host that waited on it)."""
        self.touch()
        if self.on_grant is not None:
            self.on_grant(self.horizon_s)
        if self.heartbeat_s and self._heart is None:
            self._stop.clear()
            self._heart = threading.Thread(target=self._beat, name="shared-clock-heartbeat", daemon=True)
            self._heart.start()
        return self

    def close(self) -> None:
        """Stop the heartbeat (the world then runs only on reads, writes and waits)."""
        self._stop.set()
        if self._heart is not None:
            self._heart.join(timeout=2)
            self._heart = None

    def _beat(self) -> None:
        period, stop = float(self.heartbeat_s or HEARTBEAT_S), self._stop
        while not stop.wait(period):
            self.touch()

    # ------------------------------------------------------------------ the rig's ports
    def own_port(self, path: str | os.PathLike[str]) -> None:
        """``path`` (a board's port of the rig) is on this clock: a drum client or taxel stream of this process that
        opens it without a clock of its own times itself on this one (:func:`clock_of_port`)."""
        with _PORTS_LOCK:
            for key in port_keys(path):
                _PORTS[key] = self

    def release_ports(self) -> None:
        """Forget every port :meth:`own_port` gave this clock (the rig closed: the pty numbers get reused)."""
        with _PORTS_LOCK:
            for key in [k for k, c in _PORTS.items() if c is self]:
                del _PORTS[key]

    # ------------------------------------------------------------------ the host's side
    def now(self) -> float:
        """The world's simulated time, s."""
        return float(self._world_now())

    def touch(self) -> None:
        """The host is alive now (a read, a write, the heartbeat): the world may run :attr:`lead_s` past its time
        now, but the host's last sign of life moves on no faster than the wall clock (module doc)."""
        self._alive(self.now(), waiting=False)

    def _alive(self, t: float, *, waiting: bool = True) -> None:
        with self._lock:
            if not waiting:
                wall = time.monotonic()
                if self._alive_s > -math.inf:
                    t = min(t, self._alive_s + max(0.0, wall - self._alive_wall))
                self._alive_wall = wall
            if t > self._alive_s:
                self._alive_s = t
            self._regrant()

    def sleep(self, s: float) -> None:
        """Wait ``s`` s of simulated time (the world runs on meanwhile)."""
        self.wait_for(None, s)

    def wait_for(self, ready: Callable[[], bool] | None, timeout_s: float,
                 max_step_s: float = MAX_WAIT_STEP_S, min_wall_s: float = 0.0,
                 in_flight: Callable[[], bool] | None = None) -> bool:
        """Wait until ``ready()`` or until ``timeout_s`` of simulated time have passed; the world may run on
        meanwhile. ``ready()`` and the clock are looked at after each step of the world (``world_notifies``) and at
        least every ``max_step_s`` of wall time (at most every :data:`WAIT_STEP_S`, and no later than the time left
        on the deadline, of which a paced world spends no less wall time). Returns whether ``ready()`` came true
        (``ready`` None: waits the whole time, returns False). ``min_wall_s``: a wait for something another thread
        of this process brings (an answer a simulated board's server thread writes) ends unready no earlier than
        that much wall time either: meanwhile the world stands at the deadline (plus :attr:`lead_s`), and a
        starved thread of the board gets the CPU to answer instead of the world running past its answer.
        ``in_flight``: a wait for an answer that ends unready no earlier than ``in_flight()`` is False (what the host
        waits for is known to be on its way: rigctl.simulation.virtual_mega), and at most :data:`IN_FLIGHT_MAX_S` of
        wall time past the deadline; meanwhile the world runs on (a deadline moved on as the world moves: the
        watchdog judges a request or answer on its way as a host that spoke, and a live sample source beside a world
        that stood would lag it for good), or, where :attr:`stands_while_in_flight`, stands at the deadline (plus
        :attr:`lead_s`)."""
        wall_end = time.monotonic() + max(0.0, float(min_wall_s))
        flight_end: float | None = None
        t = self.now()
        deadline = t + max(0.0, float(timeout_s))
        with self._lock:
            key = self._next_wait
            self._next_wait += 1
            self._waits[key] = deadline
            if ready is not None:
                self._looking += 1
        try:
            while True:
                self._alive(t)
                if ready is not None and ready():
                    return True
                t = self.now()
                left = deadline - t
                if left <= 0.0:
                    going_on = _flight_goes_on(in_flight, flight_end)
                    if going_on is not None:  # the answer is on its way
                        flight_end = going_on
                        if self.stands_while_in_flight:  # the world stands at the deadline meanwhile
                            left = FLIGHT_LOOK_S
                        else:  # the world runs on meanwhile
                            deadline = t + MAX_WAIT_STEP_S
                            with self._lock:
                                self._waits[key] = deadline
                            left = MAX_WAIT_STEP_S
                    elif ready is None or time.monotonic() >= wall_end:
                        return ready() if ready is not None else False
                    else:
                        left = WAIT_STEP_S
                step = min(max_step_s, max(WAIT_STEP_S, left))
                if self.world_notifies:  # woken by the world's next step
                    with self._moved:
                        self._moved.wait(step)
                else:
                    time.sleep(step)
        finally:
            with self._lock:
                del self._waits[key]
                if ready is not None:
                    self._looking -= 1
            self._alive(self.now())

    def note_write(self, path: str | os.PathLike[str], n_bytes: int) -> None:
        """The host is about to write ``n_bytes`` bytes to the board's port ``path`` (call it before the write): a
        board of this process then knows its bytes are on the way while the kernel still holds them, where no count
        sees them (:meth:`written_at`; a pty hands a writer's bytes on through a kernel worker, which a loaded machine
        holds back for hundreds of ms), and a simavr harness waits until it has read that many more bytes
        (``on_stamp``). Also a sign of life (:meth:`touch`)."""
        name = os.fspath(path)
        before = self._written.get(name, 0.0)
        _stamp(self._written, path)
        self._written_before[name] = (before, self._written[name])
        if self.on_stamp is not None:
            self.on_stamp(name, True, int(n_bytes))
        self.touch()

    def write_failed(self, path: str | os.PathLike[str], n_bytes: int) -> None:
        """The write of ``n_bytes`` bytes to ``path`` that :meth:`note_write` last stamped raised (a port gone, an I/O
        error): none of its bytes is on its way. Its stamp is taken back, the one before it stands
        (:meth:`written_at`), and ``on_stamp`` is told with ``-n_bytes`` (a simavr harness then waits for none of
        them): a board would otherwise take the host for one that spoke, and wait for its bytes, for up to
        :data:`KERNEL_HOP_MAX_S` of wall time (a watchdog that latches that much later than on a bench). A stamp a
        later :meth:`note_write` made meanwhile stays. :meth:`writing` calls it."""
        name = os.fspath(path)
        stamps = self._written_before.pop(name, None)
        if stamps is None:
            return
        if self._written.get(name) == stamps[1]:
            self._written[name] = stamps[0]
        if self.on_stamp is not None:
            self.on_stamp(name, True, -int(n_bytes))

    @contextlib.contextmanager
    def writing(self, path: str | os.PathLike[str], n_bytes: int) -> Iterator[None]:
        """A host's write of ``n_bytes`` bytes to the board's port ``path`` inside the ``with``:
        :meth:`note_write` before it, :meth:`write_failed` if it raises (the exception goes on)."""
        self.note_write(path, n_bytes)
        try:
            yield
        except BaseException:
            self.write_failed(path, n_bytes)
            raise

    def written_at(self, path: str | os.PathLike[str]) -> float:
        """When the host last began to write to ``path`` (:meth:`note_write`; ``time.monotonic``, 0.0 if never).
        Lock-free."""
        return _stamp_at(self._written, path)

    def note_read(self, path: str | os.PathLike[str]) -> None:
        """The host found bytes waiting on the board's port ``path`` and is about to read them, or opened the port
        (:meth:`read_at`: a board of this process knows what it handed on after this, none of it waiting on the host's
        side, is still in the kernel's hands: ``VirtualMega.reply_on_its_way``, ``VirtualUno.output_on_its_way``)."""
        _stamp(self._read, path)
        if self.on_stamp is not None:
            self.on_stamp(os.fspath(path), False, 0)

    def read_at(self, path: str | os.PathLike[str]) -> float:
        """When the host last found bytes to read on ``path`` (:meth:`note_read`; ``time.monotonic``, 0.0 if never:
        no host of this process reads it). Lock-free."""
        return _stamp_at(self._read, path)

    # ------------------------------------------------------------------ the world's side
    def moved(self) -> None:
        """The world took a step (``world_notifies``): the host's waits look at its time again - at once where one
        looks for something besides the time (a ``ready``), else once the world has reached the earliest deadline
        or come within a fifth of the lead of the horizon (the sleeping host then grants it more). A sleep
        is not woken at each of the world's steps: an unpaced world steps thousands of times a second, and threads
        that wake that often hold back the kernel's pty hops by seconds (``KERNEL_HOP_MAX_S``)."""
        waits = self._waits
        if not waits:
            return
        if not self._looking:
            try:
                now = self.now()
                if now < min(waits.values()) and now + 0.2 * self.lead_s < self.horizon_s:
                    return
            except (ValueError, RuntimeError):  # a wait returned or began meanwhile: look again at once
                pass
        with self._moved:
            self._moved.notify_all()

    def _regrant(self) -> None:
        """The horizon from the host's signs of life and waits (under the lock); the world told if it moved."""
        grant = self._alive_s + self.lead_s
        if self._waits:
            grant = min(grant, min(self._waits.values()) + self.lead_s)
        if grant > self.horizon_s:
            self.horizon_s = grant
            if self.on_grant is not None:
                self.on_grant(grant)


def on_its_way_until(clock: object, port: str | os.PathLike[str], flight_end: float | None) -> float | None:
    """For a wait on ``clock`` that has passed its deadline for bytes a simulated board sends to ``port`` (a banner, a
    reply): the wall time (``time.monotonic``) until which it goes on, because the board says they are on their way
    (``clock.in_flight(port)``: a pty's kernel hop, which a loaded machine holds for seconds), at most
    :data:`IN_FLIGHT_MAX_S` after it first said so (``flight_end``: the last call's answer, None at first); None:
    give up (nothing on its way, the bound passed, or a clock that cannot tell: the wall clock of a real port)."""
    in_flight = getattr(clock, "in_flight", None)
    return _flight_goes_on(None if in_flight is None else (lambda: bool(in_flight(os.fspath(port)))), flight_end)


def _flight_goes_on(in_flight: Callable[[], bool] | None, flight_end: float | None) -> float | None:
    """The one rule of a wait past its deadline for bytes on their way (:meth:`SharedClock.wait_for`'s
    ``in_flight``, :func:`on_its_way_until`): the wall time (``time.monotonic``) until which it goes on, at most
    :data:`IN_FLIGHT_MAX_S` after ``in_flight()`` first said so (``flight_end``: the last answer, None at first);
    None: give up (no ``in_flight``, the bound passed, or nothing on its way now)."""
    wall = time.monotonic()
    if in_flight is None or (flight_end is not None and wall >= flight_end) or not in_flight():
        return None
    return wall + IN_FLIGHT_MAX_S if flight_end is None else flight_end


def on_a_kernel_hop(written_at: float, found_at: float) -> bool:
    """Whether bytes written to a pty at ``written_at`` are still in the kernel's hands: written after their reader
    last took or found bytes there (``found_at``), and less than :data:`KERNEL_HOP_MAX_S` ago (a stamp older than
    that is a write that brought nothing). Both ``time.monotonic`` s, 0.0: never. The one rule of the simulated
    boards' "on its way" (rigctl.simulation.virtual_mega, virtual_uno, hil_clock)."""
    return written_at > max(found_at, time.monotonic() - KERNEL_HOP_MAX_S)


def host_stamp(clock: "SharedClock | None", path: str, remote: Callable[[bool], float] | None, written: bool) -> float:
    """When a host last began to write to the board's port ``path`` (``written``) or last found bytes there
    (``time.monotonic`` s, 0.0: never): a host of this process (its ``clock``'s :meth:`SharedClock.written_at` /
    :meth:`SharedClock.read_at`) or of another (``remote(written)``: the rig's clock file,
    :meth:`rigctl.core.port_clock.ClockFile.stamp_s`), the later."""
    own = 0.0 if clock is None else (clock.written_at(path) if written else clock.read_at(path))
    return own if remote is None else max(own, remote(written))


def note_found(clock: object, port: str | os.PathLike[str]) -> None:
    """A host found bytes on the board's port ``port``, or opened it (a board's output from then on is new to it):
    stamped on ``clock`` where it is a :class:`SharedClock` (:meth:`SharedClock.note_read`), else nothing."""
    note = getattr(clock, "note_read", None)
    if note is not None:
        note(port)


# ---------------------------------------------------------------------- a simulated rig of another process
@dataclass
class _Attached:
    clock: SharedClock
    side: HostSide
    users: int


_ATTACHED: dict[str, _Attached] = {}  # clock file (real path) -> its clock, its file, the users now
_ATTACHED_LOCK = threading.Lock()


def attach_port_clock(port: str | os.PathLike[str]) -> SharedClock | None:
    """The :class:`SharedClock` of the simulated rig of another process whose port link is ``port``, through the
    clock file beside it (:mod:`rigctl.core.port_clock`), held until every user has called
    :func:`release_port_clock` (one per rig and process: the drum port and the taxel port share it; a clock given
    out once keeps reading the rig's time after its release); None for anything else (a real port: the wall clock)."""
    side = open_beside(port)
    if side is None:
        return None
    key = os.path.realpath(side.path)
    with _ATTACHED_LOCK:
        entry = _ATTACHED.get(key)
        if entry is not None:
            side.close()
            if entry.users == 0:
                entry.side.hold(True)
                entry.clock.start()
            entry.users += 1
            return entry.clock
        side.hold(True)
        clock = SharedClock(side.world_now, on_grant=side.grant, on_stamp=side.stamp)
        clock.in_flight = side.in_flight  # an answer the rig says is on its way is waited for (rigctl.core.port_clock)
        clock.start()
        _ATTACHED[key] = _Attached(clock, side, 1)
        return clock


def release_port_clock(clock: object) -> None:
    """A user of a clock :func:`attach_port_clock` gave is done with it; the last one lets the rig go (the heartbeat
    stops, the shared lock goes: the rig runs on by itself). Anything else: nothing."""
    with _ATTACHED_LOCK:
        for entry in _ATTACHED.values():
            if entry.clock is clock and entry.users > 0:
                entry.users -= 1
                if entry.users == 0:
                    entry.clock.close()
                    entry.side.hold(False)
                return


def is_port_clock(clock: object) -> bool:
    """Whether ``clock`` is one :func:`attach_port_clock` gave (a rig of another process), held or not."""
    with _ATTACHED_LOCK:
        return any(entry.clock is clock for entry in _ATTACHED.values())


def pause_on(clock: object, stop: threading.Event, s: float, *, wall_factor: float = 1.0) -> bool:
    """Wait ``s`` s on ``clock`` (a :class:`SharedClock`: of the simulated rig's time, and no longer than
    ``wall_factor * s`` of wall time either; anything else: of wall time) or until ``stop`` is set; returns whether
    it is. A backoff or a poll of a thread of the host on the rig's own time: beside an unpaced world a taxel
    stream's reopen backoff on the wall let a host's 20 s wait for the link, on the rig's time, end before the
    replugged port was tried again."""
    if not isinstance(clock, SharedClock):
        return stop.wait(s)
    wall_end = time.monotonic() + wall_factor * s
    clock.wait_for(lambda: stop.is_set() or time.monotonic() >= wall_end, s)
    return stop.is_set()
