"""One clock for a simulated rig and a host in another process: the clock file beside the rig's port links
(docs/architecture.md, "Time on a simulated rig").

A simulated rig (``rigctl sim``, or a test's :class:`rigctl.simulation.rig.SimulatedRig`) publishes its simulated
time in ``DIR/.clock`` beside its port links ``DIR/drum`` and ``DIR/taxel``. A face in another process that opens
those links as hardware (``--drum-port DIR/drum``) attaches to the file
(:func:`rigctl.core.shared_clock.attach_port_clock`, on :func:`open_beside`): its drum client and taxel
stream then time their waits and timeouts on the rig's time, and grant the rig how far it may run, exactly as a host
in the rig's own process does (:class:`rigctl.core.shared_clock.SharedClock`). A starved face then pauses the
simulated world instead of looking silent to the controller's 1 s watchdog.

A face holds a shared ``flock`` on the file while its process lives; the rig sees that (:meth:`ClockFile.host_attached`)
and obeys the face's grants only then. A face that exits or is killed releases the lock with its process, and the
rig runs on by itself, paced to the wall clock: its controller's watchdog then acts on the silence, as on a bench.

A face also stamps, for each port link of the rig, when it last began to write to it and when it last found bytes
there to read (:meth:`HostSide.stamp`, ``time.monotonic``, one clock for every process of the machine): bytes a pty
holds in the kernel's hands on their way are seen by no byte count, and the rig's controller judges its watchdog by
these stamps as by those of a host of its own process (:meth:`ClockFile.stamp_s`; docs/architecture.md, "Bytes on
their way").

The rig in turn says whether a request a face wrote to the drum link or its answer, or the taxel board's banner or
reply, is on its way (in the kernel's or the board's hands: :meth:`ClockFile.publish_in_flight`,
:meth:`HostSide.in_flight`), and the face's waits do not give up on an answer the rig knows is coming, as a host's
of the rig's own process do (:meth:`rigctl.core.shared_clock.SharedClock.wait_for`'s ``in_flight``).

The file: eight little-endian uint64 slots, a magic number, the rig's time (ns + 1; 0: not yet), the hosts' grant
(ns + 1; never moves back), the rig's last look at the bytes on their way (``(monotonic ns << 2 | taxel << 1 |
drum) + 1``; 0: never), then the faces' stamps (monotonic ns + 1; 0: never) of the drum link, written and read, and
of the taxel link, written and read. Standard library only (``rigctl.core``).
"""

from __future__ import annotations

import fcntl
import mmap
import os
import struct
import threading
import time
from pathlib import Path

__all__ = ["CLOCK_NAME", "ClockFile", "HostSide", "open_beside"]

#: the clock file's name in a simulated rig's port folder
CLOCK_NAME = ".clock"
_MAGIC = 0x52494743544C434B  # "RIGCTLCK"
_SIZE = 64
#: the slots of the faces' stamps by port link name: (written, read) byte offsets
_STAMP_SLOTS = {"drum": (32, 40), "taxel": (48, 56)}
#: how often the rig looks whether a face holds the file, s (a flock attempt; between looks the last answer holds)
ATTACH_LOOK_S = 0.02
#: the slot of the rig's last look at the bytes on their way (:meth:`ClockFile.publish_in_flight`), and its flag bits
_IN_FLIGHT_SLOT = 24
_IN_FLIGHT_BITS = {"drum": 1, "taxel": 2}
#: a look of the rig at the drum link's answer older than this is no answer, s of wall time: the face takes the answer
#: as on its way (the rig's world loop looks at each step and at least every 5 ms while held; a rig thread the machine
#: starves longer than this says nothing, and the face's wait goes on, for at most ``IN_FLIGHT_MAX_S``)
IN_FLIGHT_LOOK_MAX_S = 0.05


def _map(fd: int) -> mmap.mmap:
    return mmap.mmap(fd, _SIZE)


def _slot_s(m: mmap.mmap, offset: int) -> float:
    """The time in the slot at ``offset`` of the mapped file ``m``, s (stored as ns + 1; 0.0 when the slot is 0)."""
    (v,) = struct.unpack_from("<Q", m, offset)
    return (v - 1) * 1e-9 if v else 0.0


