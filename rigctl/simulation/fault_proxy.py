"""A fault-injecting serial proxy: a real pty between the host and a (simulated) board's port that mangles the bytes.

:class:`FaultProxy` opens the board's port (e.g. :attr:`rigctl.simulation.rig.SimulatedRig.taxel_port` or
``drum_port``) and offers the host a new pty under :attr:`FaultProxy.path`. A thread forwards both directions,
``"to_host"`` (board -> host) and ``"to_board"`` (host -> board), and on the way it can

- flip one bit of a byte, drop a byte, insert a random byte, insert a burst of random bytes, each with a per-byte
  probability (:class:`FaultRates`, seeded random generator), and add a constant latency;
- on demand: drop the next n bytes (:meth:`FaultProxy.drop_next`), inject given bytes (:meth:`FaultProxy.inject`),
  hold a direction for a while and release what was held in order (:meth:`FaultProxy.stall`), cut the link (the
  host's port vanishes: its pty is closed and the path removed, as an unplugged USB device) and restore it
  (:meth:`FaultProxy.cut`, :meth:`FaultProxy.restore`);
- at scheduled times or on traffic: :meth:`FaultProxy.schedule` runs any of these in the proxy's thread after a
  delay, :meth:`FaultProxy.after_bytes` once so many more bytes have been received in a direction (e.g. "release
  the held response once the host has sent its next request");

and it counts exactly what it did (:meth:`FaultProxy.stats`: bytes received, forwarded, dropped, flipped,
inserted, lost while cut, per direction; cuts and restores).

The host opening the proxy's port is passed on to the board (the pty line speed changes, which the virtual Uno takes
as the DTR reset of a real Uno; see :meth:`rigctl.simulation.pty.PtyEndpoint.client_opened`), so a host that reopens
a restored port gets a fresh ready banner exactly as it would from the board itself.

Example::

    with SimulatedRig() as sim, FaultProxy(sim.taxel_port, tmp / "taxel", seed=1,
                                           to_host=FaultRates(flip=1e-5, garbage=1e-5)) as proxy:
        with TaxelStream(proxy.path) as stream:
            ...
            proxy.cut(); time.sleep(0.3); proxy.restore()
        print(proxy.stats())
"""

from __future__ import annotations

import errno
import heapq
import itertools
import logging
import os
import select
import termios
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from rigctl.simulation.priority import board_thread
from rigctl.simulation.pty import PtyEndpoint

log = logging.getLogger(__name__)

TO_HOST = "to_host"  #: board -> host
TO_BOARD = "to_board"  #: host -> board
DIRECTIONS = (TO_HOST, TO_BOARD)

_BOARD_SPEED = termios.B115200  # any speed but the pty endpoint's parking speed tells the board "a client opened"


@dataclass(frozen=True)
class FaultRates:
    """Random faults of one direction. Probabilities are per byte received (0 <= p <= 1); ``ValueError`` otherwise.

    Attributes
    ----------
    flip : probability that a forwarded byte has one random bit flipped.
    drop : probability that a byte is dropped.
    insert : probability that one random byte is inserted after a byte.
    garbage : probability that a burst of 1 .. ``garbage_max`` random bytes is inserted after a byte.
    garbage_max : longest garbage burst, bytes (>= 1).
    delay_s : latency added to every byte, s (>= 0; the order of the bytes is kept).
    """

    flip: float = 0.0
    drop: float = 0.0
    insert: float = 0.0
    garbage: float = 0.0
    garbage_max: int = 64
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("flip", "drop", "insert", "garbage"):
            p = getattr(self, name)
            if not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"fault rate {name}={p!r} is not a probability (0-1)")
        if int(self.garbage_max) < 1:
            raise ValueError(f"garbage_max must be >= 1 byte, got {self.garbage_max}")
        if not float(self.delay_s) >= 0.0:
            raise ValueError(f"delay_s must be >= 0 s, got {self.delay_s}")


@dataclass
class DirectionCounts:
    """What the proxy did to one direction, in bytes.

    Once nothing is held (:meth:`FaultProxy.wait_idle`):
    ``forwarded + lost_while_cut + overflowed == received - dropped + inserted``. ``flipped`` bytes are among the
    forwarded ones.
    """

    received: int = 0  #: bytes read from the sending side
    forwarded: int = 0  #: bytes written to the receiving side (inserted ones included)
    dropped: int = 0  #: received bytes not forwarded (random drops and :meth:`FaultProxy.drop_next`)
    flipped: int = 0  #: forwarded bytes with one bit flipped
    inserted: int = 0  #: extra bytes forwarded (random inserts, garbage bursts, :meth:`FaultProxy.inject`)
    garbage_bursts: int = 0  #: random garbage bursts inserted (their bytes are in ``inserted``)
    lost_while_cut: int = 0  #: bytes for the host discarded because the link was cut
    overflowed: int = 0  #: bytes the receiver did not take (a host that stopped reading; a board port gone)


