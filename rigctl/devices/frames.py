"""Taxel-stream framing: build frames (for the simulated Uno and tests) and parse a byte stream into frames.

The parser runs one compiled pass over each chunk (numba): it finds every sync candidate, checks its CRC, keeps the
valid non-overlapping frames and unpacks them, counts what it skipped and keeps an incomplete tail for the next chunk
(one call per chunk: the reader parses ~50 small chunks a second, where a chain of numpy calls cost more than the
bytes). Garbage, truncation and bit flips never raise and never yield a
frame whose CRC is wrong. Layout: ``docs/wire-protocol.md`` section 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np

from rigctl.devices import wire

_SYNC0, _SYNC1 = wire.SYNC[0], wire.SYNC[1]
_CRC_START = wire.CRC_START
_SYNC_IN, _STREAMING_START = int(wire.FrameFlag.SYNC_IN), int(wire.FrameFlag.STREAMING_START)
# the frame layout _scan unpacks: sync (2 bytes), seq (uint16 LE), flags (1), samples (uint16 LE each), CRC (2)
assert wire.CRC_START == 2 and [wire.frame_dtype(1).fields[k][1]  # type: ignore[index]  # a record type: fields
                                for k in ("seq", "flags", "samples", "crc")] == [2, 4, 5, 7]


def encode_frames(seq: np.ndarray, flags: np.ndarray | int, samples: np.ndarray, *, adc_max: int = wire.ADC_MAX) -> bytes:
    """Build consecutive frames.

    Parameters
    ----------
    seq : (n,) integer array, sequence numbers (taken modulo 65536).
    flags : (n,) integer array or scalar, flags bytes (:class:`rigctl.devices.wire.FrameFlag`).
    samples : (n, ch) integer array of ADC counts 0..adc_max; ``ch`` is the link's channel count (18 on the Uno).
    adc_max : largest count the link carries (``2**bits - 1``, 1023 for the Uno's 10 bits).

    Returns
    -------
    bytes of length ``n * (7 + 2 * ch)`` (43 per frame for 18 channels).

    Raises
    ------
    ValueError if ``samples`` is not 2-D with at least one channel, or holds values outside 0..adc_max.
    """
    samples = np.asarray(samples)
    if samples.ndim != 2 or samples.shape[1] < 1:
        raise ValueError(f"samples must be (n, channels), got {samples.shape}")
    if samples.size and (samples.min() < 0 or samples.max() > adc_max):
        raise ValueError(f"samples must be ADC counts 0-{adc_max}")
    n, ch = samples.shape
    out = np.empty(n * wire.frame_size(ch), np.uint8)
    _encode_kernel(np.ascontiguousarray(np.broadcast_to(np.asarray(seq, dtype=np.int64), (n,))),
                   np.ascontiguousarray(np.broadcast_to(np.asarray(flags, dtype=np.int64), (n,))),
                   np.ascontiguousarray(samples, dtype=np.uint16), wire.CRC16_TABLE, out)
    return out.tobytes()


def encode_stream_frames(seq0: int, sync_in: np.ndarray, first: bool, samples: np.ndarray, adc_max: int) -> bytes:
    """Frames ``seq0, seq0 + 1, ...`` (mod 65536) of a board's stream in one compiled pass (the simulated Uno's
    every tick): flags SYNC_IN where ``sync_in`` ((n,) bool) is set, and STREAMING_START on the first frame if
    ``first``; ``samples`` (n, ch) uint16. The same bytes as :func:`encode_frames` with those sequence numbers and
    flags; ValueError for a sample above ``adc_max``."""
    n, ch = samples.shape
    out = np.empty(n * wire.frame_size(ch), np.uint8)
    if not _encode_stream_kernel(int(seq0), sync_in, bool(first), samples, int(adc_max), wire.CRC16_TABLE, out):
        raise ValueError(f"samples must be ADC counts 0-{adc_max}")
    return out.tobytes()


@numba.njit(cache=True, nogil=True, inline="always")
def _put_frame(out: Any, p: int, seq: int, flags: int, samples: Any, i: int, table: Any) -> None:  # pragma: no cover
    """Frame ``i`` at byte offset ``p`` of ``out``: sync, seq, flags, samples (little-endian), CRC-16/MODBUS."""
    n_ch = samples.shape[1]
    out[p] = _SYNC0
    out[p + 1] = _SYNC1
    out[p + 2] = seq & 0xFF
    out[p + 3] = (seq >> 8) & 0xFF
    out[p + 4] = flags & 0xFF
    for ch in range(n_ch):
        v = samples[i, ch]
        out[p + 5 + 2 * ch] = v & 0xFF
        out[p + 6 + 2 * ch] = v >> 8
    end = p + 5 + 2 * n_ch
    crc = np.uint16(0xFFFF)
    for j in range(p + _CRC_START, end):
        crc = (crc >> np.uint16(8)) ^ table[(crc ^ out[j]) & np.uint16(0xFF)]
    out[end] = crc & np.uint16(0xFF)
    out[end + 1] = crc >> np.uint16(8)


@numba.njit(cache=True, nogil=True)
def _encode_kernel(seq: Any, flags: Any, samples: Any, table: Any, out: Any) -> None:  # pragma: no cover - compiled
    size = 7 + 2 * samples.shape[1]
    for i in range(samples.shape[0]):
        _put_frame(out, i * size, seq[i], flags[i], samples, i, table)


@numba.njit(cache=True, nogil=True)
def _encode_stream_kernel(seq0: int, sync_in: Any, first: bool, samples: Any, adc_max: int, table: Any,
                          out: Any) -> bool:  # pragma: no cover - compiled
    n, n_ch = samples.shape
    for i in range(n):
        for ch in range(n_ch):
            if samples[i, ch] > adc_max:
                return False
    size = 7 + 2 * n_ch
    for i in range(n):
        flags = _SYNC_IN if sync_in[i] else 0
        if first and i == 0:
            flags |= _STREAMING_START
        _put_frame(out, i * size, (seq0 + i) & 0xFFFF, flags, samples, i, table)
    return True


def encode_frame(seq: int, flags: int, samples: Any) -> bytes:
    """One frame (43 bytes for 18 channels) from a sequence number, a flags byte and one sample per channel; see
    :func:`encode_frames`."""
    samples = np.asarray(samples).reshape(1, -1)
    return encode_frames(np.array([seq]), np.array([flags]), samples)


@dataclass
class Frames:
    """A batch of parsed frames: ``seq`` (n,) uint16, ``flags`` (n,) uint8, ``samples`` (n, ch) uint16 ADC counts."""

    seq: np.ndarray
    flags: np.ndarray
    samples: np.ndarray

    def __len__(self) -> int:
        return len(self.seq)

    @classmethod
    def empty(cls, n_channels: int = wire.N_TAXELS) -> "Frames":
        return cls(
            np.zeros(0, np.uint16), np.zeros(0, np.uint8), np.zeros((0, int(n_channels)), np.uint16)
        )


@dataclass
class ParserStats:
    """Running counters of a :class:`FrameParser`."""

    frames: int = 0
    bytes_in: int = 0
    bytes_skipped: int = 0  #: bytes that were not part of a valid frame
    crc_errors: int = 0  #: sync candidates rejected by their CRC
    out_of_range: int = 0  #: candidates with a valid CRC but a sample above the link's ADC range (not frames)


@dataclass
class FrameParser:
    """Incremental, vectorised taxel-frame parser. Feed it chunks of any size with :meth:`feed`.

    ``n_channels`` is the link's channel count (the ``ch`` of the board's banner; 18 for the Uno): frames are
    ``7 + 2 * n_channels`` bytes. ``adc_max`` is the largest count the link carries (``2**bits - 1`` of the banner's
    ``bits``; 1023 for the Uno's 10-bit ADC): a candidate whose CRC happens to match (1 in 65,536 for garbage) but
    which holds a larger sample is no frame, and is skipped so that it cannot hide the real frame it overlaps.
    Raises ValueError for fewer than one channel or an ``adc_max`` outside 1-65535.
    """

    stats: ParserStats = field(default_factory=ParserStats)
    _buf: bytes = b""
    n_channels: int = wire.N_TAXELS
    adc_max: int = wire.ADC_MAX

    def __post_init__(self) -> None:
        self.n_channels = int(self.n_channels)
        self._size = wire.frame_size(self.n_channels)
        self.adc_max = int(self.adc_max)
        if not 1 <= self.adc_max <= 0xFFFF:
            raise ValueError(f"adc_max must be 1-65535 counts, got {self.adc_max}")

    def feed(self, chunk: bytes) -> Frames:
        """Parse ``chunk`` (appended to any kept tail); return the complete valid frames found, in stream order."""
        self.stats.bytes_in += len(chunk)
        buf = self._buf + bytes(chunk) if self._buf else bytes(chunk)
        arr = np.frombuffer(buf, dtype=np.uint8)
        n = arr.size
        size = self._size
        last_start = n - size  # last offset at which a complete frame can start
        if last_start < 0:
            self._buf = buf
            return Frames.empty(self.n_channels)
        n_max = last_start // size + 1
        seq = np.empty(n_max, np.uint16)
        flags = np.empty(n_max, np.uint8)
        samples = np.empty((n_max, self.n_channels), np.uint16)
        n_ok, crc_errors, out_of_range, consumed_to = _scan(arr, last_start, size, wire.CRC16_TABLE, self.adc_max,
                                                             seq, flags, samples)
        self.stats.crc_errors += int(crc_errors)
        self.stats.out_of_range += int(out_of_range)
        keep_from = max(int(consumed_to), last_start + 1)
        self.stats.bytes_skipped += keep_from - n_ok * size
        self.stats.frames += int(n_ok)
        self._buf = buf[keep_from:]
        if not n_ok:
            return Frames.empty(self.n_channels)
        return Frames(seq[:n_ok], flags[:n_ok], samples[:n_ok])

    def reset(self) -> None:
        """Drop any kept partial frame (e.g. after the port was reopened)."""
        self._buf = b""


@numba.njit(cache=True, nogil=True)
def _scan(arr: Any, last_start: int, size: int, table: Any, adc_max: int, seq: Any, flags: Any,
          samples: Any) -> tuple[int, int, int, int]:  # pragma: no cover - compiled
    """One pass over the buffer ``arr`` (uint8): every sync candidate at offsets 0..last_start, its CRC checked
    (CRC-16/MODBUS over bytes CRC_START..size-3, little-endian CRC in the last two) and its samples against
    ``adc_max``; a valid frame not overlapping the previous accepted one is accepted and unpacked into ``seq``,
    ``flags``, ``samples`` (little-endian). A bad candidate lying inside an accepted frame is payload, not a corrupt
    frame; the others are CRC errors, or out of range when only the range check failed.
    Returns (frames accepted, CRC errors, out-of-range candidates, the offset after the last accepted frame or 0)."""
    n_ch = samples.shape[1]
    off_crc = size - 2
    n_ok = 0
    crc_errors = 0
    out_of_range = 0
    end = 0  # after the last accepted frame
    for p in range(last_start + 1):
        if arr[p] != _SYNC0 or arr[p + 1] != _SYNC1:
            continue
        crc = np.uint16(0xFFFF)
        for j in range(p + _CRC_START, p + off_crc):
            crc = (crc >> np.uint16(8)) ^ table[(crc ^ arr[j]) & np.uint16(0xFF)]
        recv = np.uint16(arr[p + off_crc]) | (np.uint16(arr[p + off_crc + 1]) << np.uint16(8))
        if crc == recv:
            if n_ok > 0 and p < end:  # a valid frame overlapping an accepted one is dropped
                continue
            in_range = True
            for ch in range(n_ch):
                q = p + 5 + 2 * ch
                if (np.int64(arr[q]) | (np.int64(arr[q + 1]) << 8)) > adc_max:
                    in_range = False
                    break
            if not in_range:
                out_of_range += 1
                continue
            seq[n_ok] = np.uint16(arr[p + 2]) | (np.uint16(arr[p + 3]) << np.uint16(8))
            flags[n_ok] = arr[p + 4]
            for ch in range(n_ch):
                q = p + 5 + 2 * ch
                samples[n_ok, ch] = np.uint16(arr[q]) | (np.uint16(arr[q + 1]) << np.uint16(8))
            n_ok += 1
            end = p + size
        elif n_ok == 0 or p >= end:
            crc_errors += 1
    return n_ok, crc_errors, out_of_range, end


@dataclass
class SequenceTracker:
    """Counts frames missing from the device's 16-bit sequence counter (wrap-aware)."""

    last_seq: int | None = None
    dropped: int = 0

    def update(self, seq: np.ndarray) -> int:
        """Account for the next ``(n,) uint16`` sequence numbers; return how many frames are missing before/among them."""
        if len(seq) == 0:
            return 0
        seq = np.asarray(seq, dtype=np.int64)
        first = int(seq[0])
        gaps = 0 if self.last_seq is None else (first - self.last_seq - 1) & 0xFFFF
        if len(seq) > 1:  # the steps inside the chunk: 1 when no frame is missing (mod 65,536)
            gaps += int(((np.diff(seq) - 1) & 0xFFFF).sum())
        self.last_seq = int(seq[-1])
        self.dropped += gaps
        return gaps

    def reset(self) -> None:
        self.last_seq = None
