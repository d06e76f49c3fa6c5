"""The host's side of the simavr harnesses' clock-lock file (``arduino/simavr/rigctl_simavr.c``, "clock lock"): the
boards' simulated times (slot 0 the Mega's, slot 1 the Uno's) and the host's grant (slot 2), each ns + 1 (0: not
yet), when the host began its last write to each board's port (slots 3 and 4: ``CLOCK_MONOTONIC`` ns + 1), the
bytes each harness has read from its port (slots 5 and 6, the harnesses') and the bytes the host's stamped writes to
each port bring (slots 7 and 8, the host's), and when each harness last handed bytes to its port (slots 9 and 10,
``CLOCK_MONOTONIC`` ns + 1: :meth:`HilClockFile.in_flight`), shared memory between the harness processes and the host
(docs/architecture.md "Time on a simulated rig").

:class:`HilClockFile` gives a :class:`rigctl.core.shared_clock.SharedClock` the world's time (the slower board's:
the two run in lock step within 2 ms), publishes its grants and stamps and counts its writes; the harnesses run no
further than the grant, and a harness that has read fewer bytes than its host's stamped writes bring waits for the
rest (at most :data:`rigctl.core.shared_clock.KERNEL_HOP_MAX_S` of wall time after the last stamp): a pty hands a
writer's bytes on through a kernel worker, which a loaded machine holds back (two writes made one after the other
can arrive a second apart), and a request on its way is not a silent host. Counted, not timed: a harness that reads
an earlier write's bytes after a stamp has not read the stamped write's.
"""

from __future__ import annotations

import mmap
import os
import threading
import time
from pathlib import Path

import numpy as np

from rigctl.core.shared_clock import KERNEL_HOP_MAX_S, SharedClock, on_a_kernel_hop, port_keys

__all__ = ["HilClockFile", "LOCK_SLOTS"]

#: the file's slots: the Mega's time, the Uno's, the host's grant, the host's last write to the Mega's port, to the
#: Uno's, the bytes the Mega's harness has read from its port, the Uno's, the bytes the host's stamped writes bring to
#: the Mega's port, to the Uno's, when the Mega's harness last wrote to its port, the Uno's (uint64 each)
LOCK_SLOTS = 11
#: each board's index in the slots: its last write's slot is 3 + it, its harness's bytes read 5 + it, the host's
#: stamped bytes 7 + it, its harness's last write 9 + it
WRITE_SLOTS = {"mega": 0, "uno": 1}