class ClockFile:
    """The rig's side: ``DIR/.clock`` created (a leftover one of rigctl's is reused; any other file of that name is
    refused: FileExistsError), mapped, holding ``time 0`` and no grant. :meth:`close` removes it."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.path = Path(folder) / CLOCK_NAME
        if os.path.lexists(self.path) and not _is_clock_file(self.path):
            raise FileExistsError(f"{self.path} is not a rigctl clock file: rigctl never replaces it; choose another "
                                  "--port-dir")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.ftruncate(fd, _SIZE)
            self._map: mmap.mmap | None = _map(fd)
        except BaseException:
            os.close(fd)
            raise
        self._fd: int | None = fd
        struct.pack_into("<Q", self._map, 0, _MAGIC)
        self._attached = False
        self._looked = -1.0

    def publish(self, world_s: float) -> None:
        """The rig's time is now ``world_s`` (s)."""
        if self._map is not None:
            struct.pack_into("<Q", self._map, 8, int(world_s * 1e9) + 1)

    def grant_s(self) -> float:
        """How far the faces have let the rig run, s (0 before any grant)."""
        if self._map is None:
            return 0.0
        return _slot_s(self._map, 16)

    def publish_in_flight(self, drum: bool, taxel: bool) -> None:
        """Whether a request a face wrote to the drum link or its answer (``drum``), and the taxel board's banner or
        reply (``taxel``), are on their way now (the rig's look, stamped ``time.monotonic``; :meth:`HostSide.in_flight`)."""
        if self._map is not None:
            flags = _IN_FLIGHT_BITS["drum"] * bool(drum) | _IN_FLIGHT_BITS["taxel"] * bool(taxel)
            struct.pack_into("<Q", self._map, _IN_FLIGHT_SLOT, (time.monotonic_ns() << 2 | flags) + 1)

    def stamp_s(self, link: str, written: bool) -> float:
        """When a face of another process last began to write to the port link ``link`` (``written``) or last found
        bytes there to read (``time.monotonic``, s; 0.0: never, or a link without stamps). Lock-free."""
        slots = _STAMP_SLOTS.get(link)
        if self._map is None or slots is None:
            return 0.0
        return _slot_s(self._map, slots[0] if written else slots[1])

    def host_attached(self) -> bool:
        """Whether a face of another process holds the file now (looked at most every :data:`ATTACH_LOOK_S`)."""
        now = time.monotonic()
        if self._fd is None:
            return False
        if now - self._looked >= ATTACH_LOOK_S:
            self._looked = now
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                self._attached = True
            else:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                self._attached = False
        return self._attached

    def hosts_stopped(self) -> bool:
        """Whether every face that holds the file now is a stopped process (SIGSTOP, a debugger's stop: state T or t
        in ``/proc/PID/stat``; the holders from ``/proc/locks``). A stopped face grants nothing and never will until
        it is continued: the rig must not wait for it (issue 76: a SIGSTOPped ``acquire`` froze ``rigctl sim``'s
        world for 106 s, so its controller's watchdog could never act). False when no holder is found or ``/proc``
        cannot say (a starved face is running, not stopped)."""
        if self._fd is None:
            return False
        st = os.fstat(self._fd)
        dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        try:
            with open("/proc/locks", encoding="ascii", errors="replace") as f:
                pids = {int(parts[4]) for line in f if len(parts := line.split()) > 5 and parts[5] == dev
                        and parts[1] == "FLOCK" and parts[4].isdigit()}
        except OSError:
            return False
        pids.discard(os.getpid())
        if not pids:
            return False
        for pid in pids:
            try:
                with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
                    state = f.read().rsplit(")", 1)[1].split()[0]
            except (OSError, IndexError):
                return False
            if state not in ("T", "t"):
                return False
        return True

    def close(self) -> None:
        """Unmap and remove the file (idempotent)."""
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            try:
                self.path.unlink()
            except FileNotFoundError:
                pass


