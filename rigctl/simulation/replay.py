"""Replay sources: the simulated Uno streams recorded signals instead of the physical model.

:class:`FabricSlideReplay` streams the FabricSlide recordings (``../shared/data/fabricslide``, see
:mod:`rigctl.storage.fabricslide`): each recording resampled onto a 1 ms grid from its timestamps (linear
interpolation, the first sample of a repeated timestamp kept), its 16 taxels on channels 0-15, channels 16-17 at a
constant level, mapped to 10 bits with ``adc = clip(rint(counts * scale + offset), 0, 1023)`` (scale 1, offset 0 by
default), one recording after the other in file-name order, looping forever.

:meth:`FabricSlideReplay.expected_samples` gives the exact samples the stream starts with, computed independently of
the streaming state, so a test can prove that what the host recorded equals the replayed source sample for sample.

Used by :class:`rigctl.simulation.rig.SimulatedRig` (``source=FabricSlideReplay(dir)``), which pulls
``read(n) -> (n, 18) uint16`` once per physics tick.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Iterator

import numpy as np

from rigctl.storage.fabricslide import (
    CHANNEL_PRESENT,
    DEFAULT_OFFSET,
    DEFAULT_SCALE,
    FILL_COUNTS,
    Recording,
    list_files,
    read_recording,
    recording_adc,
)

N_TAXELS = 18


class FabricSlideReplay:
    """A looping taxel source streaming FabricSlide recordings at 1 kHz. Thread-safe.

    Parameters
    ----------
    directory : path
        The FabricSlide subset (``fabric/`` and optionally ``board/``).
    include_board : bool
        Also replay the Board10mm recordings (after the fabrics).
    pattern : str
        Glob of file names to replay (e.g. ``"Canvas_F120_*"``); default all.
    scale, offset : float
        The linear 10-bit map ``adc = clip(rint(counts * scale + offset), 0, 1023)``.
    fill : int
        ADC counts on the absent channels 16 and 17.
    loop : bool
        Start again at the first recording after the last one (otherwise :meth:`read` raises EOFError at the end).

    Attributes
    ----------
    files : list of Path
        The replayed files, in order.
    channel_present : (18,) bool
        True for channels 0-15.

    Raises
    ------
    FileNotFoundError
        If the directory has no ``fabric/`` folder or no file matches ``pattern``.
    """

    def __init__(self, directory: str | Path, *, include_board: bool = False, pattern: str = "*.csv",
                 scale: float = DEFAULT_SCALE, offset: float = DEFAULT_OFFSET, fill: int = FILL_COUNTS,
                 loop: bool = True):
        self.directory = Path(directory)
        self.files = list_files(self.directory, include_board=include_board, pattern=pattern)
        if not self.files:
            raise FileNotFoundError(f"no FabricSlide files matching {pattern!r} under {self.directory}")
        self.scale, self.offset, self.fill, self.loop = float(scale), float(offset), int(fill), bool(loop)
        self.channel_present = CHANNEL_PRESENT.copy()
        self._lock = threading.Lock()
        self._blocks = self._iter_blocks()
        self._block = np.empty((0, N_TAXELS), np.uint16)
        self._pos = 0
        self.samples_served = 0
        self.current_file: Path | None = None

    # -- the stream ----------------------------------------------------------------------------------------------
    def _adc(self, rec: Recording) -> np.ndarray:
        return recording_adc(rec, scale=self.scale, offset=self.offset, fill=self.fill)

    def _iter_blocks(self, *, track: bool = True) -> Iterator[np.ndarray]:
        while True:
            for path in self.files:
                if track:
                    self.current_file = path
                yield self._adc(read_recording(path))
            if not self.loop:
                return

    def read(self, n: int) -> np.ndarray:
        """The next ``n`` samples of the stream.

        Returns
        -------
        (n, 18) uint16
            ADC counts; channels 16-17 = ``fill``.

        Raises
        ------
        EOFError
            With ``loop=False``, when the last recording is exhausted (the samples up to the end are lost).
        """
        n = int(n)
        out = np.empty((n, N_TAXELS), dtype=np.uint16)
        with self._lock:
            filled = 0
            while filled < n:
                if self._pos >= self._block.shape[0]:
                    try:
                        self._block = next(self._blocks)
                    except StopIteration:
                        raise EOFError("end of the FabricSlide recordings (loop=False)") from None
                    self._pos = 0
                    continue
                k = min(n - filled, self._block.shape[0] - self._pos)
                out[filled:filled + k] = self._block[self._pos:self._pos + k]
                self._pos += k
                filled += k
            self.samples_served += n
        return out

    #: alias of :meth:`read`
    next_samples = read

    def __call__(self, n: int) -> np.ndarray:
        return self.read(n)

    def rewind(self) -> None:
        """Start the stream again at the first sample of the first recording."""
        with self._lock:
            self._blocks = self._iter_blocks()
            self._block = np.empty((0, N_TAXELS), np.uint16)
            self._pos = 0
            self.samples_served = 0

    # -- ground truth --------------------------------------------------------------------------------------------
    def expected_samples(self, n: int, start: int = 0) -> np.ndarray:
        """Samples ``start`` ... ``start + n - 1`` of the stream, computed afresh (independent of :meth:`read`).

        Returns
        -------
        (n, 18) uint16
            Exactly what :meth:`read` returns for those stream positions (after :meth:`rewind` or construction).
        """
        n, start = int(n), int(start)
        out = np.empty((n, N_TAXELS), dtype=np.uint16)
        filled = 0
        skip = start
        for block in self._iter_blocks(track=False):
            if skip >= block.shape[0]:
                skip -= block.shape[0]
                continue
            k = min(n - filled, block.shape[0] - skip)
            out[filled:filled + k] = block[skip:skip + k]
            filled += k
            skip = 0
            if filled >= n:
                return out
        raise EOFError(f"the recordings hold fewer than {start + n} samples (loop=False)")

    def recording_lengths(self) -> list[int]:
        """Samples of each file at 1 kHz (in replay order)."""
        return [self._adc(read_recording(p)).shape[0] for p in self.files]
