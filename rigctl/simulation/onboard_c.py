"""The on-board encoder's own C built for the host and loaded through cffi: the Uno encoder image's sample ring
(``arduino/common/sa_ring.c``) and integer SA encoder (``common/sa_encoder.c`` with -DSA_FIXED), with the host-only
glue ``host_model/onboard_host.c`` (the calls ``uno_taxel.cpp`` makes, in its order). One source: nothing of the
board's logic is copied into Python; the image runs the same files under simavr (:mod:`rigctl.simulation.hil_finger`).

:class:`BoardModel` is that board without its UART and its clock: the caller pushes each 1 ms sample, and says when
the host's ARM, ENCODE, SPEED and FINISH reach it. It models fast (a scan in milliseconds) what the image does when
the host starts it late, e.g. on 100 scans (``scripts/onboard_entry.py``); the image's timing (its loop, the link)
stays simavr's.

Shipped in a platform wheel or built like the drum controller's library (:mod:`rigctl.simulation.host_build`: the
host's C compiler, a cache folder named by the sources' digest, ``onboard/`` inside it; HostBuildError without a
compiler).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rigctl import firmware
from rigctl.simulation import host_build, mega_c

__all__ = ["SOURCES", "BoardModel", "BoardResult", "build", "load"]

_ONBOARD = host_build.LIBRARIES["onboard"]
#: the C sources, relative to the firmware source folder
SOURCES = _ONBOARD.sources
_N_TAXELS, _N_WINDOWS = 9, 20


def build(src: Path | None = None) -> Path:
    """Build the library from ``src`` (default the installed firmware sources) unless it is there; returns its
    folder. HostBuildError."""
    src = src or firmware.sources()
    out = mega_c.build_dir(src, files=(*SOURCES, *_ONBOARD.headers), flags=_ONBOARD.flags) / "onboard"
    return host_build.build_library("onboard", src, out)


@functools.cache
def load() -> tuple[Any, Any]:
    """``(ffi, lib)`` of the library the installed package ships for its sources, else of :func:`build` (at first use
    in the process). HostBuildError."""
    import cffi

    ffi = cffi.FFI()
    ffi.cdef(str(_ONBOARD.cdef))
    folder = host_build.shipped("onboard", firmware.sources()) or build()
    return ffi, ffi.dlopen(str(folder / _ONBOARD.lib))


@dataclass(frozen=True)
class BoardResult:
    """One scan as the board encoded it: ``start`` the sample (since ARM) it began at, ``raster`` (n, 9) uint8 its
    spikes per encoded sample, ``counts`` (9, 20) its counts frame, ``held`` windows scaled with the last speed,
    ``dropped`` samples its full ring lost, ``depth_max`` the ring's deepest while encoding."""

    start: int
    raster: np.ndarray
    counts: np.ndarray
    held: int
    dropped: int
    depth_max: int


class BoardModel:
    """The encoder board's logic (module docstring) for one scan: :meth:`arm` (CALIBRATE and ARM: ``taxel_min``,
    ``taxel_max`` (9,) ADC counts, ``k``), :meth:`tick` per 1 ms sample (into the ring; the main loop encodes up to
    ``steps`` waiting samples after it: the board encodes ~1.5 samples per tick while it catches up), :meth:`begin`
    (ENCODE from a sample), :meth:`speed` (SPEED), :meth:`finish` (FINISH) -> :class:`BoardResult`."""

    def __init__(self) -> None:
        self.ffi, self.lib = load()
        self._buf = self.ffi.new("char[]", int(self.lib.onboard_host_sizeof()))
        self._b = self.ffi.cast("void *", self._buf)
        self._mask = self.ffi.new("uint16_t *")
        self._masks: list[int] = []
        self.start: int | None = None

    def arm(self, taxel_min: np.ndarray, taxel_max: np.ndarray, k: int = 100) -> None:
        """CALIBRATE and ARM: the ring from sample 0."""
        lo = np.ascontiguousarray(taxel_min, np.uint16)
        hi = np.ascontiguousarray(taxel_max, np.uint16)
        self.lib.onboard_host_arm(self._b, self.ffi.from_buffer("uint16_t[]", lo),
                                  self.ffi.from_buffer("uint16_t[]", hi), int(k))
        self._masks, self.start = [], None

    def tick(self, x: np.ndarray, steps: float = 1.0) -> None:
        """One 1 ms sample (9 ADC counts) into the ring, then up to ``steps`` (rounded down, at least 1) waiting
        samples encoded."""
        row = np.ascontiguousarray(x, np.uint16)
        self.lib.onboard_host_push(self._b, self.ffi.from_buffer("uint16_t[]", row))
        for _ in range(max(1, int(steps))):
            if not self.lib.onboard_host_step(self._b, self._mask):
                break
            self._masks.append(int(self._mask[0]))

    def begin(self, from_sample: int) -> int:
        """ENCODE from ``from_sample`` (since ARM; again: the board starts over); returns the sample it begins at."""
        self._masks = []
        self.start = int(self.lib.onboard_host_begin(self._b, int(from_sample) % 65536))
        return self.start

    @property
    def samples(self) -> int:
        """Samples encoded so far."""
        return len(self._masks)

    def speed(self, speed_cmm_s: int) -> int:
        """SPEED of the next window without one (0.01 mm/s); -1 when 2 already wait."""
        return int(self.lib.onboard_host_speed(self._b, int(speed_cmm_s)))

    def finish(self, speed_cmm_s: int) -> BoardResult:
        """FINISH: the waiting samples encoded, the last windows scaled; the counts frame."""
        while self.lib.onboard_host_step(self._b, self._mask):  # what FINISH encodes first, with its masks
            self._masks.append(int(self._mask[0]))
        self.lib.onboard_host_finish(self._b, int(speed_cmm_s))
        counts = np.zeros(_N_TAXELS * _N_WINDOWS, np.uint16)
        self.lib.onboard_host_counts(self._b, self.ffi.from_buffer("uint16_t[]", counts))
        masks = np.asarray(self._masks, np.uint16)
        raster = ((masks[:, None] >> np.arange(_N_TAXELS, dtype=np.uint16)) & 1).astype(np.uint8)
        return BoardResult(int(self.start or 0), raster, counts.reshape(_N_TAXELS, _N_WINDOWS).astype(np.int64),
                           int(self.lib.onboard_host_held(self._b)), int(self.lib.onboard_host_dropped(self._b)),
                           int(self.lib.onboard_host_depth_max(self._b)))
