"""The handheld rig's finger with the encoder on its board (``--onboard-encoder``): the taxel board runs the Uno
encoder image (docs/firmware.md "The encoder in the Uno image", docs/wire-protocol.md 1.5) and sends, for each scan,
its spikes and its counts frame instead of raw taxel frames.

One scan (:func:`encode_pass`), as the paper's microcontroller does it with the host's tracker: at the cue the host
sends CALIBRATE (the classifier's taxel range) and ARM (the board keeps its last 32 samples in a ring); once the
tracker shows the finger's entry into the plate's used part (its position through
:data:`rigctl.core.handheld.USED_START_MM`, interpolated: the host's cut's entry) the host sends ENCODE with the
entry's sample, and the board encodes from it, out of its ring (issue 78 item 4: before, it began at the host's
ENCODE, 5-30 ms after the entry); after each 100 ms window of the board's samples it sends
the tracker's mean velocity over that window as SPEED (window-numbered); once the finger has left the used part
(past :data:`rigctl.core.handheld.USED_END_MM`) it stops the board, sends the speeds of the windows still without
one and FINISH, and takes the counts frame (:class:`rigctl.devices.encoder_stream.OnboardEncoder`). The result is a
:class:`rigctl.core.handheld.RawScan` with no taxel frames, the tracker's samples and the board's record
(:class:`rigctl.core.onboard.OnboardEncoding`), cut into a trial by position as any scan.

:class:`OnboardFingerScans` is that finger on a real board (``--taxel-port PORT`` beside ``--motion lsl:NAME`` or
``serial:PORT``); the simulated one (the board under simavr) is :class:`rigctl.simulation.hil_finger.HilFingerScans`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.core.handheld import (
    MARGIN_S,
    SPEED_FLOOR_MM_S,
    USED_END_MM,
    USED_START_MM,
    PlateAxis,
    RawScan,
    ScanError,
    Tracker,
    checked_since,
    position_window_speed,
)
from rigctl.core.onboard import OnboardEncoding
from rigctl.core.sensor import PAPER_FINGER, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import PlannedTrial
from rigctl.devices import wire
from rigctl.devices.encoder_stream import OnboardEncoder, OnboardScan

__all__ = ["BoardRange", "OnboardFingerScans", "encode_pass", "onboard_encoding", "onboard_raw_scan", "open_onboard_finger", "read_banner",
           "window_speed_mm_s"]

#: a real-time window of the on-board encoder, s (the paper's 100 ms: the board's 100 samples at 1 kHz)
WINDOW_S = 0.1
#: the board's samples per window (1 kHz)
WINDOW_SAMPLES = 100
#: how often the host polls the board and the tracker during a scan, s
POLL_S = 0.005
#: windows ahead of the last sent whose speeds go with FINISH (more than the board's quiet tail can hold)
FINISH_WINDOWS = 10


@dataclass(frozen=True)
class BoardRange:
    """The board's CALIBRATE: the 9 top-layer taxels' minimum and maximum ADC counts ((9,) integers: the classifier's
    normalisation, rounded) and the SA input gain ``k`` (an integer 1-255)."""

    taxel_min: np.ndarray
    taxel_max: np.ndarray
    k: int = 100

    @classmethod
    def of(cls, taxel_min: Any, taxel_max: Any, k: float) -> "BoardRange":
        """From a normalisation (the first 9 channels: the top layer) and k, rounded to the board's integers.
        Raises ValueError for fewer than 9 channels or a k outside 1-255."""
        lo = np.rint(np.asarray(taxel_min, np.float64).reshape(-1)[:wire.ENC_N_TAXELS])
        hi = np.rint(np.asarray(taxel_max, np.float64).reshape(-1)[:wire.ENC_N_TAXELS])
        if lo.size != wire.ENC_N_TAXELS or hi.size != wire.ENC_N_TAXELS:
            raise ValueError(f"the on-board encoder takes {wire.ENC_N_TAXELS} taxels' range, got {lo.size}")
        if k != round(k) or not 1 <= k <= 255:
            raise ValueError(f"the on-board encoder takes an integer k in 1-255, got {k}")
        return cls(lo.clip(0, 0xFFFF).astype(np.int64), hi.clip(0, 0xFFFF).astype(np.int64), int(k))


def window_speed_mm_s(t: np.ndarray, along_mm: np.ndarray, t0: float, t1: float, last: float = 0.0) -> float:
    """The finger's mean speed along the plate over ``[t0, t1)`` (s), mm/s >= 0: the position's change over the span
    (:func:`rigctl.core.handheld.position_window_speed`, floored at :data:`rigctl.core.handheld.SPEED_FLOOR_MM_S`:
    a still or backward window is scaled with 0 mm/s), as the paper's tracker velocity per 100 ms; over the part the
    tracker covers when its samples end before ``t1`` (a dropout: the speed is due before the next sample comes).
    ``last`` (the speed before) with fewer than two samples or less than 10 ms of the window covered."""
    if t.size < 2:
        return last
    t1 = min(t1, float(t[-1]))
    if t1 - t0 < 0.01:
        return last
    return max(SPEED_FLOOR_MM_S, position_window_speed(t, along_mm, t0, t1))


def _entered(t: np.ndarray, along: np.ndarray) -> float | None:
    """The time the finger last rose through the used part's start (interpolated), or None: the host's cut's entry
    (the last before the exit: a pass begun, abandoned and begun again starts at its new entry)."""
    above = along >= USED_START_MM
    rising = np.flatnonzero(above[1:] & ~above[:-1])
    if not rising.size:
        return None
    i = int(rising[-1]) + 1
    x0, x1 = along[i - 1], along[i]
    return float(t[i - 1] + (USED_START_MM - x0) / (x1 - x0) * (t[i] - t[i - 1])) if x1 != x0 else float(t[i])


def onboard_encoding(scan: OnboardScan, rate_hz: float) -> OnboardEncoding:
    """The trial's record of one scan the board encoded."""
    c = scan.counts
    return OnboardEncoding.from_raster(scan.raster, counts=c.counts, speeds_mm_s=scan.speeds_mm_s,
                                       held_windows=np.asarray(scan.held, np.int64), samples=int(c.samples),
                                       dropped_samples=int(c.dropped), queue_max=int(c.queue_max), rate_hz=rate_hz)


