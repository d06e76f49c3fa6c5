"""A simulated serial motion board on a pty: the simulated operator's passes, sent in real time as the frames of
:mod:`rigctl.devices.motion` (``rigctl sim operator --serial``; ``--motion serial:PORT`` reads it).

The board samples the finger's position along the plate at the operator's tracker times (90-120 Hz, jitter and
dropouts: :func:`rigctl.simulation.operator.operator_passes`), stamps each frame with its own clock (microseconds,
running ``drift_ppm`` fast, from a random origin) and sends the position (an encoder), the velocity (an IMU: the
mean over the last 100 ms of the position) or both, as :attr:`VirtualMotionBoard.fields` says. Like an Arduino whose
DTR line resets it, it starts its stream when a client opens the port (:meth:`rigctl.simulation.pty.PtyEndpoint.
client_opened`), and again from the start at every later open: seq 0, the finger at rest at the plate's start.
:meth:`corrupt_frames` flips a bit in the next frames (the host counts CRC errors and drops them).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from rigctl.devices.motion import pack_motion_frame
from rigctl.simulation.operator import PASS_PROFILES, REST_S, SimulatedOperator, operator_passes, plate_axis_of
from rigctl.simulation.priority import board_thread
from rigctl.simulation.pty import PtyEndpoint

__all__ = ["VirtualMotionBoard", "BOOT_S"]

#: from a reset (the client's open) to the board's first frame, s (an Arduino's bootloader waits longer; the client's
#: open has flushed its input by then)
BOOT_S = 0.1


class VirtualMotionBoard:
    """The simulated motion board (module docstring); :attr:`path` is the port a client opens. Starts sending when a
    client opens it (``reset_on_open``; else at once), in a thread; :meth:`close` stops it.

    Parameters
    ----------
    link : a stable path for the port (a symlink to the pty), or None.
    seed : the operator's seed.
    fields : "position", "velocity" or "both".
    drift_ppm : how fast the board's clock runs against the host's, ppm.
    textures : the plates the operator passes along in turn.
    reset_on_open : start the stream (seq 0, the first pass) when a client opens the port, and again at each later
        open (a board reset by DTR); False: streaming from construction on (a board that was running before).
    profiles : the velocity profiles of the passes, in turn (:data:`rigctl.simulation.operator.PASS_PROFILES`).
    """

    def __init__(self, link: str | None = None, *, seed: int = 0, fields: str = "both", drift_ppm: float = 150.0,
                 textures: tuple[str, ...] = ("A", "B", "D", "L", "N"),
                 profiles: tuple[tuple[str, float, float], ...] = PASS_PROFILES, reset_on_open: bool = True) -> None:
        if fields not in ("position", "velocity", "both"):
            raise ValueError(f"fields must be position, velocity or both, not {fields!r}")
        self.fields, self.drift = fields, 1.0 + drift_ppm * 1e-6
        self.op = SimulatedOperator(seed=seed)
        self.port = PtyEndpoint(link, max_pending=256)  # a USB-serial chip's FIFO: no backlog while nobody reads
        self._textures, self._profiles, self.reset_on_open = textures, profiles, bool(reset_on_open)
        self.resets = 0
        self._axis = plate_axis_of(self.op)
        self._clock_origin_us = int(np.random.default_rng([seed, 3739]).integers(0, 2**32))
        self._corrupt = self._every = 0
        self.frames_sent = 0
        self.passes: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=board_thread(self._run), name="virtual-motion-board", daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        return self.port.path

    def corrupt_frames(self, n: int) -> None:
        """Flip one bit in each of the next ``n`` frames."""
        self._corrupt += int(n)

    def corrupt_every(self, n: int) -> None:
        """Flip one bit in every ``n``-th frame from now on (0: none)."""
        self._every = int(n)

    def _frame(self, seq: int, t_s: float, pos: float, vel: float) -> bytes:
        t_us = (self._clock_origin_us + int(t_s * self.drift * 1e6)) & 0xFFFFFFFF
        data = pack_motion_frame(seq, t_us, pos if self.fields != "velocity" else None,
                                 vel if self.fields != "position" else None)
        if self._corrupt or (self._every and seq % self._every == 0):
            self._corrupt = max(0, self._corrupt - 1)
            b = bytearray(data)
            b[9] ^= 0x10
            data = bytes(b)
        return data

    def _run(self) -> None:
        while self.reset_on_open and not self._stop.is_set() and not self.port.client_opened():
            self._stop.wait(0.01)  # in reset until a client opens the port
        while not self._stop.is_set():
            if self.reset_on_open:
                self._stop.wait(BOOT_S)
            self._stream()
            self.resets += 1

    def _stream(self) -> None:
        """Stream from the board's start (seq 0, the operator's first pass) until stopped or, with ``reset_on_open``,
        a client opens the port again."""
        t0 = time.monotonic()
        start, seq = 0.0, 0
        passes = operator_passes(SimulatedOperator(seed=self.op.seed), self._textures, self._profiles)  # from the start
        while not self._stop.is_set():
            label, t, xyz, _texture = next(passes)
            self.passes.append(label)
            rest = t[-1] + np.arange(1, int(REST_S * self.op.tracker_rate_hz)) / self.op.tracker_rate_hz
            along = self._axis.along_mm(xyz)
            t, along = np.concatenate([t, rest]), np.concatenate([along, np.full(rest.size, along[-1])])
            vel = (along - np.interp(t - 0.1, t, along)) / 0.1  # the mean over the last 100 ms
            for ti, p, v in zip(t, along, vel):
                due = t0 + start + ti
                while not self._stop.is_set() and time.monotonic() < due:
                    self._stop.wait(min(0.005, max(0.0, due - time.monotonic())))
                if self._stop.is_set() or self.reset_on_open and self.port.client_opened():
                    return
                self.port.write(self._frame(seq, start + ti, float(p), float(v)))
                seq = (seq + 1) & 0xFF
                self.frames_sent += 1
            start += float(t[-1]) + 1.0 / self.op.tracker_rate_hz

    def close(self) -> None:
        """Stop sending and close the port."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        self.port.close()
