"""The taxel rows the trial validator read, kept for the encoder's read: one read of a session's samples, not two.

``rigctl encode`` checks every trial with the validator (:func:`rigctl.storage.validate.usable_trials`, which reads
every trial's taxels: ADC range, byte copies, the checksums sealed with them) and then reads the usable trials'
taxels again for the encoder (:meth:`rigctl.storage.session_reader.SessionReader.read_taxels`). A session whose
taxels fit the memory the encoder keeps its readings in anyway can be read once: the encoder asks its session to
:meth:`KeptRows.keep` them (a byte budget), the validator offers each block of rows it read and checked
(:meth:`KeptRows.offer`), and the encoder's read takes each trial's rows from there (:meth:`KeptRows.read`), each
trial once: taken rows are dropped, and a block of rows is freed once every trial in it was taken. What the
validator checks and the rows the encoder gets are the same bytes either way; only schema 4 and 5 files (the
recording arrays) go this way.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rigctl.storage.session_recording import read_rows

__all__ = ["KeptRows"]


class KeptRows:
    """Rows of ``/recording/taxels`` read once and kept for one more read (see the module docstring). Nothing is
    kept until :meth:`keep` gives a budget."""

    def __init__(self) -> None:
        self._budget = 0
        self._blocks: list[Any] = []  # per block: [rows (n, n_ch) array, trials not yet taken]
        self._at: dict[tuple[int, int], tuple[int, int]] = {}  # (row start, rows) -> (block, first row in it)

    def keep(self, budget_bytes: int) -> None:
        """Keep the rows offered from now on, when all of them together fit ``budget_bytes`` (:meth:`expect`);
        0 drops whatever is kept and keeps nothing more."""
        self._budget = max(0, int(budget_bytes))
        if not self._budget:
            self._blocks, self._at = [], {}

    def expect(self, nbytes: int) -> None:
        """The rows about to be offered come to ``nbytes``: more than the budget, and none of them is kept."""
        if nbytes > self._budget:
            self.keep(0)

    def offer(self, starts: np.ndarray, lengths: np.ndarray, rows: np.ndarray) -> None:
        """Rows read back to back: trial ``i`` is ``rows[sum(lengths[:i]):][:lengths[i]]``, stored at row
        ``starts[i]`` of the file. Kept (the array itself, not a copy) while the budget lasts."""
        if not self._budget or rows.nbytes > self._budget:
            return
        self._budget -= rows.nbytes
        b, pos = len(self._blocks), 0
        self._blocks.append([rows, 0])
        for start, n in zip(np.asarray(starts).tolist(), np.asarray(lengths).tolist()):
            if (start, n) not in self._at:
                self._at[(start, n)] = (b, pos)
                self._blocks[b][1] += 1
            pos += n

    def read(self, ds: Any, starts: np.ndarray, lengths: np.ndarray, out: np.ndarray) -> None:
        """:func:`rigctl.storage.session_recording.read_rows` of the dataset ``ds`` (``/recording/taxels``) into
        ``out``, each trial kept taken from memory (and dropped) instead of the file."""
        if not self._at:
            read_rows(ds, starts, lengths, out)
            return
        pos = 0
        for start, n in zip(np.asarray(starts).tolist(), np.asarray(lengths).tolist()):
            where = self._at.pop((start, n), None)
            if where is None:
                read_rows(ds, np.array([start]), np.array([n]), out[pos:pos + n])
            else:
                b, at = where
                block = self._blocks[b]
                out[pos:pos + n] = block[0][at:at + n]
                block[1] -= 1
                if not block[1]:  # every trial of the block taken: freed
                    block[0] = None
            pos += n
