"""Host side of the taxel streamer (Arduino Uno): open, identify, stream, capture trials (pyserial).

``docs/wire-protocol.md`` section 1; the frame parser and sequence accounting are
:class:`rigctl.devices.frames.FrameParser` and :class:`rigctl.devices.frames.SequenceTracker`.

A reader thread owns the port while it is open: it reads whatever is waiting in large chunks (never line by line,
pyserial #216/#440), parses frames, counts sequence gaps and CRC errors, stamps each frame with a host receive time
and fills a :class:`rigctl.devices.ring.RingBuffer` for live consumers and, between :meth:`TaxelStream.begin_capture`
and :meth:`TaxelStream.end_capture`, a capture that keeps every frame for a trial. A vanished port (an unplugged
USB cable) is reported (``stats.connected`` False, the ``on_error`` callback, a log warning) and reopened with
backoff; after the reopen the stream waits for the ready banner and restarts streaming if it was streaming.

After :meth:`TaxelStream.start` the reader waits for the first frame of the new stream: the frame flagged
STREAMING_START, or, if that frame was lost on the wire, the first frame whose sequence number shows the restart (a
number the new stream can have reached since START was sent, and not the continuation of the earlier stream's
sequence); the frames the new stream lost before it are counted as dropped. Frames of the earlier stream still on
the way are discarded and counted (``stats.stale_frames``). If no frame of the new stream arrives within
``start_timeout_s`` (the START byte itself was lost), START is sent again (``stats.start_retries``).
"""

from __future__ import annotations

import collections
import logging
import os
import queue
import re
import select
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import serial

from rigctl.core.sensor import PAPER_SENSOR, LayoutError, SensorLayout
from rigctl.core.shared_clock import (
    attach_port_clock,
    clock_of_port,
    is_port_clock,
    note_found,
    on_its_way_until,
    pause_on,
    release_port_clock,
)
from rigctl.devices import wire
from rigctl.devices.capture_parts import first_flagged, first_with_seq
from rigctl.devices.errors import TaxelLinkLost, TaxelStreamError
from rigctl.devices.frames import FrameParser, SequenceTracker
from rigctl.devices.ports import PortIdentity, lock_exclusive
from rigctl.devices.ring import RingBuffer

log = logging.getLogger(__name__)

_LINE_RE = re.compile(rb"#RIGCTL-UNO[ -~]*\n")
#: a stream whose last frame came longer ago than this has no frames left on the way when START is sent, s
_QUIET_S = 0.5
#: the span of recent chunks whose least-delayed one dates the stream's newest frame, s (a lost link's gap)
ENVELOPE_S = 2.0


#: the STREAMING_START flag bit as a plain int (an IntFlag member costs an enum lookup per use, per chunk)
_STREAMING_START = int(wire.FrameFlag.STREAMING_START)


@dataclass
class StreamStats:
    """Counters of a :class:`TaxelStream` since it was opened."""

    frames: int = 0  #: valid frames received
    dropped: int = 0  #: frames missing from the device's sequence (plus the estimate over a reconnect)
    crc_errors: int = 0  #: corrupt frames rejected: a bad CRC-16, or a valid one over a sample beyond the ADC range
    bytes_skipped: int = 0  #: received bytes that were not part of a valid frame
    frames_per_s: float = 0.0  #: receive rate over the last second (from the last chunk received >= 1 s ago)
    connected: bool = False
    reconnects: int = 0
    stale_frames: int = 0  #: valid frames of an earlier stream received after START was sent (discarded)
    start_retries: int = 0  #: START sent again because the new stream did not begin within ``start_timeout_s``


@dataclass
class Capture:
    """Every frame received between :meth:`TaxelStream.begin_capture` and :meth:`TaxelStream.end_capture`.

    ``samples`` (n, layout.n_channels) uint16 ADC counts, ``seq`` (n,) uint16 device sequence numbers, ``flags`` (n,) uint8
    (:class:`rigctl.devices.wire.FrameFlag`), ``host_time_s`` (n,) float64 host receive times (``time.monotonic``,
    s), ``dropped`` frames missing inside the capture, ``crc_errors`` corrupt frames rejected during it.

    ``dropped`` counts the sequence gaps between frames of the capture and, if the port vanished while the capture
    was running, the frames lost until the restarted stream's first frame (or until :meth:`TaxelStream.end_capture`
    if it had not arrived yet), estimated at the link's rate from the receive times. A restart of streaming (START resets the
    sequence to 0) is not a gap, and the frames lost over a disconnection that happened before
    :meth:`TaxelStream.begin_capture` belong to that reconnect (``StreamStats.dropped``), not to the capture.
    """

    samples: np.ndarray
    seq: np.ndarray
    flags: np.ndarray
    host_time_s: np.ndarray
    dropped: int = 0
    crc_errors: int = 0

    def __len__(self) -> int:
        return len(self.seq)


