"""The simulated operator's finger on the taxel board's real firmware with the encoder on board: the Uno encoder image
(``uno_encoder``) under simavr (:class:`rigctl.simulation.hil.HilRig`), the handheld rig's ``--hil
--onboard-encoder``.

For each cue the simulated operator makes its pass (:class:`rigctl.simulation.operator.SimulatedOperator`: the
taxel readings at 1 kHz and the tracker's samples); the readings are played to the board's ADC (the top layer, and
the same counts on the bottom layer's pins), and the host encodes the pass on the board exactly as on a real finger
(:func:`rigctl.devices.onboard_finger.encode_pass`): ARM at the cue, ENCODE from the entry's sample once the tracker
shows the finger entering the used part, each window's tracker velocity as SPEED, FINISH once it has left. The
tracker's samples are handed out on the board's clock (the row it plays, :meth:`rigctl.simulation.hil.HilRig
.playing_row`, then the samples it encoded: its waveform's row 0 is the pass's time 0), so a simavr slower or faster
than the wall clock changes nothing.
Each scan keeps what the board's ADC converted (:attr:`HilFingerScans.played`: the pass's readings and the row of
the first encoded sample) for a check against the host's integer kernel, and when the host sent its commands (how far
its view of the pass had got, and how long after its last read it wrote): on a starved machine the host acts late,
and what it measured of its own lateness tells that apart from the board's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.core.handheld import PlateAxis, RawScan, ScanError
from rigctl.core.sensor import PAPER_FINGER, SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import PlannedTrial
from rigctl.devices import wire
from rigctl.devices.encoder_stream import OnboardEncoder
from rigctl.devices.onboard_finger import (
    WINDOW_SAMPLES,
    BoardRange,
    encode_pass,
    onboard_encoding,
    onboard_raw_scan,
    read_banner,
)
from rigctl.simulation.model import RigConfig
from rigctl.simulation.operator import SimulatedOperator, plate_axis_of

__all__ = ["HilFingerScans", "NotingPort", "PlayedScan"]

#: rows of the pass's last reading played after it (the board keeps converting while the host finishes)
TAIL_ROWS = 2000
#: how long the harness may take to report the first encoded row, s
START_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class PlayedScan:
    """One pass as the board's ADC saw it: ``taxels`` (n, 9) the readings played (row 0 = the pass's time 0),
    ``first_row`` the row of the board's first encoded sample, ``samples`` how many it encoded, ``arm_row`` the row of
    its sample 0 (ARM's), ``from_sample`` the sample ENCODE named (the entry's, since ARM).

    And the host's side: ``encode_view_s`` the pass's time (s) the host's view had reached when it sent ENCODE;
    ``speeds_sent`` (samples the host had received, s since its last read returned) at each window's SPEED, window 0
    first (a window whose SPEED the host did not send, the board having held it, :meth:`OnboardEncoder.send_speed
    <rigctl.devices.encoder_stream.OnboardEncoder.send_speed>`: at least the board's sample 100 (w + 2) + 1, nan);
    ``stop_sent`` the same at STOP."""

    taxels: np.ndarray
    first_row: int
    samples: int
    encode_view_s: float = math.nan
    speeds_sent: tuple[tuple[int, float], ...] = ()
    stop_sent: tuple[int, float] = (-1, math.nan)
    arm_row: int = 0
    from_sample: int = 0

    def encoded(self) -> np.ndarray:
        """(samples, 9) the readings the board encoded."""
        return self.taxels[self.first_row:self.first_row + self.samples]


class NotingPort:
    """The encoder board's serial port (``read(size)``, ``write(data)``: a pyserial ``Serial``) for an
    :class:`~rigctl.devices.encoder_stream.OnboardEncoder`, noting when the host writes each command, to judge a
    starved host by its own measure: :attr:`writes` holds per write (its first byte: the command, the count of bytes
    written so far with it, the samples the host had received then: ``samples()``, s since the last read returned),
    and, given ``board_s`` (the simulated rig's clock: ``now() -> s``), :attr:`board_times_s`: the board's time as the
    host began each write, to judge a host's lateness on the board's clock (whatever made it late: its own threads, or
    the kernel holding the board's bytes on their way to it)."""

    def __init__(self, port: Any, board_s: Callable[[], float] | None = None) -> None:
        self.port = port
        self.samples: Callable[[], int] = lambda: 0
        self.written = 0
        self.writes: list[tuple[bytes, int, int, float]] = []
        self.board_s = board_s
        self.board_times_s: list[float] = []
        self._read_at = time.monotonic()

    @property
    def name(self) -> str | None:
        """The port's device name (pyserial's ``name``): an :class:`OnboardEncoder` finds a simulated rig's clock
        by it."""
        name = getattr(self.port, "name", None)
        return name if isinstance(name, str) else None

    def read(self, size: int = 1) -> bytes:
        out = self.port.read(size)
        self._read_at = time.monotonic()
        return out

    def write(self, data: bytes) -> int:
        self.board_times_s.append(self.board_s() if self.board_s is not None else math.nan)
        self.port.write(data)
        self.written += len(data)
        self.writes.append((bytes(data[:1]), self.written, self.samples(), time.monotonic() - self._read_at))
        return len(data)

    def sent(self, command: bytes) -> list[tuple[int, int, float]]:
        """(bytes written up to it, samples received, s since the read) of each write of ``command``, in order."""
        return [(end, n, s) for c, end, n, s in self.writes if c == command]

    def sent_board_s(self, command: bytes) -> list[float]:
        """The board's time (s; NaN without ``board_s``) as the host began each write of ``command``, in order."""
        return [t for (c, *_), t in zip(self.writes, self.board_times_s, strict=True) if c == command]


class HilFingerScans:
    """The simulated operator's scans encoded on the Uno encoder image under simavr (module docstring); ``board``:
    the CALIBRATE (the classifier's range). Raises ScanError when the board does not start or is not the encoder
    image (:class:`rigctl.simulation.hil.HilError` for simavr's own failures)."""

    layout: SensorLayout = PAPER_FINGER

    def __init__(self, board: BoardRange, *, seed: int = 0, rig_config: RigConfig | None = None,
                 textures: TextureSet | None = None, timeout_s: float = 60.0) -> None:
        import serial

        from rigctl.simulation.hil import HilRig

        self.operator = SimulatedOperator(seed=seed, rig_config=rig_config, textures=textures)
        self.textures = self.operator.textures
        self.seed = int(seed)
        self.board, self.timeout_s = board, float(timeout_s)
        self._axis: PlateAxis = plate_axis_of(self.operator)
        #: every scan's readings as the board converted them (:class:`PlayedScan`), in order
        self.played: list[PlayedScan] = []
        self.hil = HilRig(rig_config, seed=seed, live=False, uno_image="uno_encoder").start()
        try:
            self.port = serial.Serial(self.hil.taxel_port, wire.TAXEL_BAUD, timeout=0.02)
            self.banner = read_banner(self.port, 30.0)
        except BaseException:
            self.hil.close()
            raise

    def touch_ends(self) -> tuple[np.ndarray, np.ndarray]:
        """The operator's touches of the plate's two ends (the rig calibrates its axis from them)."""
        return self.operator.touch_ends()

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """The operator's pass for ``planned``, played to the board and encoded there. Raises ScanError."""
        t_origin = self.operator.clock_s
        raw = self.operator.scan(planned, stop=stop)
        if raw is None:
            return None
        x = np.clip(raw.taxels[:, :wire.ENC_N_TAXELS], 0, wire.ADC_MAX).astype(np.uint16)
        ok = np.all(np.isfinite(raw.tracker_xyz), axis=1) if raw.tracker_xyz is not None else np.zeros(0, bool)
        t_pass = np.asarray(raw.tracker_time_s, np.float64)[ok] - t_origin
        along = self._axis.along_mm(raw.tracker_xyz[ok]) if raw.tracker_xyz is not None else np.zeros(0)
        wave = np.concatenate([x, np.repeat(x[-1:], TAIL_ROWS, axis=0)])
        self.hil.play_waveform(np.concatenate([wave, wave], axis=1))
        t_played = time.monotonic()
        noted = NotingPort(self.port)
        enc = OnboardEncoder(noted)
        noted.samples = lambda: enc.samples
        starts = len(self.hil.encoder_start_rows)
        first: list[int] = []
        view: list[tuple[float, int]] = []

        def started(t_sent: float) -> float:
            deadline = time.monotonic() + START_TIMEOUT_S
            while len(self.hil.encoder_start_rows) <= starts:
                if time.monotonic() > deadline:
                    raise ScanError("the board under simavr did not report its first encoded row")
                time.sleep(0.002)
            first.append(self.hil.encoder_start_rows[starts])
            return first[0] / 1000.0

        def now() -> float:  # the board's clock: the row it converts (its encoded samples once it encodes)
            if first and enc.first_sample is not None:
                return (first[0] + enc.first_sample + enc.samples) / 1000.0
            row, wall = self.hil.playing_row(), time.monotonic() - t_played
            # simavr runs at most in real time: a row ahead of the wall clock is the last waveform's (its reply before
            # the new one began), not this one's
            return wall if row is None or row / 1000.0 > wall + 0.05 else row / 1000.0

        def motion() -> tuple[np.ndarray, np.ndarray]:
            n = int(np.searchsorted(t_pass, now(), side="right"))
            return t_pass[:n], along[:n]

        got = encode_pass(enc, self.board, motion, now=now, started=started, stop=stop, timeout_s=self.timeout_s,
                          on_encode=lambda t, k: view.append((t, k)))
        if got is None:
            return None
        t0, scan = got
        written = dict(zip(enc.speed_windows, ((n, s) for _, n, s in noted.sent(wire.EncoderCommand.SPEED.value))))
        speeds = tuple(written.get(w, (WINDOW_SAMPLES * (w + 2) + 1, math.nan)) for w in range(len(enc.speeds_sent)))
        stop_sent = [(n, s) for _, n, s in noted.sent(wire.UnoCommand.STOP.value)][0]
        first_row = first[0] + (enc.first_sample or 0)
        self.played.append(PlayedScan(wave, first_row, int(scan.counts.samples), view[-1][0], speeds, stop_sent,
                                      first[0], view[-1][1]))
        return onboard_raw_scan(t_pass, along, t0, onboard_encoding(scan, self.layout.sample_rate_hz), self.layout,
                                {**raw.attrs, "taxels_from": "encoded on the Uno encoder image under simavr",
                                 "onboard_crc_errors": int(enc.parser.crc_errors),
                                 "onboard_late_start_samples": int(scan.late_start)})

    def describe(self) -> dict[str, Any]:
        return {**self.operator.describe(), "kind": "simulated_operator_hil_onboard_encoder",
                "taxels": "encoded on board (uno_encoder under simavr)", "taxel_board": dict(self.banner),
                "onboard_taxel_min": self.board.taxel_min.tolist(), "onboard_taxel_max": self.board.taxel_max.tolist(),
                "onboard_k": self.board.k}

    def close(self) -> None:
        try:
            self.port.close()
        finally:
            self.hil.close()