@dataclass
class ProxyStats:
    """A snapshot of a :class:`FaultProxy`'s counters."""

    to_host: DirectionCounts = field(default_factory=DirectionCounts)
    to_board: DirectionCounts = field(default_factory=DirectionCounts)
    cuts: int = 0
    restores: int = 0
    connected: bool = True  #: the host's port exists (not cut)


def _check_direction(direction: str) -> str:
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    return direction


class FaultProxy:
    """A pty at ``link`` that forwards to and from the port at ``board_path``, injecting faults (context manager).

    Parameters
    ----------
    board_path : str or path
        The board's port (a pty slave or a symlink to one, e.g. a simulated rig's ``taxel_port``).
    link : str or path
        Path of the symlink the host opens (created; replaced by :meth:`restore`).
    to_host, to_board : FaultRates
        Random faults of each direction (none by default).
    seed : int
        Seed of the random generator.

    Raises
    ------
    OSError
        The board's port cannot be opened.
    """

    def __init__(self, board_path, link, *, to_host: FaultRates | None = None, to_board: FaultRates | None = None,
                 seed: int = 0):
        self.board_path = os.fspath(board_path)
        self._rng = np.random.default_rng(seed)
        self._rates = {TO_HOST: to_host or FaultRates(), TO_BOARD: to_board or FaultRates()}
        self._counts = {d: DirectionCounts() for d in DIRECTIONS}
        self._drop_next = {d: 0 for d in DIRECTIONS}
        self._stall_until = {d: 0.0 for d in DIRECTIONS}
        self._queues: dict[str, deque] = {d: deque() for d in DIRECTIONS}  # (release time, bytes)
        self._cuts = self._restores = 0
        self._cut = False
        self._timers: list = []  # heap of (due, n, fn, args)
        self._triggers: list = []  # (direction, received count that fires it, fn, args)
        self._timer_ids = itertools.count()
        self._lock = threading.RLock()
        self._board_fd: int | None = None
        self._open_board()
        self.host = PtyEndpoint(link)
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def path(self) -> str:
        """The path the host opens (a symlink to the proxy's pty; absent while the link is cut)."""
        return self.host.path

    def start(self) -> "FaultProxy":
        """Start forwarding (idempotent)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=board_thread(self._run), name="fault-proxy", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop forwarding, close both sides and remove the host's path."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=3)
            self._thread = None
        self.host.close()
        with self._lock:
            self._close_board()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "FaultProxy":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _open_board(self) -> None:
        fd = os.open(self.board_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        self._board_fd = fd
        self._signal_open()

    def _close_board(self) -> None:
        if self._board_fd is not None:
            try:
                os.close(self._board_fd)
            except OSError:
                pass
            self._board_fd = None

    def _signal_open(self) -> None:
        """Tell the board a client opened its port (the line speed changes: the virtual Uno's DTR reset)."""
        if self._board_fd is None:  # the board's side is not open
            return
        try:
            attrs = termios.tcgetattr(self._board_fd)
            attrs[4] = attrs[5] = _BOARD_SPEED
            termios.tcsetattr(self._board_fd, termios.TCSANOW, attrs)
        except (termios.error, OSError, TypeError):
            pass

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    # ------------------------------------------------------------------ faults
    def set_rates(self, direction: str, rates: FaultRates) -> None:
        """Replace the random faults of ``direction`` (``"to_host"`` or ``"to_board"``) from now on."""
        with self._lock:
            self._rates[_check_direction(direction)] = rates

    def rates(self, direction: str) -> FaultRates:
        """The random faults of ``direction`` now."""
        return self._rates[_check_direction(direction)]

    def drop_next(self, n: int, direction: str = TO_HOST) -> None:
        """Drop the next ``n`` bytes received in ``direction``."""
        with self._lock:
            self._drop_next[_check_direction(direction)] += int(n)

    def inject(self, data: bytes, direction: str = TO_HOST) -> None:
        """Send ``data`` in ``direction`` now (after what is already held there); counted as inserted."""
        with self._lock:
            d = _check_direction(direction)
            self._counts[d].inserted += len(data)
            self._enqueue(d, bytes(data), time.monotonic())
        self._wake()

    def stall(self, seconds: float, direction: str | None = None) -> None:
        """Hold ``direction`` (both if None) for ``seconds`` from now: nothing passes, what arrives meanwhile is
        kept and released in order when the stall ends (a board or USB hub that stops answering for a while)."""
        until = time.monotonic() + float(seconds)
        with self._lock:
            for d in DIRECTIONS if direction is None else (_check_direction(direction),):
                self._stall_until[d] = max(self._stall_until[d], until)
        self._wake()

    def cut(self) -> None:
        """Cut the link: the host's port vanishes (its pty is closed, the path removed); bytes for the host are
        lost (counted) until :meth:`restore`. No-op if already cut."""
        with self._lock:
            if self._cut:
                return
            self._cut = True
            self._cuts += 1
            lost = sum(len(b) for _, b in self._queues[TO_HOST])
            self._counts[TO_HOST].lost_while_cut += lost
            self._queues[TO_HOST].clear()
            unsent = len(self.host._pending)  # handed to the host's pty queue but not in the pty yet: lost too
            self._counts[TO_HOST].forwarded -= unsent
            self._counts[TO_HOST].lost_while_cut += unsent
            self.host.unplug()
        self._wake()

    def restore(self) -> None:
        """Restore a cut link: a fresh pty under the same path (the host reopens it). No-op if not cut."""
        with self._lock:
            if not self._cut:
                return
            self.host.replug()
            self._cut = False
            self._restores += 1
        self._wake()

    def release(self, direction: str | None = None) -> None:
        """End a stall of ``direction`` (both if None) now: what was held goes out, in order."""
        with self._lock:
            for d in DIRECTIONS if direction is None else (_check_direction(direction),):
                self._stall_until[d] = 0.0
        self._wake()

    @property
    def is_cut(self) -> bool:
        return self._cut

    def schedule(self, after_s: float, action, *args) -> None:
        """Run ``action(*args)`` (e.g. ``proxy.cut``, ``proxy.restore``, ``proxy.stall, 0.5``) in the proxy's thread
        ``after_s`` seconds from now."""
        with self._lock:
            heapq.heappush(self._timers, (time.monotonic() + float(after_s), next(self._timer_ids), action, args))
        self._wake()

    def after_bytes(self, direction: str, n: int, action, *args) -> None:
        """Run ``action(*args)`` in the proxy's thread once ``n`` more bytes have been received in ``direction``
        (before those bytes are forwarded), e.g. ``proxy.after_bytes("to_board", 8, proxy.release)``."""
        with self._lock:
            d = _check_direction(direction)
            self._triggers.append((d, self._counts[d].received + int(n), action, args))

    def _fire_triggers(self) -> None:
        with self._lock:
            due = [t for t in self._triggers if self._counts[t[0]].received >= t[1]]
            self._triggers = [t for t in self._triggers if t not in due]
        for _, _, fn, args in due:
            try:
                fn(*args)
            except Exception:  # a triggered action must not kill the proxy
                log.exception("triggered fault %r failed", fn)

    # ------------------------------------------------------------------ counters
    def stats(self) -> ProxyStats:
        """A snapshot of the counters (:class:`ProxyStats`)."""
        with self._lock:
            return ProxyStats(replace(self._counts[TO_HOST]), replace(self._counts[TO_BOARD]), self._cuts,
                              self._restores, not self._cut)

    def held(self, direction: str | None = None) -> int:
        """Bytes received and not yet forwarded (delayed, stalled, or waiting for the receiver)."""
        with self._lock:
            ds = DIRECTIONS if direction is None else (_check_direction(direction),)
            n = sum(len(b) for d in ds for _, b in self._queues[d])
            if direction in (None, TO_HOST):
                n += len(self.host._pending)
        return n

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        """Wait until nothing is held in either direction; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while self.held():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)
        return True

    # ------------------------------------------------------------------ the forwarding thread
    def _mangle(self, d: str, data: bytes) -> bytes:
        """Apply the random and the on-demand faults of direction ``d`` to ``data``; count them."""
        rates, counts, rng = self._rates[d], self._counts[d], self._rng
        counts.received += len(data)
        arr = np.frombuffer(data, np.uint8).copy()
        n = arr.size
        keep = np.ones(n, bool)
        if self._drop_next[d]:
            k = min(n, self._drop_next[d])
            keep[:k] = False
            self._drop_next[d] -= k
        if rates.drop:
            keep &= rng.random(n) >= rates.drop
        if rates.flip:
            flip = (rng.random(n) < rates.flip) & keep
            k = int(flip.sum())
            if k:
                arr[flip] ^= (np.uint8(1) << rng.integers(0, 8, k).astype(np.uint8))
                counts.flipped += k
        counts.dropped += int(n - keep.sum())
        inserts: list[tuple[int, bytes]] = []  # (after byte i, bytes)
        if rates.insert:
            for i in np.flatnonzero(rng.random(n) < rates.insert):
                inserts.append((int(i), rng.integers(0, 256, 1, dtype=np.uint8).tobytes()))
        if rates.garbage:
            for i in np.flatnonzero(rng.random(n) < rates.garbage):
                burst = rng.integers(0, 256, int(rng.integers(1, rates.garbage_max + 1)), dtype=np.uint8).tobytes()
                inserts.append((int(i), burst))
                counts.garbage_bursts += 1
        if not inserts:
            return arr[keep].tobytes()
        inserts.sort(key=lambda x: x[0])
        out, lo = [], 0
        for at, extra in inserts:
            out.append(arr[lo:at + 1][keep[lo:at + 1]].tobytes())
            out.append(extra)
            counts.inserted += len(extra)
            lo = at + 1
        out.append(arr[lo:][keep[lo:]].tobytes())
        return b"".join(out)

    def _enqueue(self, d: str, data: bytes, now: float) -> None:
        if not data:
            return
        if d == TO_HOST and self._cut:
            self._counts[d].lost_while_cut += len(data)
            return
        q = self._queues[d]
        release = now + self._rates[d].delay_s
        if q:
            release = max(release, q[-1][0])  # the order of the bytes is kept
        q.append((release, data))

    def _release(self, now: float) -> float:
        """Forward what is due; return the time until the next release (or a default poll period)."""
        wait = 0.01
        for d in DIRECTIONS:
            q = self._queues[d]
            if now < self._stall_until[d]:
                if q:
                    wait = min(wait, self._stall_until[d] - now)
                continue
            while q and q[0][0] <= now:
                _, data = q.popleft()
                if d == TO_HOST:
                    if self._cut:
                        self._counts[d].lost_while_cut += len(data)
                        continue
                    taken = self.host.write(data)
                    self._counts[d].forwarded += taken
                    if taken < len(data):  # the host's pty queue overflowed (the host does not read)
                        self._counts[d].overflowed += len(data) - taken
                else:
                    self._write_board(data)
            if q:
                wait = min(wait, max(0.0, q[0][0] - now))
        return wait

    def _write_board(self, data: bytes) -> None:
        fd = self._board_fd
        view = memoryview(data)
        deadline = time.monotonic() + 1.0
        while view and fd is not None:
            try:
                k = os.write(fd, view)
                self._counts[TO_BOARD].forwarded += k
                view = view[k:]
            except BlockingIOError:
                if time.monotonic() > deadline:
                    break
                select.select([], [fd], [], 0.01)
            except OSError:
                break
        if view:  # the board is gone or does not read: what it could not take is lost
            self._counts[TO_BOARD].overflowed += len(view)

    def _run_timers(self, now: float) -> float:
        wait = 0.01
        while True:
            with self._lock:
                if not self._timers:
                    return wait
                due, _, fn, args = self._timers[0]
                if due > now:
                    return min(wait, due - now)
                heapq.heappop(self._timers)
            try:
                fn(*args)
            except Exception:  # a scheduled action must not kill the proxy
                log.exception("scheduled fault %r failed", fn)

    def _run(self) -> None:
        wait = 0.01
        while not self._stop.is_set():
            fds = [self._wake_r]
            host_fd = self.host.master_fd
            board_fd = self._board_fd
            if host_fd is not None and not self._cut:
                fds.append(host_fd)
            if board_fd is not None:
                fds.append(board_fd)
            try:
                ready, _, _ = select.select(fds, [], [], max(0.0005, wait))
            except (OSError, ValueError):
                ready = []  # an fd was closed meanwhile (cut); rebuild the set
            now = time.monotonic()
            if self.host.client_opened():  # the host (re)opened its port: the board resets, as on DTR
                with self._lock:
                    if self._board_fd is not None:
                        self._signal_open()
            for fd in ready:
                if fd == self._wake_r:
                    os.read(self._wake_r, 64)
                elif fd == board_fd:
                    data = self._read(board_fd)
                    if data is None:  # the board's port vanished: try to reopen it later
                        with self._lock:
                            self._close_board()
                    elif data:
                        with self._lock:
                            self._enqueue(TO_HOST, self._mangle(TO_HOST, data), now)
                elif fd == host_fd:
                    data = self.host.read(65536)
                    if data:
                        with self._lock:
                            self._enqueue(TO_BOARD, self._mangle(TO_BOARD, data), now)
            if self._board_fd is None:
                try:
                    with self._lock:
                        self._open_board()
                except OSError:
                    pass
            if self._triggers:
                self._fire_triggers()
            wait = self._run_timers(time.monotonic())
            with self._lock:
                wait = min(wait, self._release(time.monotonic()))
                self.host.flush()

    @staticmethod
    def _read(fd: int) -> bytes | None:
        """Bytes waiting on the board's side; ``b""`` if none, None if the port is gone."""
        try:
            data = os.read(fd, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EBADF, errno.ENXIO):
                return None
            raise
        return data if data else None


__all__ = ["DIRECTIONS", "TO_BOARD", "TO_HOST", "DirectionCounts", "FaultProxy", "FaultRates", "ProxyStats"]