def _number(text: str) -> int | float:
    value = float(text)
    return int(value) if value.is_integer() else value


def parse_identity(line: str) -> dict[str, Any]:
    """Parse an identity/banner line ``#RIGCTL-UNO [READY] fw=1.0 ch=18 rate_hz=1000 bits=10 baud=1000000
    [layout=3x3x2] [build=1a2b3c4d5e6f]`` (spec section 1.4: ``ch``, ``rate_hz`` and ``bits`` describe the link;
    ``layout`` and ``build`` are optional).

    Returns ``{"firmware": (1, 0), "channels": 18, "ch": 18, "rate_hz": 1000, "bits": 10, "baud": 1000000,
    "layout": "3x3x2" or None, "build": the firmware's build id (``build=``, hex digits of its sources' digest) or
    None, "line": ...}`` (``rate_hz`` an int when whole, else a float).
    Raises :class:`TaxelStreamError` if a field is missing or malformed.
    """
    fields = dict(kv.split("=", 1) for kv in line.split() if "=" in kv)
    try:
        major, minor = fields["fw"].split(".")
        ch = int(fields["ch"])
        rate = _number(fields["rate_hz"])
        if ch < 1 or not rate > 0:
            raise ValueError("ch and rate_hz must be positive")
        return {
            "firmware": (int(major), int(minor)),
            "channels": ch,
            "ch": ch,
            "rate_hz": rate,
            "bits": int(fields["bits"]),
            "baud": int(fields["baud"]),
            "layout": fields.get("layout"),
            "build": fields.get("build"),
            "line": line.strip(),
        }
    except (KeyError, ValueError) as exc:
        raise TaxelStreamError(f"malformed identity line from the taxel streamer: {line.strip()!r}") from exc


def layout_from_banner(banner: dict[str, Any]) -> SensorLayout:
    """The :class:`SensorLayout` a banner / identify reply announces (``SensorLayout.from_identify``).

    Raises :class:`TaxelStreamError` when its ``layout`` disagrees with ``ch`` or is malformed.
    """
    try:
        return SensorLayout.from_identify({k: banner[k] for k in ("ch", "rate_hz", "bits", "layout")
                                           if banner.get(k) is not None})
    except LayoutError as exc:
        raise TaxelStreamError(f"taxel streamer banner {banner.get('line', '')!r}: {exc}") from exc


#: the taxel reader's default period, s: a chunk about every 27 ms (the period plus the wait for a fresh burst), so
#: each frame of the live view (capped at 30/s, ``rigctl gui --max-fps``) finds new data; the host's CPU falls with
#: the wake-ups while the host-time stamps stay as accurate, each chunk being stamped at the arrival of a fresh burst
#: (benchmarks/bench_acquisition.py --recording-only, simulated rig, load 1.0-1.9, the whole acquiring process with
#: its 10 Hz drum poll: 20 ms 2.95-3.03 %, 25 ms 2.72-2.87 %, 30 ms 2.13 % of a core; stamp residual p50 0.22-0.42 ms,
#: p99 1.2-2.4 ms at every period)
READ_PERIOD_S = 0.025
#: the longest wall-clock step of a wait on the stream's clock, s (a simulated rig's clock may move slower than the
#: wall's, or faster)
_WAIT_STEP_S = 0.05
#: a reopen's backoff on a simulated rig's clock lasts at most this many times its length of wall time (pause_on)
PAUSE_WALL_FACTOR = 10.0



