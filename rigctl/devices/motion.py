"""A serial motion board (an IMU or an encoder on the finger's carriage) as the handheld rig's motion source
(``--motion serial:PORT``): its frame, the parser and the reader.

The frame is specified in docs/guides/handheld.md ("A serial motion board"): 18 bytes, little-endian, sync ``A5 4D``,
seq u8, flags u8 (bit 0 position valid, bit 1 velocity valid), ``t_us`` u32 (the board's clock), ``position_um`` i32
(along the plate), ``velocity_um_s`` i32, CRC-16/MODBUS of bytes 2-15 (:func:`pack_motion_frame`; the test of the
guide's table: ``tests/acquisition/test_handheld_serial.py``).

:class:`MotionParser` finds frames in a byte stream (a bad CRC: the sync searched again one byte on, counted in
``crc_errors``). :class:`SerialMotion` reads a port in a thread and puts each frame on the host clock with the clock
fit of the taxel board (:class:`rigctl.core.clocksync.DeviceClockFit`: the lower envelope of the receive times
against the board's own timestamps in 1 ms ticks, each frame's microseconds kept; :class:`MotionTrack`), so the
motion and the taxel frames share one clock. A board that sends velocity only (an IMU) gets its position integrated
from the last valid position, 0 at the board's stream start (its frame seq 0: the finger at the plate's start when the
board starts; a board reset by the port's opening, as DTR resets an Arduino, starts there). A velocity-only board
whose first frame rigctl receives is not its stream start (it was streaming before rigctl opened its port: the
finger may be anywhere) is refused at open, the user told to start rigctl first (:data:`STREAM_START_SEQ`).
"""

from __future__ import annotations

import struct
import threading
import time
from typing import Any, NamedTuple

import numpy as np

from rigctl.core.clocksync import DeviceClockFit
from rigctl.devices.wire import crc16

__all__ = ["MOTION_SYNC", "MOTION_FRAME_SIZE", "MOTION_BAUD", "POSITION_VALID", "VELOCITY_VALID", "MotionFrame",
           "MotionParser", "MotionTrack", "SerialMotion", "STREAM_START_SEQ", "pack_motion_frame"]

MOTION_SYNC = b"\xa5\x4d"
MOTION_FRAME_SIZE = 18
MOTION_BAUD = 115_200
POSITION_VALID = 0x01
VELOCITY_VALID = 0x02
#: the seq of a board's first frame after it starts (or is reset): a velocity-only board's position is integrated
#: from that frame, so rigctl must receive it
STREAM_START_SEQ = 0
_BODY = struct.Struct("<BBIii")  # seq, flags, t_us, position_um, velocity_um_s
#: the clock fit's tick: the board's clock in milliseconds (its 16-bit count wraps every 65 s: a reader held up for
#: less than half that keeps the count), each frame's fraction of a tick kept beside it
_TICK_US = 1000


class MotionFrame(NamedTuple):
    """One frame (NaN for a field its flag says is invalid)."""

    seq: int
    flags: int
    t_us: int
    position_mm: float
    velocity_mm_s: float


def pack_motion_frame(seq: int, t_us: int, position_mm: float | None = None,
                      velocity_mm_s: float | None = None) -> bytes:
    """The 18 bytes of one frame (module docstring); None leaves a field invalid. Raises struct.error for a value
    out of its field's range."""
    flags = (POSITION_VALID if position_mm is not None else 0) | (VELOCITY_VALID if velocity_mm_s is not None else 0)
    body = _BODY.pack(seq & 0xFF, flags, int(t_us) & 0xFFFFFFFF,
                      int(round((position_mm or 0.0) * 1000.0)), int(round((velocity_mm_s or 0.0) * 1000.0)))
    return MOTION_SYNC + body + struct.pack("<H", crc16(body))