def _is_clock_file(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    return len(head) == 8 and struct.unpack("<Q", head)[0] == _MAGIC


class HostSide:
    """A face's view of the clock file at ``path`` (opened on ``fd``, which it owns): the rig's time, the face's
    grants, the shared lock that says a face is there (:meth:`hold`). Raises OSError/ValueError if it cannot map it."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd = fd
        self._map = _map(fd)
        self._last_s = 0.0
        self._lock = threading.Lock()
        self._stamped_before: dict[int, tuple[int, int]] = {}  # a write stamp's slot -> (its value before, ours)

    def world_now(self) -> float:
        t = _slot_s(self._map, 8)
        if t > self._last_s:
            self._last_s = t
        return self._last_s

    def grant(self, horizon_s: float) -> None:
        ns = int(horizon_s * 1e9) + 1
        with self._lock:
            (old,) = struct.unpack_from("<Q", self._map, 16)
            if ns > old:
                struct.pack_into("<Q", self._map, 16, ns)

    def stamp(self, port: str, written: bool, n_bytes: int) -> None:
        """This face is about to write (``written``, ``n_bytes`` of them: the model rig's boards count their own) or
        has found bytes to read on the port ``port`` (a path whose name is a link of the rig: ``DIR/drum``): stamped
        now (``time.monotonic``) for the rig's side (:meth:`ClockFile.stamp_s`); a port of another name: nothing.
        ``written`` with ``n_bytes`` negative: the last stamped write failed (``SharedClock.write_failed``), and the
        stamp before it stands again (a later write's stamp made meanwhile stays)."""
        slots = _STAMP_SLOTS.get(os.path.basename(port))
        if slots is None:
            return
        offset = slots[0] if written else slots[1]
        with self._lock:
            if written and n_bytes < 0:
                stamps = self._stamped_before.pop(offset, None)
                if stamps is not None and struct.unpack_from("<Q", self._map, offset)[0] == stamps[1]:
                    struct.pack_into("<Q", self._map, offset, stamps[0])  # (a later write's stamp stays)
                return
            now_ns = time.monotonic_ns() + 1
            if written:
                self._stamped_before[offset] = (struct.unpack_from("<Q", self._map, offset)[0], now_ns)
            struct.pack_into("<Q", self._map, offset, now_ns)

    def in_flight(self, port: str) -> bool:
        """Whether a request this face wrote to the drum link ``port`` (a path named ``drum``) or its answer, or the
        taxel board's banner or reply (``taxel``), is on its way, by the rig's last look
        (:meth:`ClockFile.publish_in_flight`); a look older than :data:`IN_FLIGHT_LOOK_MAX_S`, the rig's thread
        starved: True (the rig cannot say; the face's wait goes on, bounded by the clock); never looked, or another
        port: False. The attached clock's ``in_flight``."""
        bit = _IN_FLIGHT_BITS.get(os.path.basename(port))
        (v,) = struct.unpack_from("<Q", self._map, _IN_FLIGHT_SLOT)
        if bit is None or not v:
            return False
        v -= 1
        if time.monotonic_ns() - (v >> 2) > IN_FLIGHT_LOOK_MAX_S * 1e9:
            return True
        return bool(v & bit)

    def hold(self, on: bool) -> None:
        """Take (``on``) or give back the shared lock that tells the rig a face of this process is there."""
        fcntl.flock(self._fd, fcntl.LOCK_SH if on else fcntl.LOCK_UN)

    def close(self) -> None:
        """Unmap and close (the lock, if held, goes with it)."""
        self._map.close()
        os.close(self._fd)


def open_beside(port: str | os.PathLike[str]) -> HostSide | None:
    """The clock file beside the port link ``port`` (a simulated rig of any process), opened for a face, not yet
    held; None when ``port`` is no link or has no rigctl clock file beside it (a real serial port)."""
    link = Path(os.fspath(port))
    if not link.is_symlink():
        return None
    path = link.absolute().parent / CLOCK_NAME
    if not _is_clock_file(path):
        return None
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return None
    try:
        return HostSide(path, fd)
    except (OSError, ValueError):
        os.close(fd)
        return None