def _read_chunk(ser: Any, timeout_s: float) -> bytes:
    """All that is waiting on the port, then the next burst it delivers (block until its first byte, at most
    ``timeout_s``): see :meth:`TaxelStream._reader`. On a POSIX port (pyserial's, with a file descriptor) straight
    from the descriptor (FIONREAD, select, read: five system calls, without pyserial's per-read timeout objects and
    select loops, which were a good part of the reader's CPU at ~40 chunks a second); otherwise through pyserial.
    Raises OSError / SerialException when the port is gone (readable but empty: disconnected), unless it had
    read bytes before (a starved reader's backlog, read as the cable is pulled): those are returned, and the next
    call raises."""
    fd = getattr(ser, "fd", None)
    if not isinstance(fd, int):
        waiting = ser.in_waiting
        data = ser.read(waiting) if waiting else b""
        fresh = ser.read(1)
        if fresh:
            fresh += ser.read(ser.in_waiting)
        return bytes(data + fresh)
    waiting = ser.in_waiting
    data = os.read(fd, waiting) if waiting else b""
    try:
        ready, _, _ = select.select([fd], [], [], timeout_s)
        if ready:
            waiting = ser.in_waiting
            if not waiting:  # what pyserial's read raises: readable with nothing to read is a vanished device
                raise serial.SerialException("device reports readiness to read but returned no data (device "
                                             "disconnected or multiple access on port?)")
            data += os.read(fd, waiting)
    except (serial.SerialException, OSError):
        if data:  # the bytes read before the port vanished were received: handed over, the next call raises
            return data
        raise
    return data


