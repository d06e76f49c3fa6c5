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
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import struct
import termios
import threading
import tty
from pathlib import Path

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
            try:
                n = os.write(self.master_fd, self._pending)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    return
                raise
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

    The copy thread is a Python thread and can be starved (GIL, a loaded CPU) for hundreds of ms, which a USB cable
    never is: :meth:`bytes_to_board` tells the board bytes that the client has sent but the board's server has not
    read yet, wherever they wait on the way.
    """

    def __init__(self, client_link: str | os.PathLike | None = None):
        self.board = PtyEndpoint(None)
        self.client = PtyEndpoint(client_link)
        self._copying = False  # client bytes in this thread's hands (about to be read, or read and not yet written)
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)
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
                try:
                    data = end.read(65536)
                    if data:
                        other.write(data)
                finally:
                    self._copying = False
            self.board.flush()
            self.client.flush()

    def bytes_to_board(self) -> int:
        """Bytes the client has written that the board's server has not read yet (in the client pty, in the copy
        thread's hands (counted as 1), queued for the board or in the board pty). Lock-free, and looked at upstream
        first, so bytes that move on meanwhile are counted where they get to."""
        n = self.client.unread_from_client()
        n += 1 if self._copying else 0
        return n + self.board.unread_by_board()

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