class MotionParser:
    """Frames out of a byte stream: :meth:`feed` returns the complete, CRC-checked frames; counts ``crc_errors``,
    ``lost_frames`` (seq gaps) and ``frames``."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.crc_errors = 0
        self.lost_frames = 0
        self.frames = 0
        self._last_seq: int | None = None

    def feed(self, data: bytes) -> list[MotionFrame]:
        buf = self._buf
        buf += data
        out: list[MotionFrame] = []
        while True:
            i = buf.find(MOTION_SYNC)
            if i < 0:
                del buf[:max(0, len(buf) - 1)]  # keep a trailing A5
                return out
            if len(buf) - i < MOTION_FRAME_SIZE:
                del buf[:i]
                return out
            body = bytes(buf[i + 2:i + 16])
            if struct.unpack_from("<H", buf, i + 16)[0] != crc16(body):
                self.crc_errors += 1
                del buf[:i + 1]
                continue
            del buf[:i + MOTION_FRAME_SIZE]
            seq, flags, t_us, pos_um, vel_um_s = _BODY.unpack(body)
            if self._last_seq is not None:
                self.lost_frames += (seq - self._last_seq - 1) & 0xFF
            self._last_seq = seq
            self.frames += 1
            out.append(MotionFrame(seq, flags, t_us, pos_um / 1000.0 if flags & POSITION_VALID else np.nan,
                                   vel_um_s / 1000.0 if flags & VELOCITY_VALID else np.nan))


class MotionTrack:
    """A motion board's frames on the host clock (module docstring): :meth:`add` the frames of each read with its
    receive time, :meth:`since` the samples; thread-safe. The board's timestamps are unwrapped (u32 microseconds) and
    fitted against the receive times (:attr:`fit`, 1 ms ticks); a velocity-only frame's position is integrated."""

    def __init__(self) -> None:
        self.fit = DeviceClockFit(1e6 / _TICK_US)
        self._lock = threading.Lock()
        self._rows: list[np.ndarray] = []  # (k, 4): fit count (ticks), receive time, position, velocity
        self._running_us: int | None = None
        self._anchor: tuple[float, float] | None = None  # (count, receive time) of the least-delayed frame
        self._last_t_us = 0
        self._pos = 0.0

    def add(self, frames: list[MotionFrame], receive_s: float) -> None:
        """The frames of one read, received at ``receive_s`` (host clock, s)."""
        if not frames:
            return
        rows = np.empty((len(frames), 4))
        for k, (_, _, t_us, pos, vel) in enumerate(frames):
            if self._running_us is None:  # the first frame: a velocity-only board's position starts at 0 here
                self._running_us = 0
                if np.isnan(pos) and not np.isnan(vel):
                    pos = self._pos
            else:
                dt_us = (t_us - self._last_t_us) & 0xFFFFFFFF
                self._running_us += dt_us
                if np.isnan(pos) and not np.isnan(vel):  # velocity only: integrated from the last position
                    pos = self._pos + vel * dt_us * 1e-6
            self._last_t_us = t_us
            if not np.isnan(pos):
                self._pos = pos
            rows[k] = (self._running_us / _TICK_US, receive_s, pos, vel)
        rate = self.fit.nominal_rate_hz
        with self._lock:  # the fit counts whole ticks; each frame keeps its fraction of one
            ticks = np.floor(rows[:, 0])
            rows[:, 0] = self.fit.add((ticks.astype(np.int64) & 0xFFFF).astype(np.uint16), rows[:, 1]) + (
                rows[:, 0] - ticks)
            lag = rows[:, 1] - rows[:, 0] / rate
            i = int(np.argmin(lag))
            if self._anchor is None or lag[i] < self._anchor[1] - self._anchor[0] / rate:
                self._anchor = (float(rows[i, 0]), float(rows[i, 1]))
            self._rows.append(rows)

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Samples with host time >= ``t0``: times (k,) s (the clock fit's; before it has two seconds of frames,
        the board's timestamps from its least-delayed frame so far) and (k, 2) position along the plate (mm) and
        velocity (mm/s, NaN when not sent)."""
        with self._lock:
            rows = np.concatenate(self._rows) if self._rows else np.zeros((0, 4))
            m = self.fit.mapping()
            if m is not None:
                t = m.host_time(rows[:, 0])
            elif self._anchor is not None:  # the board's clock at its nominal rate from the least-delayed frame
                t = self._anchor[1] + (rows[:, 0] - self._anchor[0]) / self.fit.nominal_rate_hz
            else:
                t = np.zeros(0)
            self._rows = [rows[t >= t.max() - 60.0]] if t.size else []  # the last minute is enough for any scan
        keep = t >= t0
        return t[keep], rows[keep][:, 2:4]


class SerialMotion:
    """A serial motion board read in a thread (module docstring): a tracker for
    :class:`rigctl.simulation.handheld_lsl.TrackedFingerScans` whose :meth:`since` gives the position along the
    plate and the velocity (two columns, :meth:`MotionTrack.since`).

    Parameters
    ----------
    port : the serial port (a path; ``rigctl ports`` lists them).
    baudrate : the board's line speed (:data:`MOTION_BAUD`).
    open_timeout_s : how long to wait for the first valid frame.

    Raises
    ------
    rigctl.core.handheld.ScanError
        The port cannot be opened, or no valid frame arrives within ``open_timeout_s``.
    """

    channels: tuple[int, ...] = (0,)  # one position channel: along the plate

    def __init__(self, port: str, *, baudrate: int = MOTION_BAUD, open_timeout_s: float = 5.0) -> None:
        import serial

        from rigctl.core.handheld import ScanError

        self.name = str(port)
        try:
            self._serial = serial.Serial(self.name, baudrate, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ScanError(f"cannot open the motion board's port {self.name}: {exc}") from None
        self.parser = MotionParser()
        self.track = MotionTrack()
        self._halt = threading.Event()
        self._got = threading.Event()
        self.error: str | None = None
        #: the first valid frame received (its seq: the board's stream start or not)
        self.first_frame: MotionFrame | None = None
        self._thread = threading.Thread(target=self._read, name="motion-board", daemon=True)
        self._thread.start()
        if not self._got.wait(open_timeout_s):
            self.close()
            raise ScanError(f"no valid frame from the motion board on {self.name} within {open_timeout_s:g} s "
                            f"({self.parser.crc_errors} CRC errors): check the port and the baud rate "
                            f"({baudrate})")
        first = self.first_frame
        if first is not None and not first.flags & POSITION_VALID and first.seq != STREAM_START_SEQ:
            self.close()
            raise ScanError(f"the motion board on {self.name} sends velocity only (an IMU) and was streaming before "
                            f"rigctl opened its port (its first frame here is seq {first.seq}, not its stream start "
                            f"{STREAM_START_SEQ}): its position is integrated from the stream's start, which rigctl "
                            "missed; start rigctl first, then (re)start the board with the finger at the plate's start")

    def _read(self) -> None:
        while not self._halt.is_set():
            try:
                data = self._serial.read(max(1, self._serial.in_waiting))
            except Exception as exc:  # noqa: BLE001 - a lost port: kept for link_problem, the scan times out
                self.error = f"the motion board's port {self.name} failed: {exc}"
                return
            t = time.monotonic()
            frames = self.parser.feed(data) if data else []
            if frames:
                if self.first_frame is None:
                    self.first_frame = frames[0]
                self.track.add(frames, t)
                self._got.set()

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`MotionTrack.since`."""
        return self.track.since(t0)

    def counters(self) -> dict[str, int]:
        """The link's counts so far: ``motion_frames``, ``motion_crc_errors``, ``motion_lost_frames``."""
        p = self.parser
        return {"motion_frames": p.frames, "motion_crc_errors": p.crc_errors, "motion_lost_frames": p.lost_frames}

    def link_problem(self) -> str | None:
        """Why the board is not usable now (its port failed), or None."""
        return self.error

    def describe(self) -> dict[str, Any]:
        m = self.track.fit.mapping()
        return {"tracker": "serial motion board", "port": self.name, "frames": self.parser.frames,
                "crc_errors": self.parser.crc_errors, "lost_frames": self.parser.lost_frames,
                "clock": None if m is None else m.to_dict()}

    def close(self) -> None:
        self._halt.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2)
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - closing a lost port
            pass