class TaxelStream:
    """Reader of the Uno's taxel stream on a serial port.

    Parameters
    ----------
    port : str
        Serial device path (e.g. ``/dev/rigctl-taxel``, ``/dev/ttyACM0`` or the simulated rig's ``taxel_port``), or
        ``serial:<USB serial number>``. Reopens go to the board first opened, by its USB serial number
        (:class:`rigctl.devices.ports.PortIdentity`): a board that re-enumerates under another name is found again,
        and the two boards cannot swap.
    baudrate : int
        1,000,000 (spec section 1).
    ring_seconds : float
        Length of the live ring buffer, s (at the link's rate, from the banner).
    banner_timeout_s : float
        How long :meth:`open` waits for ``#RIGCTL-UNO READY`` after opening (the Uno resets on open).
    on_error : callable(TaxelLinkLost) or None
        Called from the reader thread when the port vanishes or fails, with a
        :class:`~rigctl.devices.errors.TaxelLinkLost` (the OS or pyserial error as its ``__cause__``).
    reconnect : bool
        Reopen a vanished port automatically (backoff 0.1 s doubling to 2 s).
    read_timeout_s : float
        The reader's period, s (default :data:`READ_PERIOD_S`): frames reach the ring at most this late.
    start_timeout_s : float
        After :meth:`start`, how long to wait for the first frame of the new stream before sending START again, s.
    clock : object or None
        The clock of the receive stamps, timeouts and waits (``now() -> s``): the host's monotonic clock (None), or
        a simulated rig's shared clock (:class:`rigctl.core.shared_clock.SharedClock`: the drum client's, so frames
        and drum statuses share one time; every read and write is then a sign of the host's life).
    """

    def __init__(self, port: str, *, baudrate: int = wire.TAXEL_BAUD, ring_seconds: float = 30.0,
                 banner_timeout_s: float = 3.0, on_error: Any = None, reconnect: bool = True,
                 read_timeout_s: float = READ_PERIOD_S,
                 start_timeout_s: float = 1.0, clock: Any = None) -> None:
        self.port = port
        # a simulated rig's port in this process is on that rig's clock (rigctl.core.shared_clock)
        self.clock = clock if clock is not None else clock_of_port(port)
        # a simulated rig of another process: this stream holds its clock file while open (rigctl.core.shared_clock.attach_port_clock)
        self._holds_port_clock = clock is None and is_port_clock(self.clock)
        self._identity = PortIdentity(port)  # reopens go to this board, by USB serial number
        self.baudrate = baudrate
        self.banner_timeout_s = banner_timeout_s
        self.on_error = on_error
        self.reconnect = reconnect
        self.read_timeout_s = read_timeout_s
        self.start_timeout_s = start_timeout_s
        self.ring_seconds = ring_seconds
        self._layout: SensorLayout = PAPER_SENSOR
        self.ring = RingBuffer(max(1, int(ring_seconds * PAPER_SENSOR.sample_rate_hz)), PAPER_SENSOR.n_channels)
        self.banner: dict[str, Any] | None = None
        self.last_error: Exception | None = None
        self._serial: serial.Serial | None = None
        self._parser = FrameParser()
        self._tracker = SequenceTracker()
        self._lock = threading.Lock()  # guards counters, capture and state shared with the reader thread
        self._write_lock = threading.Lock()
        self._lines: queue.Queue[str] = queue.Queue()
        self._text = b""
        self._streaming = False
        self._await_start = False
        self._t_start_sent = 0.0  # when START was last sent (time.monotonic)
        self._stale_possible = False  # frames of an earlier stream may still be on their way after START
        self._old_seq: int | None = None  # while awaiting the new stream: the earlier stream's last sequence number
        self._old_time = 0.0  # ... and when it was received
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stats = StreamStats()
        self._rate: collections.deque[Any] = collections.deque(maxlen=256)
        self._capture: list[Any] | None = None
        self._capture_crc_base = 0
        self._capture_dropped = 0
        self._capture_count = 0
        self._loss_in_capture = False  # the pending reconnect gap happened while the running capture was open
        self._capture_event = threading.Condition(self._lock)
        self._last_frame_time: float | None = None
        self._gap_pending = False
        #: the stream's chunks of the last ENVELOPE_S: (host time, running frame count) of each chunk's newest frame
        self._envelope: collections.deque[tuple[float, int]] = collections.deque()
        self._envelope_seq = 0  # the sequence number of the newest frame in it

    def _now(self) -> float:
        """The stream's clock, s: :attr:`clock`'s, else the host's monotonic clock."""
        return float(self.clock.now()) if self.clock is not None else time.monotonic()

    def _touch(self) -> None:
        """A read or a write: a sign of the host's life on a shared clock."""
        touch = getattr(self.clock, "touch", None)
        if touch is not None:
            touch()

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> "TaxelStream":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ layout
    @property
    def layout(self) -> SensorLayout:
        """The sensor the link carries, from the board's banner (``ch``, ``rate_hz``, ``bits``, ``layout``); the
        paper's 3x3x2 at 1 kHz before :meth:`open`. Frames are ``7 + 2 * layout.n_channels`` bytes."""
        return self._layout

    def _apply_layout(self, banner: dict[str, Any]) -> None:
        layout = layout_from_banner(banner)
        if layout == self._layout and self._parser.n_channels == layout.n_channels \
                and self._parser.adc_max == layout.adc_max:
            return
        if self._thread is not None and layout.n_channels != self._layout.n_channels:
            log.warning("taxel streamer on %s now reports %d channels (was %d)", self.port, layout.n_channels,
                        self._layout.n_channels)
        self._layout = layout
        self._parser = FrameParser(n_channels=layout.n_channels, adc_max=layout.adc_max)
        capacity = max(1, int(self.ring_seconds * layout.sample_rate_hz))
        if self.ring.n_channels != layout.n_channels or self.ring.capacity != capacity:
            self.ring = RingBuffer(capacity, layout.n_channels)

    # ------------------------------------------------------------------ open / close
    def open(self) -> dict[str, Any]:
        """Open the port, wait for the ready banner, start the reader thread. Returns the parsed banner.

        Raises
        ------
        TaxelStreamError
            The port cannot be opened, or no ``#RIGCTL-UNO READY`` line arrived within ``banner_timeout_s``.
        """
        if self._thread is not None:
            return self.banner or {}
        if not self._holds_port_clock and is_port_clock(self.clock):  # reopened after close()
            self._holds_port_clock = attach_port_clock(self.port) is self.clock
        # compile/load the frame parser's numba kernel now, not on the reader's first chunk: that first call takes
        # 1-4 s (longer on a loaded machine, a clean clone compiles) and would hold the stream back behind real time
        FrameParser().feed(bytes(wire.frame_size(wire.N_TAXELS)))
        try:
            ser = self._open_serial()
            self.banner = self._wait_banner(ser)
        except (serial.SerialException, OSError) as exc:  # OSError: ports.PortNotFound (serial:<number> absent)
            raise TaxelStreamError(f"cannot open the taxel streamer port {self.port}: {exc}") from exc
        try:
            self._apply_layout(self.banner)
        except TaxelStreamError:
            ser.close()
            raise
        self._serial = ser
        self._stats.connected = True
        self._stop.clear()
        self._thread = threading.Thread(target=self._reader, name="taxel-reader", daemon=True)
        self._thread.start()
        return self.banner

    def _open_serial(self) -> serial.Serial:
        # exclusive: a second program can neither open the port nor, by opening it, reset the board under a stream
        ser = serial.Serial(self._identity.device(), self.baudrate, timeout=self.read_timeout_s, write_timeout=1.0, exclusive=True)
        lock_exclusive(ser)
        return ser

    def _wait_banner(self, ser: serial.Serial) -> dict[str, Any]:
        deadline, flight_end, buf, last = self._now() + self.banner_timeout_s, None, b"", False
        note_found(self.clock, self.port)  # the port opened: what the board sends from now on is new to this host
        while not last:  # past the deadline: on while a simulated board says its banner is in the kernel's hands
            last = self._now() >= deadline and not (flight_end := on_its_way_until(self.clock, self.port, flight_end))
            chunk = ser.read(ser.in_waiting if last else max(1, ser.in_waiting))  # (last: what is there now)
            if chunk:
                note_found(self.clock, self.port)
            buf += chunk
            idx = buf.find(wire.UNO_BANNER_PREFIX.encode())
            if idx >= 0:
                end = buf.find(b"\n", idx)
                if end >= 0:
                    return parse_identity(buf[idx:end].decode("ascii", "replace"))
            buf = buf[-256:]
        ser.close()
        raise TaxelStreamError(
            f"no ready banner ({wire.UNO_BANNER_PREFIX!r}) from {self.port} within {self.banner_timeout_s:g} s: "
            "is this the taxel streamer (Uno) running rigctl firmware at 1,000,000 baud?"
        )

    def close(self) -> None:
        """Stop streaming (best effort), stop the reader thread and close the port."""
        if self._thread is not None:
            if self._streaming:
                try:
                    self._write(wire.UnoCommand.STOP.value)
                except (serial.SerialException, OSError, TaxelStreamError):
                    pass
            self._stop.set()
            self._thread.join(timeout=3)
            self._thread = None
        self._streaming = False
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
            self._serial = None
        self._stats.connected = False
        if self._holds_port_clock:
            self._holds_port_clock = False
            release_port_clock(self.clock)

    # ------------------------------------------------------------------ commands
    def _write(self, data: bytes) -> None:
        with self._write_lock:
            ser = self._serial
            if ser is None or not self._stats.connected:
                raise TaxelStreamError(f"taxel streamer on {self.port} is not connected")
            self._touch()
            note = getattr(self.clock, "note_write", None)
            if note is not None:  # a simulated rig's board waits for bytes the kernel still holds
                note(self.port, len(data))
            ser.write(data)

    def identify(self, timeout_s: float = 1.0) -> dict[str, Any]:
        """Ask the Uno who it is (stops streaming first, as the spec's IDENTIFY does).

        Returns ``{"firmware": (major, minor), "channels", "ch", "rate_hz", "bits", "baud", "layout", "line"}``.
        Raises :class:`TaxelStreamError` on no answer within ``timeout_s``.
        """
        self._streaming = False
        while not self._lines.empty():
            self._lines.get_nowait()
        self._write(wire.UnoCommand.IDENTIFY.value)
        deadline, flight_end = self._now() + timeout_s, None
        while True:
            left = deadline - self._now()
            if left <= 0:
                if not (flight_end := on_its_way_until(self.clock, self.port, flight_end)):
                    raise TaxelStreamError(f"no identity reply from the taxel streamer on {self.port} in {timeout_s:g} s")
                left = 0.005  # (the reply is on its way)
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                continue
            if not line.startswith(wire.UNO_BANNER_PREFIX):
                return parse_identity(line)

    def start(self) -> None:
        """Start streaming (the device resets its sequence counter to 0).

        The frames of the new stream are counted from its first frame (sequence number 0, flagged STREAMING_START);
        if frames at its start are lost on the wire the stream is still recognised (by its restarted sequence
        numbers) and the lost ones are counted as dropped. Raises :class:`TaxelStreamError` if the port is not
        connected."""
        self._start(board_reset=False)

    def _start(self, *, board_reset: bool) -> None:
        """Send START; ``board_reset``: the board has just booted (a reopened port), no earlier frames can follow."""
        with self._lock:
            now = self._now()
            recent = self._last_frame_time is not None and now - self._last_frame_time < _QUIET_S
            self._stale_possible = not board_reset and (self._streaming or recent)
            self._old_seq, self._old_time = self._tracker.last_seq, self._last_frame_time or now
            self._streaming = True
            self._await_start = True
            self._t_start_sent = now
        self._write(wire.UnoCommand.START.value)

    def _retry_start(self) -> None:
        """Send START again: the new stream has not begun within ``start_timeout_s`` (the START byte was lost)."""
        with self._lock:
            if not (self._streaming and self._await_start and self._stats.connected):
                return
            self._t_start_sent = self._now()
            self._stats.start_retries += 1
        log.warning("taxel streamer on %s: no frame of the new stream %.1f s after START; sending START again",
                    self.port, self.start_timeout_s)
        try:
            self._write(wire.UnoCommand.START.value)
        except (serial.SerialException, OSError, TaxelStreamError) as exc:
            log.info("START retry failed: %s", exc)  # a vanished port is noticed (and reopened) by the reader

    def stop(self) -> None:
        """Stop streaming (frames already on the wire are still parsed)."""
        self._streaming = False
        self._write(wire.UnoCommand.STOP.value)

    @property
    def streaming(self) -> bool:
        return self._streaming

    # ------------------------------------------------------------------ captures
    def begin_capture(self) -> None:
        """Start keeping every received frame (for one trial) until :meth:`end_capture`."""
        with self._lock:
            self._capture = []
            self._capture_count = 0
            self._capture_dropped = 0
            self._capture_crc_base = self._stats.crc_errors
            # a disconnection that is already under way (or whose restarted stream has not delivered its first
            # frame yet) is not inside this capture: its lost frames belong to the reconnect
            self._loss_in_capture = False

    def wait_capture(self, n_frames: int, timeout_s: float) -> bool:
        """Block until the running capture holds at least ``n_frames`` frames; False on timeout."""
        deadline = self._now() + timeout_s
        with self._capture_event:
            while self._capture is not None and self._capture_count < n_frames:
                left = deadline - self._now()
                if left <= 0:
                    return False
                self._capture_event.wait(min(left, _WAIT_STEP_S))
            return self._capture is not None

    def capture_flag_index(self, mask: int) -> int | None:
        """Position, in the running capture, of the first frame whose flags have a bit of ``mask`` (e.g.
        ``FrameFlag.SYNC_IN``, the index pulse); None if none has arrived yet or no capture runs."""
        with self._lock:
            parts = list(self._capture or ())
        return first_flagged(parts, mask)

    def capture_seq_index(self, seq: int) -> int | None:
        """Position, in the running capture, of the first frame of wire sequence number ``seq`` (mod 65536); None if
        it has not arrived yet or no capture runs."""
        with self._lock:
            parts = list(self._capture or ())
        return first_with_seq(parts, seq)

    def end_capture(self) -> Capture:
        """Stop the capture; return every frame received since :meth:`begin_capture` (a :class:`Capture`).

        Raises :class:`TaxelStreamError` if no capture is running.
        """
        with self._lock:
            parts = self._capture
            if parts is None:
                raise TaxelStreamError("end_capture() without begin_capture()")
            self._capture = None
            dropped = self._capture_dropped
            if self._gap_pending and self._loss_in_capture and self._last_frame_time is not None:
                # the port vanished during the capture and the stream has not come back yet: the frames due
                # until now are lost
                dropped += max(0, int((self._now() - self._last_sent_s()) * self._layout.sample_rate_hz))
            self._loss_in_capture = False
            crc = self._stats.crc_errors - self._capture_crc_base
        if parts:
            samples, seq, flags, t = (np.concatenate([p[i] for p in parts]) for i in range(4))
        else:
            samples = np.zeros((0, self._layout.n_channels), np.uint16)
            seq, flags, t = np.zeros(0, np.uint16), np.zeros(0, np.uint8), np.zeros(0, np.float64)
        return Capture(samples, seq, flags, t, dropped=int(dropped), crc_errors=int(crc))

    # ------------------------------------------------------------------ stats
    @property
    def stats(self) -> StreamStats:
        """A snapshot of the counters (:class:`StreamStats`)."""
        with self._lock:
            s = StreamStats(**vars(self._stats))
            if len(self._rate) >= 2:
                (t0, n0), (t1, n1) = self._rate[0], self._rate[-1]
                now = self._now()
                # the window reaches back to the last chunk received a second ago or more, so it spans a second or
                # more: begun at the first chunk inside the last second, a window after a stall of the reader could
                # hold just two chunks of the backlog read ms apart (15,000 frames/s read from a 1 kHz stream)
                for t, n in self._rate:
                    if now - t < 1.0:
                        break
                    t0, n0 = t, n
                s.frames_per_s = (n1 - n0) / (t1 - t0) if t1 > t0 else 0.0
                if now - t1 > 0.5:
                    s.frames_per_s = 0.0
        return s

    # ------------------------------------------------------------------ reader thread
    def _reader(self) -> None:
        while not self._stop.is_set():
            ser = self._serial
            try:
                # a port closed meanwhile (None) raises AttributeError, handled as a lost link below
                # all that is waiting, then the next burst the link delivers (block until its first byte, at most
                # read_timeout_s): the chunk is stamped as that burst arrives, so its newest frame's host time is
                # fresh. Stamped at the reader's wake-up instead, every chunk's frames carry the time they sat in the
                # buffer (up to the sender's burst interval: ms, more on a loaded machine), and the least-delayed
                # frames host_rate_hz measures from would vary by as much. Then the next chunk gathers for
                # read_timeout_s: two wake-ups per chunk, not one per burst (pyserial's read(n) wakes on every burst
                # until it has n bytes: ~1000 wake-ups/s at 1 kHz)
                data = _read_chunk(ser, self.read_timeout_s)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if self._stop.is_set():
                    break
                self._port_lost(exc)
                if not self._reopen():
                    break
                continue
            if data:
                self._touch()
                note_found(self.clock, self.port)
                self._handle(data, self._now())
            if self._await_start and self._streaming and \
                    self._now() - self._t_start_sent > self.start_timeout_s:
                self._retry_start()
            # a chunk of more than two read periods of frames: the reader is behind (a stall on a loaded host);
            # read on at once, or the backlog drains at one tty buffer (4 KiB) per period, barely faster than the
            # stream, and delays every frame for seconds
            behind = len(data) > 2 * self.read_timeout_s * self._layout.sample_rate_hz * \
                wire.frame_size(self._layout.n_channels)
            if data and not behind:
                self._stop.wait(self.read_timeout_s)

    def _handle(self, data: bytes, t_rx: float) -> None:
        if not self._streaming or self._await_start:
            self._scan_text(data)
        frames = self._parser.feed(data)
        ps = self._parser.stats
        with self._lock:
            st = self._stats
            st.crc_errors = ps.crc_errors + ps.out_of_range
            st.bytes_skipped = ps.bytes_skipped
            n = len(frames)
            if n == 0:
                return
            seq, flags, samples = frames.seq, frames.flags, frames.samples
            lost_at_start = 0
            new_stream = self._gap_pending or self._await_start or not self._envelope
            if self._await_start:
                k = self._new_stream_start(seq, flags, t_rx)
                st.stale_frames += n if k is None else k
                if k is None:
                    return  # frames of an earlier stream still on their way
                # the new stream's frames before this one (sequence numbers 0 .. seq[k] - 1) were lost on the wire
                lost_at_start = 0 if flags[k] & _STREAMING_START else int(seq[k])
                seq, flags, samples = seq[k:], flags[k:], samples[k:]
                self._await_start = False
                self._tracker.reset()
            starts = np.flatnonzero(flags & _STREAMING_START)
            n = len(seq)
            # receive time of the chunk, spread back over its frames at the frame period, never earlier
            # than the previous frame: host times increase strictly
            rate = self._layout.sample_rate_hz
            period = 1.0 / rate
            first = t_rx - (n - 1) * period
            if self._last_frame_time is not None and not self._gap_pending and first <= self._last_frame_time:
                first = self._last_frame_time + 1e-6
                period = (t_rx - first) / (n - 1) if n > 1 else period
            host_t = first + np.arange(n) * period
            if n == 1:
                host_t[0] = max(t_rx, first)
            capturing = self._capture is not None
            if self._gap_pending and self._last_frame_time is not None:
                # frames lost while the port was gone: estimated from the time gap at the link's rate. They count in
                # a capture only if it was running when the port vanished
                lost = max(0, int(round((host_t[0] - self._last_sent_s()) * rate)) - 1)
                lost_at_start = 0  # lost frames at the restarted stream's start lie inside that time gap
                st.dropped += lost
                if capturing and self._loss_in_capture:
                    self._capture_dropped += lost
            self._gap_pending = False
            self._loss_in_capture = False
            st.dropped += lost_at_start
            if capturing:
                self._capture_dropped += lost_at_start
            # a STREAMING_START frame restarts the device's sequence at 0: not a gap
            bounds = [0, *[int(k) for k in starts if k > 0], n]
            for lo, hi in zip(bounds[:-1], bounds[1:]):
                if flags[lo] & _STREAMING_START:
                    self._tracker.reset()
                gaps = self._tracker.update(seq[lo:hi])
                st.dropped += gaps
                if capturing:
                    self._capture_dropped += gaps
            self._last_frame_time = float(host_t[-1])
            self._note_envelope(seq, new_stream or bool(starts.size), float(host_t[-1]))
            st.frames += n
            self._rate.append((t_rx, st.frames))
            if self._capture is not None:
                self._capture.append((samples, seq, flags, host_t))
                self._capture_count += n
                self._capture_event.notify_all()
        self.ring.write(samples, seq, flags, host_t)

    def _note_envelope(self, seq: np.ndarray, restart: bool, t: float) -> None:
        """Add a chunk (``seq`` as received, its newest frame stamped ``t``) to the envelope; ``restart``: a new
        stream (its counts start again). Called under the lock."""
        if restart:
            self._envelope.clear()
            count = 0
        else:
            count = self._envelope[-1][1] + ((int(seq[-1]) - self._envelope_seq) & 0xFFFF)
        self._envelope.append((t, count))
        self._envelope_seq = int(seq[-1])
        while self._envelope[0][0] < t - ENVELOPE_S:
            self._envelope.popleft()

    def _last_sent_s(self) -> float:
        """When the board sent the newest frame received (host clock, s): its stamp less the least delay of the
        stream's chunks over the last :data:`ENVELOPE_S` (the lower envelope, at the nominal rate). A stamp is the
        time the reader read a chunk: on a loaded host it is late by however long the reader (or a simulated board
        behind its clock) was starved, and the frames lost across a reconnect, counted from the time gap to the
        restarted stream's first frame, would be under-counted by as much. Called under the lock."""
        if not self._envelope:
            return float(self._last_frame_time or 0.0)
        period = 1.0 / self._layout.sample_rate_hz
        count_last = self._envelope[-1][1]
        return min(t + (count_last - c) * period for t, c in self._envelope)

    def _new_stream_start(self, seq: np.ndarray, flags: np.ndarray, t_rx: float) -> int | None:
        """Index of the first frame of the stream START began, or None if all are frames of an earlier stream.

        The frame flagged STREAMING_START; else the first frame whose sequence number the new stream can have reached
        since START was sent (at the link's rate, with slack) and that does not continue the earlier stream's
        sequence (only possible while frames of that stream may still be on their way). Called under the lock."""
        rate = self._layout.sample_rate_hz
        slack = 2 + 0.02 * rate
        bound = (t_rx - self._t_start_sent) * rate + slack
        for i in range(len(seq)):
            if flags[i] & _STREAMING_START:
                return i
            s = int(seq[i])
            old = self._old_seq
            if self._stale_possible and old is not None:
                ahead = (s - old) & 0xFFFF
                if 0 < ahead <= (t_rx - self._old_time) * rate + slack:
                    self._old_seq, self._old_time = s, t_rx  # the earlier stream goes on
                    continue
            if s <= bound:
                return i
        return None

    def _scan_text(self, data: bytes) -> None:
        self._text = (self._text + data)[-4096:]
        while True:
            m = _LINE_RE.search(self._text)
            if not m:
                break
            self._lines.put(m.group(0).decode("ascii", "replace").strip())
            self._text = self._text[m.end():]

    def _port_lost(self, cause: Exception) -> None:
        exc = cause
        if not isinstance(cause, TaxelLinkLost):
            exc = TaxelLinkLost(f"taxel streamer on {self.port} vanished: {cause}")
            exc.__cause__ = cause
        self.last_error = exc
        with self._lock:
            self._stats.connected = False
            if not self._gap_pending:  # a failed restart after a reopen is still the same disconnection
                self._loss_in_capture = self._capture is not None
            self._gap_pending = True
            self._rate.clear()  # the receive rate restarts with the reconnected stream
        log.warning("%s", exc)
        if self.on_error is not None:
            try:
                self.on_error(exc)
            except Exception:  # a callback must not kill the reader
                log.exception("on_error callback failed")
        try:
            self._serial.close()  # type: ignore[union-attr]  # None: nothing to close (handled)
        except Exception:
            pass

    def _reopen(self) -> bool:
        """Reopen the port with backoff until it works or :meth:`close` is called."""
        if not self.reconnect:
            return False
        delay = 0.1
        while not pause_on(self.clock, self._stop, delay, wall_factor=PAUSE_WALL_FACTOR):  # on the rig's time
            delay = min(delay * 2, 2.0)
            try:
                ser = self._open_serial()
            except (serial.SerialException, OSError):
                continue
            try:
                self.banner = self._wait_banner(ser)
            except (TaxelStreamError, serial.SerialException, OSError) as exc:
                log.info("reopened %s but no banner yet: %s", self.port, exc)
                try:
                    ser.close()
                except Exception:
                    pass
                continue
            try:
                self._apply_layout(self.banner)
            except TaxelStreamError as exc:
                log.warning("%s", exc)
                try:
                    ser.close()
                except Exception:
                    pass
                continue
            with self._write_lock:
                self._serial = ser
            self._parser.reset()
            with self._lock:
                self._stats.connected = True
                self._stats.reconnects += 1
            log.warning("taxel streamer on %s reconnected", self.port)
            if self._streaming:
                try:
                    self._start(board_reset=True)
                except (serial.SerialException, OSError, TaxelStreamError) as exc:
                    self._port_lost(exc)
                    continue
            return True
        return False
