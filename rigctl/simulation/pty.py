"""Pseudo-terminal ports for the virtual boards: paths a client opens with pyserial exactly like a USB serial port.

Two building blocks:

- :class:`PtyEndpoint`: one ``os.openpty()`` pair. The virtual board owns the master side (non-blocking reads and
  writes); the client opens the slave through a stable symlink (``link``), so the path survives an unplug/replug
  (a new pty under the same name, as udev does for a re-enumerated USB device). It can tell when a client opened the
  port (as DTR resets an Arduino on open): see :meth:`PtyEndpoint.client_opened`.
- :class:`PtyBridge`: two endpoints whose masters a thread copies to each other (like ``socat pty,link=A pty,link=B``)
  for servers that insist on opening a device path themselves (pymodbus' serial server).

``unplug()`` closes the board side: the client's next read fails the way an unplugged USB serial device fails under
pyserial (``SerialException``: "device reports readiness to read but returned no data" / "read failed: [Errno 5]"),
and the path disappears until ``replug()``.

The folder the port links live in is a :class:`PortDir`: one live process owns it (an ``flock`` on a lock file in
it), so a second simulated rig cannot take over (and on exit delete) the links of a running one; the temporary
folders (``rigctl-sim-<pid>-*``) of processes that died without cleaning up are removed when the next one starts.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import select
import shutil
import struct
import tempfile
import termios
import threading
import time
import tty
from pathlib import Path

from rigctl.simulation.priority import board_thread

log = logging.getLogger(__name__)

#: line speed the endpoint parks the slave at between client opens; any client open sets its own speed
_SENTINEL_SPEED = termios.B50


def _unread(fd: int | None) -> int:
    """Bytes waiting in the input queue of the tty behind ``fd`` (TIOCINQ); 0 for a closed fd."""
    if fd is None:
        return 0
    try:
        return struct.unpack("i", fcntl.ioctl(fd, termios.TIOCINQ, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def _write_some(fd: int, data: bytes | bytearray) -> int:
    """Write what the pty behind ``fd`` takes of ``data`` now (non-blocking): bytes written, 0 when it is full or
    has no reader side (EIO)."""
    try:
        return os.write(fd, data)
    except BlockingIOError:
        return 0
    except OSError as exc:
        if exc.errno in (errno.EIO, errno.EAGAIN):
            return 0
        raise


class PtyEndpoint:
    """One pty pair; the board side holds the master fd and a slave fd, the client opens :attr:`path`.

    Parameters
    ----------
    link : path or None
        Stable symlink created to the slave device (replaced on replug). ``None``: clients use the slave name.
    max_pending : int
        Bytes queued for the client when it does not read (a USB-serial chip would drop them too); beyond this,
        further writes are dropped and counted in :attr:`dropped_bytes`.
    """

    def __init__(self, link: str | os.PathLike | None = None, *, max_pending: int = 256 * 1024):
        self.link = Path(link) if link is not None else None
        self.max_pending = max_pending
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self.slave_name: str | None = None
        self._pending = bytearray()
        self.dropped_bytes = 0
        self._lock = threading.Lock()
        self._open()

    # ------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        attrs = termios.tcgetattr(slave)
        attrs[4] = attrs[5] = _SENTINEL_SPEED
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self.master_fd, self._slave_fd = master, slave
        self.slave_name = os.ttyname(slave)
        self._pending.clear()
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".new")
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link)

    @property
    def path(self) -> str:
        """The path a client opens (the symlink if any, else the slave device)."""
        return str(self.link) if self.link is not None else str(self.slave_name)

    @property
    def plugged(self) -> bool:
        return self.master_fd is not None

    def fileno(self) -> int:
        if self.master_fd is None:
            raise OSError(errno.EBADF, "pty endpoint is unplugged")
        return self.master_fd

    def unplug(self) -> None:
        """Close the board side and remove the link: the client sees the device vanish."""
        with self._lock:
            if self.link is not None:
                try:
                    self.link.unlink()
                except FileNotFoundError:
                    pass
            for fd in (self.master_fd, self._slave_fd):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self.master_fd = self._slave_fd = None
            self._pending.clear()

    def replug(self) -> None:
        """Create a fresh pty under the same link (no-op if plugged)."""
        with self._lock:
            if self.master_fd is None:
                self._open()

    def close(self) -> None:
        self.unplug()

    # ------------------------------------------------------------------ I/O (board side)
    def write(self, data: bytes) -> int:
        """Queue ``data`` for the client and write what the pty takes now (non-blocking). Returns bytes accepted."""
        with self._lock:
            if self.master_fd is None:
                return 0
            room = self.max_pending - len(self._pending)
            if len(data) > room:
                self.dropped_bytes += len(data) - max(room, 0)
                data = data[: max(room, 0)]
            if not self._pending:  # straight into the pty; what it does not take now is queued
                n = _write_some(self.master_fd, data) if data else 0
                if n < len(data):
                    self._pending += data[n:]
                return len(data)
            self._pending += data
            self._flush_locked()
            return len(data)

    def flush(self) -> int:
        """Write queued bytes that the pty now takes; returns bytes still queued."""
        with self._lock:
            self._flush_locked()
            return len(self._pending)

    def _flush_locked(self) -> None:
        while self._pending and self.master_fd is not None:
            n = _write_some(self.master_fd, self._pending)
            if not n:
                return
            del self._pending[:n]

    def unread_from_client(self) -> int:
        """Bytes the client wrote that nobody has read from the master side yet."""
        return _unread(self.master_fd)

    def unread_by_board(self) -> int:
        """Bytes written to the client side of this pty (queued or in the pty) that its client has not read yet.

        For the board end of a :class:`PtyBridge`, whose "client" is the board's server (e.g. pymodbus). Lock-free
        (a starved writer holding the lock must not stall the caller): a flush writes bytes into the pty before it
        drops them from the queue, and the queue is looked at first, so bytes on the move are never missed."""
        return len(self._pending) + _unread(self._slave_fd)

    def read(self, size: int = 4096) -> bytes:
        """Bytes the client wrote (non-blocking; ``b""`` if none or unplugged)."""
        fd = self.master_fd
        if fd is None:
            return b""
        try:
            return os.read(fd, size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EBADF):
                return b""
            raise

    def discard_output(self) -> None:
        """Drop bytes queued for the client (not yet in the pty)."""
        with self._lock:
            self._pending.clear()

    def client_opened(self) -> bool:
        """True once after a client opened and configured the port (pyserial sets the line speed on open).

        Emulates the DTR reset of an Arduino: the endpoint parks the slave at a sentinel speed, a client's
        ``tcsetattr`` changes it, and this call re-arms the sentinel (the speed of a pty is otherwise unused).
        """
        with self._lock:
            fd = self._slave_fd
            if fd is None:
                return False
            try:
                attrs = termios.tcgetattr(fd)
            except termios.error:
                return False
            if attrs[4] == _SENTINEL_SPEED and attrs[5] == _SENTINEL_SPEED:
                return False
            attrs[4] = attrs[5] = _SENTINEL_SPEED
            try:
                termios.tcsetattr(fd, termios.TCSANOW, attrs)
            except termios.error:
                pass
            return True


class PtyBridge:
    """Two pty endpoints joined by a copy thread: the board opens :attr:`board_path`, the client :attr:`client_path`.

    Parameters
    ----------
    client_link : path or None
        Stable symlink for the client side. ``unplug()``/``replug()`` act on the client side.

    Notes
    -----
    The copy thread is a Python thread and can be starved (GIL, a loaded CPU) for hundreds of ms, which a USB cable
    never is: :meth:`bytes_to_board` tells the board bytes that the client has sent but the board's server has not
    read yet, wherever they wait on the way.
    """

    def __init__(self, client_link: str | os.PathLike | None = None):
        self.board = PtyEndpoint(None)
        self.client = PtyEndpoint(client_link)
        self._copying = False  # client bytes in this thread's hands (about to be read, or read and not yet written)
        self._copying_from_board = False  # and the board's
        #: when the copy thread last began to hand the client's bytes to the board's pty (time.monotonic): bytes a
        #: pty's writer has handed over reach its reader through a kernel worker, which a loaded machine can hold
        #: back for hundreds of ms, and no byte count (TIOCINQ) sees them meanwhile
        self.to_board_at = 0.0
        #: when the copy thread last took bytes from the client's pty (time.monotonic): a client's write after it is
        #: still in the kernel's hands on the client side (:meth:`rigctl.core.shared_clock.SharedClock.note_write`)
        self.from_client_at = 0.0
        #: when the copy thread last took bytes from the board's pty (time.monotonic): a reply the board's server wrote
        #: after it is still in the kernel's hands on the board side
        self.from_board_at = 0.0
        #: when the copy thread last began to hand the board's bytes to the client's pty (time.monotonic)
        self.to_client_at = 0.0
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=board_thread(self._run), name="pty-bridge", daemon=True)
        self._thread.start()

    @property
    def board_path(self) -> str:
        return self.board.path

    @property
    def client_path(self) -> str:
        return self.client.path

    def _run(self) -> None:
        while not self._stop.is_set():
            fds = [self._wake_r]
            ends = {}
            for end, other in ((self.board, self.client), (self.client, self.board)):
                fd = end.master_fd
                if fd is not None:
                    fds.append(fd)
                    ends[fd] = (end, other)
            try:
                ready, _, _ = select.select(fds, [], [], 0.05)
            except (OSError, ValueError):
                continue  # an fd was closed by unplug(); rebuild the set
            for fd in ready:
                if fd == self._wake_r:
                    os.read(self._wake_r, 64)
                    continue
                end, other = ends[fd]
                self._copying = end is self.client
                self._copying_from_board = end is self.board
                try:
                    data = end.read(65536)
                    if data:
                        if other is self.board:  # stamped before the write: whatever the server reads of them is later
                            self.to_board_at = self.from_client_at = time.monotonic()
                        else:
                            self.from_board_at = self.to_client_at = time.monotonic()
                        other.write(data)
                finally:
                    self._copying = self._copying_from_board = False
            self.board.flush()
            self.client.flush()

    def bytes_to_board(self) -> int:
        """Bytes the client has written that the board's server has not read yet (in the client pty, in the copy
        thread's hands (counted as 1), queued for the board or in the board pty). Lock-free, and looked at upstream
        first, so bytes that move on meanwhile are counted where they get to."""
        n = self.client.unread_from_client()
        n += 1 if self._copying else 0
        return n + self.board.unread_by_board()

    def bytes_from_board(self) -> int:
        """Bytes the board's server has written that have not reached the client's side yet (in the board pty, in
        the copy thread's hands (counted as 1), or queued for the client pty): the simulator's own delay, which the
        host waits out. Bytes already in the client's pty are the host's to read, and not counted. Lock-free."""
        n = self.board.unread_from_client()
        n += 1 if self._copying_from_board else 0
        return n + len(self.client._pending)

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def unplug(self) -> None:
        self.client.unplug()
        self._wake()

    def replug(self) -> None:
        self.client.replug()
        self.from_client_at = time.monotonic()  # what the client wrote into the old pty is gone with it
        self._wake()

    def close(self) -> None:
        self._stop.set()
        self._wake()
        self._thread.join(timeout=2)
        self.client.close()
        self.board.close()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass


# ---------------------------------------------------------------------------------------------------------------------
# The folder of the port links
# ---------------------------------------------------------------------------------------------------------------------
#: lock file a live simulated rig holds (flock) in its port folder; it contains the owner's pid
LOCK_NAME = ".rigctl-sim.lock"
#: temporary port folders are ``<tmp>/rigctl-sim-<pid>-<random>``
TEMP_PREFIX = "rigctl-sim-"
_TEMP_NAME = re.compile(r"^rigctl-sim-(\d+)-")


class PortDirBusy(RuntimeError):
    """The port folder is owned by another live simulated rig (the message names the folder and its pid)."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's
        return True
    return True


def _try_lock(path: Path, *, create: bool) -> int | None:
    """An fd holding an exclusive flock on ``path`` (the file at that path now, not an unlinked one), or None if
    another process holds it (or, without ``create``, there is no such file)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | (os.O_CREAT if create else 0), 0o644)
        except FileNotFoundError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the owner removed the file meanwhile: lock the one there now
        if not create:
            return None


def _owner(path: Path) -> str:
    try:
        return path.read_text().strip() or "?"
    except OSError:
        return "?"


def _dead_links_only(d: Path) -> bool:
    """True if ``d`` holds only symlinks whose targets are gone (at least one)."""
    try:
        entries = list(d.iterdir())
    except OSError:
        return False
    return bool(entries) and all(e.is_symlink() and not e.exists() for e in entries)


def remove_stale_port_dirs(tmp_dir: str | os.PathLike | None = None) -> list[Path]:
    """Remove the temporary port folders (``rigctl-sim-<pid>-*``) of simulated rigs that died without cleaning up
    (killed: their pid is gone and nobody holds the folder's lock), and those of older versions (``rigctl-sim-*``
    without a pid) whose port links all point at ptys that are gone. Returns the folders removed.

    Folders of live processes are left alone; so is anything that does not look like a port folder."""
    removed: list[Path] = []
    base = Path(tmp_dir or tempfile.gettempdir())
    try:
        entries = list(base.glob(TEMP_PREFIX + "*"))
    except OSError:
        return removed
    for d in entries:
        m = _TEMP_NAME.match(d.name)
        if not d.is_dir() or d.is_symlink():
            continue
        if m is None:  # a folder of an older rigctl (no pid in its name, no lock): stale once its ptys are gone
            if _dead_links_only(d):
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
            continue
        if _alive(int(m.group(1))):
            continue
        fd = _try_lock(d / LOCK_NAME, create=False)
        if fd is None and (d / LOCK_NAME).exists():
            continue  # held: alive after all (another pid namespace)
        try:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
            log.info("removed the port folder %s of a simulated rig that is gone (pid %s)", d, m.group(1))
        finally:
            if fd is not None:
                os.close(fd)
    return removed


class PortDir:
    """The folder of a simulated rig's port links, owned by this process while it runs.

    Parameters
    ----------
    path : folder or None
        A folder to use (created if missing; the links in it are removed on :meth:`release`, the folder is kept),
        or None: a fresh temporary folder ``rigctl-sim-<pid>-*`` (removed on :meth:`release`). Either way the
        temporary folders of dead simulated rigs are removed first (:func:`remove_stale_port_dirs`).

    links : the names of the port links the rig makes in it: one that exists and is not a symlink (a file of the
        user's named ``drum``) is refused (FileExistsError), never replaced nor removed.

    Raises
    ------
    PortDirBusy if another live process owns ``path``; FileExistsError if a ``links`` name is taken by a file;
    OSError if the folder cannot be made or written.
    """

    def __init__(self, path: str | os.PathLike | None = None, links: tuple[str, ...] = ()):
        self.temporary = path is None
        remove_stale_port_dirs()
        if path is None:
            self.path = Path(tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-"))
        else:
            self.path = Path(path)
            self.path.mkdir(parents=True, exist_ok=True)
        lock = self.path / LOCK_NAME
        lock_was_there = os.path.lexists(lock)
        fd = _try_lock(lock, create=True)
        if fd is None:
            raise PortDirBusy(f"{self.path} holds the ports of another running simulated rig (pid {_owner(lock)}): "
                              "choose another --port-dir, or stop that one")
        taken = [name for name in links if os.path.lexists(self.path / name) and not (self.path / name).is_symlink()]
        if taken:
            if not lock_was_there:
                with contextlib.suppress(OSError):
                    lock.unlink()
            os.close(fd)
            raise FileExistsError(errno.EEXIST, f"{self.path / taken[0]} is a file, not a port link: rigctl never "
                                                "replaces it; choose another --port-dir")
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd: int | None = fd

    def release(self, links: tuple[str, ...] = ()) -> None:
        """Give the folder up: a temporary one is removed; in a given one the ``links`` and the lock file are."""
        if self._fd is None:
            return
        try:
            if self.temporary:
                shutil.rmtree(self.path, ignore_errors=True)
            else:
                for name in (*links, LOCK_NAME):
                    try:
                        (self.path / name).unlink()
                    except FileNotFoundError:
                        pass
        finally:
            os.close(self._fd)
            self._fd = None