def encode_pass(enc: OnboardEncoder, board: BoardRange, motion: Callable[[], tuple[np.ndarray, np.ndarray]], *,
                now: Callable[[], float], started: Callable[[float], float], stop: Callable[[], bool] | None = None,
                timeout_s: float = 60.0, on_encode: Callable[[float, int], None] | None = None,
                rate_hz: float = 1000.0) -> tuple[float, OnboardScan] | None:
    """One scan on the board (module docstring).

    Parameters
    ----------
    enc : the host's side of the board's link.
    board : its CALIBRATE.
    motion : ``motion()`` -> the tracker's samples so far on the scan's clock: times (k,) s and positions along the
        plate (k,) mm.
    now : the scan's clock, s.
    started : ``started(t_sent)`` once ARM is sent (``t_sent`` = ``now()``); returns the time of the board's sample 0
        (its first after ARM) on the scan's clock: sample k is at that time + k / ``rate_hz``.
    stop : the scan is abandoned (the board stopped, None returned) once it turns true.
    on_encode : ``on_encode(now(), sample)`` as ENCODE is sent (the host's view then, and the entry's sample).
    rate_hz : the board's sample rate.

    Returns
    -------
    (the time of the board's first encoded sample: the entry's, or later when the host was later than the board's
    ring holds, ``scan.late_start``; the scan) or None when stopped.

    Raises
    ------
    ScanError
        No pass within ``timeout_s``, the board sent nothing, or its counts frame did not come.
    """
    t_begin = time.monotonic()
    motion()  # a tracker the host refuses (stamped ahead: ScanError) refuses the pass before the board is armed
    enc.arm(board.taxel_min, board.taxel_max, board.k)
    t_zero = started(now())  # the board's sample 0 on the scan's clock
    t_in = math.nan
    w_origin = math.nan
    while True:
        if stop is not None and stop():
            enc.abandon()
            return None
        if time.monotonic() - t_begin > timeout_s:
            enc.abandon()
            raise ScanError(f"no pass of the finger through the plate within {timeout_s:g} s")
        try:
            t, along = motion()
        except ScanError:  # the motion refused (a tracker stamped ahead): the board stopped
            enc.abandon()
            raise
        entry = _entered(t, along) if t.size >= 2 else None
        if math.isnan(t_in) or (entry is not None and entry > t_in):  # the entry, or a pass begun again: from it
            if entry is None:
                time.sleep(POLL_S)
                continue
            t_in = entry
            # the first sample at or after the entry (the host's cut keeps the frames from the entry on)
            from_sample = max(0, math.ceil((t_in - t_zero) * rate_hz - 1e-6))
            if on_encode is not None:
                on_encode(now(), from_sample)
            enc.encode_from(from_sample)
            continue
        n = enc.poll()
        first = enc.first_sample
        if first is None:  # no spike frame yet: where the board began is not known
            continue
        w_origin = t_zero + first / rate_hz
        w = len(enc.speeds_sent)
        # a window's speed once the tracker has passed its end, or (a tracker dropout) once the board is half way
        # through the next window: later, the board would scale it with the last speed (held)
        while t.size and (t[-1] >= w_origin + WINDOW_S * (w + 1) or n >= WINDOW_SAMPLES * (w + 1) + WINDOW_SAMPLES // 2):
            enc.send_speed(window_speed_mm_s(t, along, w_origin + WINDOW_S * w, w_origin + WINDOW_S * (w + 1),
                                             enc.speeds_sent[-1] if enc.speeds_sent else 0.0))
            w += 1
        if np.any(along[t >= t_in] > USED_END_MM):
            break
    rest: list[float] = []
    for i in range(len(enc.speeds_sent), len(enc.speeds_sent) + FINISH_WINDOWS):
        before = rest[-1] if rest else enc.speeds_sent[-1] if enc.speeds_sent else 0.0
        rest.append(window_speed_mm_s(t, along, w_origin + WINDOW_S * i, w_origin + WINDOW_S * (i + 1), before))
    try:
        scan = enc.finish(rest)
    except (TimeoutError, ValueError) as exc:
        raise ScanError(f"the board's encoded scan is incomplete: {exc}") from None
    return w_origin, scan


class OnboardFingerScans:
    """Scans of the real finger whose board encodes them (module docstring): ``port`` (the board's serial port, open,
    the encoder image's banner read), ``tracker`` (the motion source), ``axis`` (the plate's axis when the tracker
    gives x, y, z), ``board`` (CALIBRATE). Raises ScanError for x, y, z without an axis."""

    def __init__(self, port: Any, port_name: str, tracker: Tracker, axis: PlateAxis | None, board: BoardRange, *,
                 layout: SensorLayout = PAPER_FINGER, textures: TextureSet | None = None,
                 timeout_s: float = 60.0, banner: dict[str, str] | None = None) -> None:
        if len(tracker.channels) == 3 and axis is None:
            raise ScanError("a tracker's x, y, z need the plate's axis: calibrate it (the rig config's handheld block, "
                            "docs/guides/handheld.md), or give the position along the plate as one channel")
        self.port, self.port_name, self.tracker, self.axis, self.board = port, port_name, tracker, axis, board
        self.layout, self.textures, self.timeout_s = layout, textures or PAPER_TEXTURES, float(timeout_s)
        self.banner = dict(banner or {})
        self.scans = 0

    def _along(self, x: np.ndarray) -> np.ndarray:
        return x[:, 0] if x.shape[1] != 3 else self.axis.along_mm(x)  # type: ignore[union-attr]  # checked above

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """Encode one pass on the board (:func:`encode_pass`), the tracker on the host clock (``time.monotonic``).
        Raises ScanError."""
        t_cue = time.monotonic()

        def motion() -> tuple[np.ndarray, np.ndarray]:  # refused before the board starts when stamped ahead
            t, x = checked_since(self.tracker, t_cue - MARGIN_S)
            return t, self._along(x) if t.size else np.zeros(0)

        enc = OnboardEncoder(self.port)
        got = encode_pass(enc, self.board, motion, now=time.monotonic, started=lambda t: t, stop=stop,
                          timeout_s=self.timeout_s)
        if got is None:
            return None
        t0, scan = got
        time.sleep(MARGIN_S / 2)
        t, x = self.tracker.since(t_cue - MARGIN_S)
        self.scans += 1
        return onboard_raw_scan(t, self._along(x), t0, onboard_encoding(scan, self.layout.sample_rate_hz),
                                self.layout, {"tracker_stream": self.tracker.name,
                                              "taxels_from": f"encoded on the taxel board on {self.port_name}",
                                              "onboard_crc_errors": int(enc.parser.crc_errors),
                                              "onboard_late_start_samples": int(scan.late_start),
                                              **getattr(self.tracker, "counters", dict)()})

    def describe(self) -> dict[str, Any]:
        return {"kind": "taxel_board_finger_onboard_encoder", **self.tracker.describe(), "taxels": "encoded on board",
                "taxel_port": self.port_name, "taxel_board": {k: self.banner[k] for k in sorted(self.banner)},
                "onboard_taxel_min": self.board.taxel_min.tolist(), "onboard_taxel_max": self.board.taxel_max.tolist(),
                "onboard_k": self.board.k}

    def link_problem(self) -> str | None:
        problem = getattr(self.tracker, "link_problem", None)
        return problem() if callable(problem) else None

    def close(self) -> None:
        try:
            self.port.close()
        finally:
            self.tracker.close()


def onboard_raw_scan(t: np.ndarray, along_mm: np.ndarray, t0: float, onboard: OnboardEncoding,
                     layout: SensorLayout, attrs: dict[str, Any]) -> RawScan:
    """A pass the board encoded as a :class:`RawScan`: no taxel frames, the tracker's samples (times ``t`` s, the
    positions along the plate), the board's record and the time ``t0`` of its first encoded sample (same clock)."""
    none = np.zeros(0)
    return RawScan(taxels=np.zeros((0, layout.n_channels), np.uint16), seq=none.astype(np.uint16),
                   host_time_s=none, tracker_time_s=np.asarray(t, np.float64),
                   along_mm=np.asarray(along_mm, np.float64), attrs=attrs, onboard=onboard, onboard_start_s=float(t0))


def read_banner(port: Any, timeout_s: float) -> dict[str, str]:
    """The board's banner line (``key=value`` words) within ``timeout_s``. Raises ScanError when none comes or it is
    not the encoder image's."""
    text = b""
    deadline = time.monotonic() + timeout_s
    while b"\n" not in text:
        if time.monotonic() > deadline:
            raise ScanError(f"no banner from the board within {timeout_s:g} s")
        text += port.read(256)
    line = text.split(b"\n", 1)[0].decode("ascii", "replace")
    if wire.UNO_ENCODER_FIELD not in line:
        raise ScanError(f"the board does not run the encoder image (its banner: {line.strip()!r}; flash it with "
                        "`rigctl firmware --image uno_encoder`)")
    return {k: v for k, _, v in (w.partition("=") for w in line.split()) if v}


def open_onboard_finger(port_name: str, tracker: Tracker, axis: PlateAxis | None, board: BoardRange, *,
                        textures: TextureSet | None = None, timeout_s: float = 60.0,
                        banner_timeout_s: float = 5.0) -> OnboardFingerScans:
    """Open the finger's board on ``port_name`` (1 Mbaud, its banner checked for the encoder image) and make the scan
    source on it and ``tracker``. On any failure the port and the tracker are closed. Raises ScanError."""
    import serial

    try:
        port = serial.Serial(port_name, wire.TAXEL_BAUD, timeout=0.02)
    except (OSError, ValueError) as exc:
        tracker.close()
        raise ScanError(f"cannot open the finger's taxel board on {port_name}: {exc}") from None
    try:
        banner = read_banner(port, banner_timeout_s)
        return OnboardFingerScans(port, port_name, tracker, axis, board, textures=textures, timeout_s=timeout_s,
                                  banner=banner)
    except BaseException:
        port.close()
        tracker.close()
        raise
