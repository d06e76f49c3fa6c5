"""Taxel-stream framing: build frames (for the simulated Uno and tests) and parse a byte stream into frames.

The parser is vectorised with numpy: it finds every sync candidate in the buffer at once, checks all their CRCs in
one pass (:func:`rigctl.devices.wire.crc16_rows`), keeps the valid non-overlapping frames, counts what it skipped
and keeps an incomplete tail for the next chunk. Garbage, truncation and bit flips never raise and never yield a
frame whose CRC is wrong. Layout: ``docs/wire-protocol.md`` section 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.devices import wire

_SYNC0, _SYNC1 = wire.SYNC[0], wire.SYNC[1]


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
    size = wire.frame_size(ch)
    out = np.zeros(n, dtype=wire.frame_dtype(ch))
    out["sync"] = np.frombuffer(wire.SYNC, dtype=np.uint8)
    out["seq"] = np.asarray(seq, dtype=np.int64) & 0xFFFF
    out["flags"] = np.broadcast_to(np.asarray(flags, dtype=np.int64) & 0xFF, (n,))
    out["samples"] = samples
    raw = out.view(np.uint8).reshape(n, size)
    out["crc"] = wire.crc16_rows(raw[:, wire.CRC_START : size - 2])
    return out.tobytes()


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


@dataclass
class FrameParser:
    """Incremental, vectorised taxel-frame parser. Feed it chunks of any size with :meth:`feed`.

    ``n_channels`` is the link's channel count (the ``ch`` of the board's banner; 18 for the Uno): frames are
    ``7 + 2 * n_channels`` bytes. Raises ValueError for fewer than one channel.
    """

    stats: ParserStats = field(default_factory=ParserStats)
    _buf: bytes = b""
    n_channels: int = wire.N_TAXELS

    def __post_init__(self) -> None:
        self.n_channels = int(self.n_channels)
        self._size = wire.frame_size(self.n_channels)
        self._dtype = wire.frame_dtype(self.n_channels)
        self._offsets = np.arange(self._size)[None, :]  # byte offsets within a frame (one fancy index per chunk)

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
        head = arr[: last_start + 1]
        cand = np.flatnonzero((head == _SYNC0) & (arr[1 : last_start + 2] == _SYNC1))
        accepted = np.zeros(0, dtype=np.int64)
        if cand.size:
            rows = arr[cand[:, None] + self._offsets]  # (candidates, frame size) bytes
            off_crc = size - 2
            crc_calc = wire.crc16_rows(rows[:, wire.CRC_START : off_crc])
            crc_recv = rows[:, off_crc].astype(np.uint16) | (rows[:, off_crc + 1].astype(np.uint16) << 8)
            ok = crc_calc == crc_recv
            valid = cand[ok]
            if valid.size > 1 and np.any(np.diff(valid) < size):
                valid = _non_overlapping(valid, size)
            accepted = valid
            bad = cand[~ok]
            if bad.size:
                if accepted.size:
                    # a bad candidate lying inside an accepted frame is payload, not a corrupt frame
                    idx = np.searchsorted(accepted, bad, side="right") - 1
                    inside = (idx >= 0) & (bad < accepted[np.maximum(idx, 0)] + size)
                    bad = bad[~inside]
                self.stats.crc_errors += int(bad.size)
        consumed_to = int(accepted[-1]) + size if accepted.size else 0
        keep_from = max(consumed_to, last_start + 1)
        self.stats.bytes_skipped += keep_from - accepted.size * size
        self.stats.frames += int(accepted.size)
        self._buf = buf[keep_from:]
        if not accepted.size:
            return Frames.empty(self.n_channels)
        windows = arr[accepted[:, None] + self._offsets]  # (frames, frame size) bytes, contiguous
        rec: Any = windows.view(self._dtype).reshape(-1)  # records: fields by name
        return Frames(rec["seq"].astype(np.uint16), rec["flags"].astype(np.uint8), rec["samples"].astype(np.uint16))

    def reset(self) -> None:
        """Drop any kept partial frame (e.g. after the port was reopened)."""
        self._buf = b""


def _non_overlapping(valid: np.ndarray, size: int) -> np.ndarray:
    keep = []
    end = -1
    for pos in valid.tolist():
        if pos >= end:
            keep.append(pos)
            end = pos + size
    return np.asarray(keep, dtype=np.int64)


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
        prev = np.concatenate(([seq[0] - 1 if self.last_seq is None else self.last_seq], seq[:-1]))
        gaps = int(((seq - prev - 1) & 0xFFFF).sum())
        self.last_seq = int(seq[-1])
        self.dropped += gaps
        return gaps

    def reset(self) -> None:
        self.last_seq = None
