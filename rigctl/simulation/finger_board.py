"""The simulated operator's finger as a taxel board on a pty (``rigctl sim operator --lsl NAME --taxel-board``).

A :class:`rigctl.simulation.virtual_uno.VirtualUno` streaming the paper's 3x3 finger (``PAPER_FINGER``: its banner
announces ``layout=3x3x1``) at 1 kHz on its own real-time clock, each frame the physical sensor model's reading at
the place the finger is at that moment: :meth:`SimulatedFingerBoard.follow` hands it each pass the tracker publisher
plays (:func:`rigctl.simulation.operator.publish_tracker`'s ``on_pass``), so the board's frames and the tracker's
samples describe one motion on one clock. The host reads it as it reads a real finger's board
(``--taxel-port PORT``: :class:`rigctl.devices.finger_board.BoardFingerScans`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from rigctl.core.sensor import PAPER_FINGER
from rigctl.simulation.model import RigConfig, SensorModel
from rigctl.simulation.textures import get_texture
from rigctl.simulation.virtual_uno import VirtualUno

__all__ = ["SimulatedFingerBoard"]

#: the finger's press while it touches the plate, g (the handheld protocols' intended press)
PRESS_G = 500.0
#: how often the board's clock hands out frames, s (a batch of frames rendered at once)
TICK_S = 0.01


class SimulatedFingerBoard:
    """The finger's taxel board (module docstring) on a pty at ``link`` (or a fresh one: :attr:`path`); ``clock()``
    is the clock of the passes' times (``pylsl.local_clock``: on Linux the same monotonic clock as
    ``time.monotonic``). Off a pass the finger is lifted (no press)."""

    def __init__(self, link: str | None = None, *, clock: Callable[[], float], seed: int = 0,
                 rig_config: RigConfig | None = None) -> None:
        self.clock = clock
        self.layout = PAPER_FINGER
        self.sensor = SensorModel((rig_config or RigConfig()).sensor)
        self._rng = np.random.default_rng([seed, 3740])
        self._lock = threading.Lock()
        self._pass: tuple[str, np.ndarray, np.ndarray] | None = None
        self._frames(1)  # the sensor model's kernels compiled or loaded now, not in the board's first tick
        self.board = VirtualUno(link, layout=self.layout, seed=seed)
        self.board.run_paced(self._frames, tick_s=TICK_S)

    @property
    def path(self) -> str:
        """The port a client opens."""
        return self.board.path

    def follow(self, texture: str, t: np.ndarray, along_mm: np.ndarray) -> None:
        """The finger's next pass: along plate ``texture``, at positions ``along_mm`` (k,) mm at times ``t`` (k,) s
        of :attr:`clock`."""
        with self._lock:
            self._pass = (str(texture), np.asarray(t, np.float64), np.asarray(along_mm, np.float64))

    def _frames(self, n: int) -> tuple[np.ndarray, None]:
        """The board's next ``n`` frames: the sensor model at the finger's place at each frame's time."""
        now = self.clock()
        times = now - (n - 1 - np.arange(n)) / self.layout.sample_rate_hz
        with self._lock:
            current = self._pass
        if current is None:
            return self.sensor.render(get_texture("A"), np.zeros(n), 0.0, self._rng)[:, :self.layout.n_channels], None
        texture, t, along = current
        pos = np.interp(times, t, along)
        force = np.where((times >= t[0]) & (times <= t[-1]), PRESS_G, 0.0)
        taxels = self.sensor.render(get_texture(texture), pos, force, self._rng)
        return np.ascontiguousarray(taxels[:, :self.layout.n_channels]), None

    def close(self) -> None:
        self.board.close()
