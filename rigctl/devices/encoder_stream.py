"""The host's side of the Uno encoder image's link (docs/wire-protocol.md 1.5): its commands (CALIBRATE, SPEED,
FINISH with their CRC-16) and a parser that splits the byte stream into taxel frames, spike frames and counts frames.

The encoder image streams the taxel frames of 1.1 and, beside them, a spike frame every 10 samples (the 9 top-layer
taxels' spike masks of the integer SA kernel, :mod:`rigctl.encoding.fixed_sa` bit for bit) and, after FINISH, one
counts frame (the 20 scaled-time windows' spike counts of each taxel, with the samples encoded, the windows held and
the samples dropped). Source: the firmware ``arduino/uno_taxel/uno_taxel.cpp`` built with ``-DUNO_SA_ENCODER``.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from rigctl.core.shared_clock import clock_of_port
from rigctl.devices import wire

__all__ = ["STOP_BURST", "STOP_RESEND_S", "CountsFrame", "EncoderStreamParser", "OnboardEncoder", "OnboardScan", "SpikeFrame",
           "applied_speeds",
           "calibrate_command", "encode_command", "finish_command", "held_windows", "speed_command", "spike_raster"]

_MAX_SPEED_CMM_S = 0xFFFF
#: s of spike frames after STOP before the host sends :data:`STOP_BURST` (the board stops within a frame: ~10 ms)
STOP_RESEND_S = 1.0
#: STOP repeated once more than the most payload and CRC bytes a command of the board waits for (CALIBRATE's): the
#: first complete a command whose byte was lost (its CRC then fails, and the board drops it), the rest stop the stream
STOP_BURST = wire.UnoCommand.STOP.value * (wire.ENC_CALIBRATE_PAYLOAD + 3)


def _with_crc(cmd: wire.EncoderCommand, payload: bytes) -> bytes:
    return cmd.value + payload + struct.pack("<H", wire.crc16(payload))


def calibrate_command(taxel_min: np.ndarray, taxel_max: np.ndarray, k: int = 100) -> bytes:
    """CALIBRATE: the 9 top-layer taxels' minimum and maximum ADC counts ((9,) each, 0-65535) and the input gain
    ``k`` (1-255: the integer kernel's range; 100 for SA). Raises ValueError for other shapes or values."""
    lo = np.asarray(taxel_min)
    hi = np.asarray(taxel_max)
    if lo.shape != (wire.ENC_N_TAXELS,) or hi.shape != (wire.ENC_N_TAXELS,):
        raise ValueError(f"taxel_min and taxel_max must be ({wire.ENC_N_TAXELS},), got {lo.shape} and {hi.shape}")
    if lo.min() < 0 or hi.min() < 0 or lo.max() > 0xFFFF or hi.max() > 0xFFFF:
        raise ValueError("taxel_min and taxel_max must be ADC counts 0-65535")
    if not 1 <= int(k) <= 255:
        raise ValueError(f"k must be 1-255, got {k}")
    payload = np.concatenate([lo, hi, [int(k)]]).astype("<u2").tobytes()
    return _with_crc(wire.EncoderCommand.CALIBRATE, payload)


def encode_command(from_sample: int) -> bytes:
    """ENCODE from sample ``from_sample`` (counted from ARM's first sample, 0; sent mod 65536): the board encodes
    from it, out of its ring of the last :data:`rigctl.devices.wire.ENC_RING_SAMPLES` samples (docs/wire-protocol.md
    1.5). Raises ValueError for a negative sample."""
    if from_sample < 0:
        raise ValueError(f"the sample to encode from must be >= 0, got {from_sample}")
    return _with_crc(wire.EncoderCommand.ENCODE, struct.pack("<H", int(from_sample) % 65536))


def _cmm(speed_mm_s: float) -> int:
    cmm = int(round(float(speed_mm_s) * 100.0))
    if not 0 <= cmm <= _MAX_SPEED_CMM_S:
        raise ValueError(f"speed must be 0-{_MAX_SPEED_CMM_S / 100:.2f} mm/s, got {speed_mm_s}")
    return cmm


def speed_command(window: int, speed_mm_s: float) -> bytes:
    """SPEED: the mean speed of real-time window ``window`` (0, 1, ... from the scan's start: samples 100 w to
    100 w + 99; sent mod 65536) as 0.01 mm/s (rounded). The board drops the speed of a window it already scaled with
    the last speed (held: its speed came after the next window but one had begun). Raises ValueError outside
    0-655.35 mm/s or for a negative window."""
    if window < 0:
        raise ValueError(f"window must be >= 0, got {window}")
    return _with_crc(wire.EncoderCommand.SPEED, struct.pack("<HH", window % 65536, _cmm(speed_mm_s)))


def finish_command(speed_mm_s: float) -> bytes:
    """FINISH: end the scan (the stream stops); ``speed_mm_s`` scales the windows still without a speed, if no
    speed was ever sent. Raises ValueError outside 0-655.35 mm/s."""
    return _with_crc(wire.EncoderCommand.FINISH, struct.pack("<H", _cmm(speed_mm_s)))


@dataclass(frozen=True)
class SpikeFrame:
    """One spike frame: ``seq`` of its first sample (the taxel frame's seq of that sample), ``masks`` ((n,) uint16,
    bit i = taxel i spiked at that sample), ``flags`` (:class:`rigctl.devices.wire.SpikeFlag`)."""

    seq: int
    flags: int
    masks: np.ndarray


@dataclass(frozen=True)
class CountsFrame:
    """The counts frame after FINISH: ``counts`` ((9, 20) uint16, spikes per taxel and scaled-time window),
    ``samples`` encoded, windows ``held`` (scaled with the last speed: theirs came late), samples ``dropped`` (the
    board's queue was full), ``queue_max`` (the deepest its sample queue was)."""

    samples: int
    held: int
    dropped: int
    queue_max: int
    counts: np.ndarray


@dataclass
class EncoderStreamParser:
    """Splits the encoder image's byte stream into its three frames (feed chunks of any size with :meth:`feed`):
    each candidate (sync ``0xA5`` then ``0x5A`` taxel, ``0xC3`` spike, ``0xC4`` counts) whose CRC-16 holds is taken
    whole, anything else is skipped a byte at a time (``crc_errors`` counts the candidates that failed).

    Attributes: ``seq``, ``flags``, ``samples`` (lists of the taxel frames' fields, samples (18,) uint16 each),
    ``spikes`` (:class:`SpikeFrame` list), ``counts`` (:class:`CountsFrame` list), ``crc_errors``, ``bytes_skipped``.
    """

    seq: list[int] = field(default_factory=list)
    flags: list[int] = field(default_factory=list)
    samples: list[np.ndarray] = field(default_factory=list)
    spikes: list[SpikeFrame] = field(default_factory=list)
    counts: list[CountsFrame] = field(default_factory=list)
    crc_errors: int = 0
    bytes_skipped: int = 0
    _buf: bytes = b""

    _SIZES = {wire.SYNC[1]: wire.FRAME_SIZE, wire.SPIKE_SYNC[1]: wire.SPIKE_FRAME_SIZE,
              wire.COUNTS_SYNC[1]: wire.COUNTS_FRAME_SIZE}

    def feed(self, chunk: bytes) -> None:
        """Parse ``chunk`` (after any kept tail) into the frame lists."""
        buf = self._buf + bytes(chunk)
        p, n = 0, len(buf)
        while p < n:
            q = buf.find(wire.SYNC[:1], p)
            if q < 0:
                self.bytes_skipped += n - p
                p = n
                break
            self.bytes_skipped += q - p
            p = q
            if p + 1 >= n:
                break
            size = self._SIZES.get(buf[p + 1])
            if size is None:
                p += 1
                self.bytes_skipped += 1
                continue
            if p + size > n:
                break
            frame = buf[p:p + size]
            if wire.crc16(frame[2:size - 2]) != struct.unpack_from("<H", frame, size - 2)[0]:
                self.crc_errors += 1
                self.bytes_skipped += 1
                p += 1
                continue
            self._take(frame)
            p += size
        self._buf = buf[p:]

    def _take(self, frame: bytes) -> None:
        kind = frame[1]
        if kind == wire.SYNC[1]:
            self.seq.append(struct.unpack_from("<H", frame, wire.OFFSET_SEQ)[0])
            self.flags.append(frame[wire.OFFSET_FLAGS])
            self.samples.append(np.frombuffer(frame, "<u2", wire.N_TAXELS, wire.OFFSET_SAMPLES).astype(np.uint16))
        elif kind == wire.SPIKE_SYNC[1]:
            seq, n, flags = struct.unpack_from("<HBB", frame, 2)
            masks = np.frombuffer(frame, "<u2", wire.SPIKE_MASKS, 6).astype(np.uint16)
            self.spikes.append(SpikeFrame(seq, flags, masks[:min(n, wire.SPIKE_MASKS)]))
        else:
            samples, held, dropped, queue_max = struct.unpack_from("<IHHB", frame, 2)
            counts = np.frombuffer(frame, "<u2", wire.ENC_N_TAXELS * wire.ENC_N_WINDOWS, 11).astype(np.uint16)
            self.counts.append(CountsFrame(samples, held, dropped, queue_max,
                                           counts.reshape(wire.ENC_N_TAXELS, wire.ENC_N_WINDOWS)))


def spike_raster(frames: list[SpikeFrame]) -> np.ndarray:
    """The spike frames of one scan (from its first: the sample ENCODE started at) as a raster ``(n_samples, 9)``
    uint8 (1 = a spike at that sample). Raises ValueError if the frames leave a gap (a frame lost: its samples are
    unknown)."""
    n = frames[0].seq if frames else 0
    rows = []
    for f in frames:
        if f.seq != n % 65536:
            raise ValueError(f"spike frames: sample {n} expected, a frame starts at seq {f.seq} (a frame was lost)")
        rows.append(f.masks)
        n += len(f.masks)
    masks = np.concatenate(rows) if rows else np.zeros(0, np.uint16)
    return ((masks[:, None] >> np.arange(wire.ENC_N_TAXELS, dtype=np.uint16)) & 1).astype(np.uint8)


def held_windows(frames: list[SpikeFrame]) -> list[int]:
    """The real-time windows the board scaled with the last speed (held) during one scan, from its spike frames (from
    the first, seq 0): a frame flagged HELD holds the start of window W (a window starts every 100 samples, a frame
    holds 10), whose step held window W - 2 (:mod:`rigctl.arduino` ``sa_step``: 2 windows may wait)."""
    out = []
    n = 0
    for f in frames:
        if f.flags & wire.SpikeFlag.HELD:
            out.append(-(-n // 100) - 2)
        n += len(f.masks)
    return out


def applied_speeds(sent_mm_s: np.ndarray, held: list[int]) -> np.ndarray:
    """The speed each window was scaled with on the board ((n,) mm/s): the speed sent for it (``sent_mm_s[w]``, as
    rounded to 0.01 mm/s), or for a held window the one before it used; a held window 0 had none before it and was
    scaled with 0 (the board's last speed after ENCODE: ``sa_reset``)."""
    out = np.round(np.asarray(sent_mm_s, dtype=np.float64), 2)
    for w in sorted(held):
        if 0 <= w < out.size:
            out[w] = out[w - 1] if w else 0.0
    return out


class _Port(Protocol):
    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...


@dataclass(frozen=True)
class OnboardScan:
    """One scan the board encoded: ``raster`` ((n, 9) uint8 spikes per sample), ``counts`` (its counts frame),
    ``speeds_mm_s`` ((n_windows,) the speed each real-time window was scaled with: the ones sent, a held window's
    the one before), ``held`` (the windows held), ``late_start`` (samples the board began after the one ENCODE named:
    its ring no longer held it, docs/wire-protocol.md 1.5; 0 when it began there)."""

    raster: np.ndarray
    counts: CountsFrame
    speeds_mm_s: np.ndarray
    held: list[int]
    late_start: int = 0


class OnboardEncoder:
    """The host's side of one scan on the Uno encoder image, on its open serial port (a pyserial ``Serial`` with a
    short read timeout, or anything with ``read(size)`` and ``write(data)``): :meth:`arm` calibrates it and starts its
    ring of samples, :meth:`encode_from` starts the encoding at a sample of it (the finger's entry), :meth:`start`
    does both from ARM's first sample, :meth:`poll` reads what has arrived, :meth:`send_speed` gives each 100 ms
    window's speed in order (the window numbers are counted here), :meth:`finish` stops, gives the last speeds and
    returns the :class:`OnboardScan`. The board's features are :func:`rigctl.encoding.features
    .counted_realtime_features` of its counts and speeds."""

    def __init__(self, port: _Port) -> None:
        self.port = port
        # a board of a simulated rig (the port's ``name`` one of its ports): each write stamped on its clock before
        # it is made, so the board waits for bytes the kernel still holds (SharedClock.note_write)
        name = getattr(port, "name", None)
        self._name = name if isinstance(name, str) else ""
        self._clock = clock_of_port(self._name) if self._name else None
        self.parser = EncoderStreamParser()
        self.speeds_sent: list[float] = []
        self.speed_windows: list[int] = []
        self.from_sample: int | None = None

    def _write(self, data: bytes) -> None:
        if self._clock is None:
            self.port.write(data)
            return
        with self._clock.writing(self._name, len(data)):
            self.port.write(data)

    @property
    def samples(self) -> int:
        """Samples the board has encoded (and sent the spike frames of) so far."""
        return sum(len(f.masks) for f in self.spikes)

    @property
    def spikes(self) -> list[SpikeFrame]:
        """The spike frames of the scan's encoding: those from the sample the last ENCODE named on (a frame of an
        earlier ENCODE of the same ARM, still on its way, is not the scan's)."""
        if self.from_sample is None:
            return list(self.parser.spikes)
        return [f for f in self.parser.spikes if (f.seq - self.from_sample) % 65536 < 32768]

    def arm(self, taxel_min: np.ndarray, taxel_max: np.ndarray, k: int = 100, *, from_sample: int | None = None) -> None:
        """CALIBRATE with the 9 taxels' range and ``k``, then ARM: a new scan, its samples into the board's ring
        (sample 0 the first after ARM); with ``from_sample`` ENCODE from it at once (errors of
        :func:`calibrate_command`)."""
        self.parser = EncoderStreamParser()
        self.speeds_sent = []
        self.speed_windows = []
        self.from_sample = None
        out = calibrate_command(taxel_min, taxel_max, k) + wire.EncoderCommand.ARM.value
        if from_sample is not None:
            out += encode_command(from_sample)
            self.from_sample = int(from_sample)
        self._write(out)

    def encode_from(self, from_sample: int) -> None:
        """ENCODE from sample ``from_sample`` of the ring (since ARM): the finger's entry. Again, with a later
        sample, for a pass begun again (the board starts over from it, out of its ring; the speeds given so far are
        dropped). Errors of :func:`encode_command`."""
        self._write(encode_command(from_sample))
        self.from_sample = int(from_sample)
        self.speeds_sent = []
        self.speed_windows = []

    def start(self, taxel_min: np.ndarray, taxel_max: np.ndarray, k: int = 100) -> None:
        """CALIBRATE, ARM and ENCODE from ARM's first sample: a new scan encoded from now (errors of
        :func:`calibrate_command`)."""
        self.arm(taxel_min, taxel_max, k, from_sample=0)

    @property
    def first_sample(self) -> int | None:
        """The sample (since ARM) the board began encoding at, from its first spike frame (None before it): the one
        ENCODE named, or later when its ring no longer held that one."""
        spikes = self.spikes
        if not spikes or self.from_sample is None:
            return None
        return self.from_sample + (spikes[0].seq - self.from_sample) % 65536

    def abandon(self) -> None:
        """STOP the board's scan without finishing it (no counts frame is read): the host gives the pass up."""
        self._write(wire.UnoCommand.STOP.value)

    def poll(self) -> int:
        """Read once from the port (its timeout); returns :attr:`samples`."""
        chunk = self.port.read(4096)
        if chunk:
            self.parser.feed(chunk)
        return self.samples

    def send_speed(self, speed_mm_s: float) -> None:
        """The next window's mean speed (window 0 first; sent once it is known, at the latest 100 ms after the
        window ended: later, the board holds it). Errors of :func:`speed_command`.

        The SPEED of a window the board has held already is not written (it would drop it): once the host has the
        board's sample 100 (w + 2), the board began window w + 2 without w's speed and scaled w with the last one. A
        host catching up after a stall so sends at most two SPEEDs at once, never a burst longer than the board's
        receive ring (docs/wire-protocol.md 1.5). :attr:`speed_windows` lists the windows written, in order;
        :attr:`speeds_sent` every window's speed given."""
        w = len(self.speeds_sent)
        command = speed_command(w, speed_mm_s)
        if self.samples <= 100 * (w + 2):
            self._write(command)
            self.speed_windows.append(w)
        self.speeds_sent.append(round(float(speed_mm_s), 2))

    def finish(self, last_speeds_mm_s: list[float], *, quiet_s: float = 0.3, timeout_s: float = 10.0) -> OnboardScan:
        """STOP, read the spike frames still coming (until ``quiet_s`` without bytes), send the speeds of the windows
        still without one (``last_speeds_mm_s``, in order; the last one repeated if they are too few), FINISH, and
        read the counts frame. The applied speeds cover every window of the counts frame's samples (a last partial
        frame's window, sent with FINISH, is scaled with the last speed: docs/wire-protocol.md 1.5).

        A board still streaming ``STOP_RESEND_S`` after STOP gets :data:`STOP_BURST` (again each ``STOP_RESEND_S``):
        a host byte lost on the way (a burst beyond the board's receive ring, docs/wire-protocol.md 1.5: the image
        of before 2026-11-26 held 63 bytes, which a host catching up with ten windows' SPEEDs overran while the board
        scaled a window; or a byte lost on the line) makes the board read the STOP as a payload byte of the command
        that byte belonged to.

        Raises
        ------
        TimeoutError
            Spike frames still coming ``timeout_s`` after STOP, or no counts frame within ``timeout_s`` of FINISH.
        ValueError
            A spike frame was lost (:func:`spike_raster`), or no speed at all.
        """
        self._write(wire.UnoCommand.STOP.value)
        quiet = stop_at = sent_at = time.monotonic()
        while True:
            chunk = self.port.read(4096)
            now = time.monotonic()
            if chunk:
                self.parser.feed(chunk)
                quiet = now
            elif now - quiet >= quiet_s:  # quiet: a read found nothing, quiet_s after the last bytes (a host
                break  # stalled for quiet_s while the board streamed finds its bytes at the next read, not quiet)
            if now - stop_at > timeout_s:
                raise TimeoutError(f"the board kept sending spike frames {timeout_s} s after STOP")
            if now - sent_at > STOP_RESEND_S:  # still streaming: the STOP was taken as a command's payload
                self._write(STOP_BURST)
                sent_at = now
        pending = list(last_speeds_mm_s)
        while len(self.speeds_sent) < -(-self.samples // 100):  # the windows still without a speed
            if not pending and not self.speeds_sent:
                raise ValueError("no speed for the scan's windows")
            self.send_speed(pending.pop(0) if pending else self.speeds_sent[-1])
        if not self.speeds_sent:
            raise ValueError("no speed for the scan's windows")
        self._write(finish_command(self.speeds_sent[-1]))
        deadline = time.monotonic() + timeout_s
        while not self.parser.counts:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no counts frame from the board within {timeout_s} s of FINISH")
            self.poll()
        held = held_windows(self.spikes)
        applied = applied_speeds(np.array(self.speeds_sent), held)
        n_windows = -(-self.parser.counts[0].samples // 100)
        if applied.size < n_windows:  # samples whose spike frame came after FINISH: FINISH scaled them with the last
            applied = np.concatenate([applied, np.repeat(applied[-1:], n_windows - applied.size)])
        first = self.first_sample
        late = first - self.from_sample if first is not None and self.from_sample is not None else 0
        return OnboardScan(spike_raster(self.spikes), self.parser.counts[0], applied, held, late)
