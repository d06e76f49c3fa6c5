"""Serial-port discovery: which port is the drum controller (Mega) and which the taxel streamer (Uno).

Guesses from the USB vendor/product id (pyserial's ``serial.tools.list_ports``). Clone boards with a CH340 or
FTDI bridge cannot be told apart by id: they are reported with ``board=None`` and the candidates in ``note``.

A port can be named by the board's USB serial number instead of its path: ``serial:<number>`` (:func:`resolve_port`,
looked up again at every open, so a board that re-enumerates as another ttyACM keeps its role and the two boards
cannot swap), and :func:`udev_rules` writes udev rules that give each board a stable symlink by ``ATTRS{serial}``
and keep ModemManager off it. :func:`lock_exclusive` makes an open port exclusive (TIOCEXCL).
"""

from __future__ import annotations

import fcntl
import os
import re
import termios
from dataclasses import asdict, dataclass
from typing import Any

from serial.tools import list_ports

#: (vid, pid) -> (board guess, description). Arduino SA / Arduino LLC ids and the usual clone bridges.
USB_IDS: dict[tuple[int, int], tuple[str | None, str]] = {
    (0x2341, 0x0042): ("mega", "Arduino Mega 2560 R3"),
    (0x2341, 0x0010): ("mega", "Arduino Mega 2560"),
    (0x2A03, 0x0042): ("mega", "Arduino Mega 2560 R3 (arduino.org)"),
    (0x2A03, 0x0010): ("mega", "Arduino Mega 2560 (arduino.org)"),
    (0x2341, 0x0043): ("uno", "Arduino Uno R3"),
    (0x2341, 0x0001): ("uno", "Arduino Uno"),
    (0x2A03, 0x0043): ("uno", "Arduino Uno R3 (arduino.org)"),
    (0x2341, 0x0243): ("uno", "Arduino Uno R3 (CH340 edition)"),
    (0x2341, 0x0069): ("uno", "Arduino Uno R4 Minima"),
    (0x1A86, 0x7523): (None, "CH340 USB-serial (clone Uno or Mega)"),
    (0x1A86, 0x55D4): (None, "CH9102 USB-serial (clone Uno or Mega)"),
    (0x0403, 0x6001): (None, "FTDI FT232R USB-serial (clone or older Arduino)"),
    (0x10C4, 0xEA60): (None, "Silicon Labs CP210x USB-serial (clone)"),
}


@dataclass(frozen=True)
class PortInfo:
    """One serial port: ``device`` path, USB ``vid``/``pid`` (None if not USB), ``description``, ``board`` guess
    ("mega" | "uno" | None), ``serial_number`` and a ``note`` on how the guess was made."""

    device: str
    vid: int | None
    pid: int | None
    description: str
    board: str | None
    serial_number: str | None = None
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["vid"] = f"{self.vid:04x}" if self.vid is not None else None
        d["pid"] = f"{self.pid:04x}" if self.pid is not None else None
        return d


def guess_board(vid: int | None, pid: int | None) -> tuple[str | None, str]:
    """(board guess, note) for a USB id: ``("mega", ...)``, ``("uno", ...)`` or ``(None, why)``."""
    if vid is None or pid is None:
        return None, "not a USB device"
    hit = USB_IDS.get((vid, pid))
    if hit is None:
        return None, "unknown USB id"
    board, name = hit
    return board, name if board else name + ": open it to tell (banner or Modbus reply)"


def find_ports(include_all: bool = False) -> list[PortInfo]:
    """Serial ports of this machine with a board guess, Arduino boards first.

    Parameters
    ----------
    include_all : bool
        Also list ports without a USB id (e.g. built-in ``/dev/ttyS*``); by default only USB ports.
    """
    out = []
    for p in list_ports.comports():
        if p.vid is None and not include_all:
            continue
        board, note = guess_board(p.vid, p.pid)
        out.append(PortInfo(device=p.device, vid=p.vid, pid=p.pid, description=p.description or "", board=board,
                            serial_number=p.serial_number, note=note))
    out.sort(key=lambda i: ({"mega": 0, "uno": 1}.get(i.board or "", 2), i.device))
    return out


#: TIOCGEXCL (Linux >= 3.8, asm-generic/ioctls.h): whether a tty is in exclusive mode
TIOCGEXCL = 0x80045440


def lock_exclusive(ser: Any) -> None:
    """Put an open serial port (anything with ``fileno()``) in the tty's exclusive mode (``TIOCEXCL``): any further
    ``open()`` of the device fails with EBUSY in the kernel, before the driver raises DTR, so another program (a
    second rigctl, a serial monitor, ModemManager's probe) can neither talk to the board nor reset it. pyserial's
    ``exclusive=True`` is an advisory ``flock`` only, taken after the open, which has already reset the board. Root
    (CAP_SYS_ADMIN) bypasses TIOCEXCL. Ports without a tty (test transports) are left alone."""
    try:
        fcntl.ioctl(ser.fileno(), termios.TIOCEXCL)
    except (OSError, ValueError, AttributeError):
        pass


def is_exclusive(ser: Any) -> bool:
    """Whether the open port ``ser`` is in the tty's exclusive mode (TIOCGEXCL); False when it cannot be asked."""
    buf = bytearray(4)
    try:
        fcntl.ioctl(ser.fileno(), TIOCGEXCL, buf)
    except (OSError, ValueError, AttributeError):
        return False
    return int.from_bytes(buf, "little") != 0