class HilClockFile:
    """The clock-lock file at ``path`` (created, zeroed: no board has published, no grant yet), mapped."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.ftruncate(fd, LOCK_SLOTS * 8)
            self._map: mmap.mmap | None = mmap.mmap(fd, LOCK_SLOTS * 8)
        finally:
            os.close(fd)
        # aligned 8-byte loads and stores (one instruction each on the machines simavr runs on), as the harness's atomics
        self._slots: np.ndarray | None = np.frombuffer(self._map, dtype=np.uint64)
        self._last_s = 0.0
        self._write_slots: dict[str, int] = {}
        self._stamp_lock = threading.Lock()
        self._clock: SharedClock | None = None

    def shared_clock(self) -> SharedClock:
        """A :class:`SharedClock` on the boards' time whose grants go to the file (its first one written now) and
        whose hosts' writes to a board's port (:meth:`board_port`) are stamped in it (:meth:`stamp`)."""
        clock = self._clock = SharedClock(self.world_now, on_grant=self.grant, on_stamp=self.stamp)
        clock.in_flight = self.in_flight  # and its waits go on while a board's bytes are on their way,
        clock.stands_while_in_flight = True  # the world standing: the firmware's watchdog cannot judge them
        self.grant(clock.horizon_s)
        return clock

    def in_flight(self, path: str) -> bool:
        """Whether bytes the harness of the board whose port is ``path`` (:meth:`board_port`) handed to the pty are
        on their way to the host: written (slot 9 + the board, ``CLOCK_MONOTONIC``) after a host of this process
        last found bytes there or opened it (:meth:`SharedClock.read_at`), less than :data:`KERNEL_HOP_MAX_S` ago
        (a pty hands them on through a kernel worker, which a loaded machine holds for seconds); never found or
        opened, or another port: False. The clock's ``in_flight`` (a drum client's answer wait, the taxel stream's
        banner and identify waits)."""
        slots, clock = self._slots, self._clock
        board = next((self._write_slots[k] for k in port_keys(path) if k in self._write_slots), None)
        if slots is None or clock is None or board is None or not int(slots[9 + board]):
            return False
        read_at = clock.read_at(path)
        wrote_s = (int(slots[9 + board]) - 1) * 1e-9
        return read_at > 0.0 and on_a_kernel_hop(wrote_s, read_at)

    def world_now(self) -> float:
        """The simulated rig's time, s: the slower board's that has published (0 before either has); never moves
        back (a board that starts publishing later, behind the other, is caught up by the lock)."""
        slots = self._slots
        if slots is None:
            return self._last_s
        mega, uno = int(slots[0]), int(slots[1])
        started = [v for v in (mega, uno) if v]
        if started:
            t = (min(started) - 1) * 1e-9
            if t > self._last_s:
                self._last_s = t
        return self._last_s

    def grant(self, horizon_s: float) -> None:
        """Let the boards run to ``horizon_s`` of simulated time (s)."""
        slots = self._slots
        if slots is not None:
            slots[2] = np.uint64(int(horizon_s * 1e9) + 1)

    def harness_args(self, *, paced: bool) -> list[str]:
        """The command-line options that put a harness on this file: its clock lock, the longest it waits for a
        stamped write's bytes (:data:`KERNEL_HOP_MAX_S`), ``--no-pace`` unless ``paced``."""
        return ["--clock-lock", str(self.path), "--host-write-hold-s", str(KERNEL_HOP_MAX_S),
                *([] if paced else ["--no-pace"])]

    def board_port(self, board: str, path: str | os.PathLike[str]) -> None:
        """``path`` is the port of ``board`` (``"mega"`` or ``"uno"``: a key of :data:`WRITE_SLOTS`): a host's
        writes to it are stamped in that board's slot, and a client of this process that opens it finds the clock of
        :meth:`shared_clock` by it (:meth:`SharedClock.own_port`)."""
        if self._clock is not None:
            self._clock.own_port(path)
        index = WRITE_SLOTS[board]
        for key in port_keys(path):
            self._write_slots[key] = index

    def stamp(self, path: str, written: bool, n_bytes: int) -> None:
        """The clock's ``on_stamp``: a host of this process is about to write ``n_bytes`` bytes to the port ``path``
        (``written`` True; reads are not stamped): the bytes its stamped writes bring to the board, the bytes the
        harness has read or those the stamps before brought, whichever is more, plus ``n_bytes`` (the stamps before
        count only while the last is less than :data:`KERNEL_HOP_MAX_S` old: a write that failed brings nothing),
        then the moment, ``time.monotonic_ns`` (the harness's ``CLOCK_MONOTONIC``) + 1, in its board's slots.
        ``n_bytes`` negative: a stamped write that failed (:meth:`SharedClock.write_failed`), whose bytes the harness
        no longer waits for. A port of no board of this file is ignored."""
        board = self._write_slots.get(path) if written else None
        slots = self._slots
        if board is None or slots is None:
            return
        if n_bytes < 0:  # a stamped write that failed (SharedClock.write_failed): its bytes are not on their way
            with self._stamp_lock:
                read = int(slots[5 + board])
                slots[7 + board] = np.uint64(max(read, int(slots[7 + board]) + int(n_bytes)))
            return
        with self._stamp_lock:
            now_ns = time.monotonic_ns()
            last = int(slots[3 + board])
            brought = int(slots[7 + board]) if last and now_ns - (last - 1) < KERNEL_HOP_MAX_S * 1e9 else 0
            slots[7 + board] = np.uint64(max(brought, int(slots[5 + board])) + max(0, int(n_bytes)))
            slots[3 + board] = np.uint64(now_ns + 1)

    def bytes_read(self, board: str) -> int:
        """The bytes ``board``'s harness has read from its port (``"mega"`` or ``"uno"``)."""
        slots = self._slots
        return int(slots[5 + WRITE_SLOTS[board]]) if slots is not None else 0

    def board_times_s(self) -> tuple[float | None, float | None]:
        """The Mega's and the Uno's published times, s (None: not yet)."""
        slots = self._slots
        if slots is None:
            return None, None
        return tuple((int(v) - 1) * 1e-9 if v else None for v in slots[:2])  # type: ignore[return-value]

    def close(self) -> None:
        """Unmap the file (the harnesses keep their own mappings)."""
        self._slots = None
        if self._map is not None:
            try:
                self._map.close()
            except BufferError:  # an array view still alive somewhere: left to the garbage collector
                pass
            self._map = None