#: prefix of a port named by the board's USB serial number
SERIAL_PREFIX = "serial:"


class PortNotFound(OSError):
    """No connected serial port has the USB serial number asked for (an OSError: like a device path that is
    missing, the board may come back)."""


def resolve_port(port: str) -> str:
    """The device path of ``port``: ``serial:<number>`` is the USB serial port whose serial number is ``<number>``
    (pyserial's ``list_ports``, looked up now: call it at every open); anything else is returned as it is.

    Raises
    ------
    PortNotFound
        No connected port has that serial number (the board is unplugged, or not yet re-enumerated).
    """
    if not port.startswith(SERIAL_PREFIX):
        return port
    number = port[len(SERIAL_PREFIX):]
    for p in list_ports.comports():
        if p.serial_number == number:
            return str(p.device)
    raise PortNotFound(f"no serial port with USB serial number {number!r} is connected (`rigctl ports` lists them)")


def usb_serial_of(port: str) -> str | None:
    """USB serial number of the port at path ``port`` (symlinks followed), None if it has none or is not listed
    (a pty, a board without a serial number)."""
    try:
        real = os.path.realpath(port)
    except OSError:
        return None
    for p in list_ports.comports():
        if p.serial_number and os.path.realpath(p.device) == real:
            return str(p.serial_number)
    return None


class PortIdentity:
    """Which board a client's port is: its USB serial number, learnt at the first open. Every later open goes to the
    port that has that number now, wherever the board re-enumerated (a replug, a USB reset), so a client of the Mega
    never reopens ``/dev/ttyACM0`` once the Uno holds that name. ``serial:<number>`` names are looked up at every
    open; a port without a serial number (a pty, some clones) is reopened by its path.

    Raises (:meth:`device`) :class:`PortNotFound` when the board is not connected now."""

    def __init__(self, port: str) -> None:
        self.port = port
        self.serial_number = port[len(SERIAL_PREFIX):] if port.startswith(SERIAL_PREFIX) else None
        self._learnt = self.serial_number is not None

    def device(self) -> str:
        """The device path to open now."""
        if not self._learnt:
            self._learnt = True
            self.serial_number = usb_serial_of(self.port)
            return self.port
        if self.serial_number is None:
            return self.port
        return resolve_port(SERIAL_PREFIX + self.serial_number)


#: udev symlink names (under /dev) of the two boards
UDEV_SYMLINKS = {"mega": "rigctl-drum", "uno": "rigctl-taxel"}
_SERIAL_RE = re.compile(r"^[0-9A-Za-z._-]+$")


def udev_rules(boards: list[PortInfo]) -> str:
    """udev rules for the rig's boards: for each board in ``boards`` (``board`` "mega" or "uno" and
    ``serial_number`` known) a rule matching its ``ATTRS{serial}`` (and USB ids when known) that creates
    ``/dev/rigctl-drum`` / ``/dev/rigctl-taxel`` (:data:`UDEV_SYMLINKS`), puts the port in the dialout group and sets
    ``ENV{ID_MM_DEVICE_IGNORE}="1"`` so ModemManager does not probe it (its probe bytes reset the board and reach the
    bootloader). Install as ``/etc/udev/rules.d/99-rigctl.rules``.

    Raises
    ------
    ValueError
        A board without a role or a serial number, two boards in one role, or a serial number with
        characters udev rules cannot carry.
    """
    lines = ["# rigctl: stable names for the rig's boards by USB serial number (`rigctl udev-rules`).",
             "# Install: sudo cp THIS_FILE /etc/udev/rules.d/99-rigctl.rules && sudo udevadm control --reload-rules"
             " && sudo udevadm trigger",
             "# then open /dev/rigctl-drum and /dev/rigctl-taxel (or serial:<number>); add yourself to dialout:",
             "#   sudo usermod -aG dialout $USER   (log in again)"]
    seen: set[str] = set()
    for b in boards:
        if b.board not in UDEV_SYMLINKS:
            raise ValueError(f"{b.device}: not known as the Mega or the Uno (give its role)")
        if b.board in seen:
            raise ValueError(f"two boards in the role {b.board!r}: give each board's serial number")
        seen.add(b.board)
        if not b.serial_number:
            raise ValueError(f"{b.device}: no USB serial number to match (a clone without one cannot get a stable "
                             "name this way; use its /dev/serial/by-path link)")
        if not _SERIAL_RE.match(b.serial_number):
            raise ValueError(f"{b.device}: serial number {b.serial_number!r} has characters a udev rule cannot match")
        lines.append(f"# {b.board}: {b.description or b.device}")
        ids = (f'ATTRS{{idVendor}}=="{b.vid:04x}", ATTRS{{idProduct}}=="{b.pid:04x}", '
               if b.vid is not None and b.pid is not None else "")
        lines.append(f'SUBSYSTEM=="tty", {ids}ATTRS{{serial}}=="{b.serial_number}", '
                     f'SYMLINK+="{UDEV_SYMLINKS[b.board]}", GROUP="dialout", MODE="0660", '
                     'ENV{ID_MM_DEVICE_IGNORE}="1"')
    return "\n".join(lines) + "\n"
