"""rigctl.storage.kept_rows: the rows the validator read, given once to the next read instead of the file; kept only
when all of them fit the budget; a block freed once every trial in it was taken."""

from __future__ import annotations

import h5py
import numpy as np

from rigctl.storage.kept_rows import KeptRows


def _file(tmp_path):
    rows = np.arange(60 * 3, dtype=np.uint16).reshape(60, 3)
    f = h5py.File(tmp_path / "rows.h5", "w")
    f["taxels"] = rows
    return f, rows


def test_kept_trials_come_from_memory_once_the_others_from_the_file(tmp_path):
    f, rows = _file(tmp_path)
    with f:
        kept = KeptRows()
        kept.keep(10_000)
        starts, lengths = np.array([0, 10, 30]), np.array([10, 5, 20])
        block = np.concatenate([rows[0:10], rows[10:15], rows[30:50]]).copy()
        block[:] += 1000  # marked: what comes from memory, not the file
        kept.offer(starts, lengths, block)
        out = np.zeros((35, 3), np.uint16)
        kept.read(f["taxels"], np.array([30, 50, 0]), np.array([20, 5, 10]), out)
        np.testing.assert_array_equal(out[:20], rows[30:50] + 1000)  # kept
        np.testing.assert_array_equal(out[20:25], rows[50:55])  # never offered: the file's
        np.testing.assert_array_equal(out[25:], rows[0:10] + 1000)
        assert kept._blocks[0][0] is not None  # trial (10, 5) not taken yet: the block stays
        again = np.zeros((20, 3), np.uint16)
        kept.read(f["taxels"], np.array([30]), np.array([20]), again)  # taken once: the file's now
        np.testing.assert_array_equal(again, rows[30:50])
        kept.read(f["taxels"], np.array([10]), np.array([5]), again[:5])
        assert kept._blocks[0][0] is None  # every trial of the block taken: freed


def test_nothing_is_kept_beyond_the_budget_or_without_one(tmp_path):
    f, rows = _file(tmp_path)
    with f:
        for budget, expected in ((0, 0), (10 * 3 * 2 - 1, 0), (10 * 3 * 2, 10 * 3 * 2)):
            kept = KeptRows()
            kept.keep(budget)
            kept.expect(10 * 3 * 2)
            kept.offer(np.array([0]), np.array([10]), rows[0:10] + 1)
            assert sum(b[0].nbytes for b in kept._blocks) == expected
        kept.expect(10_000)  # all the rows to come do not fit: nothing is kept, what was is dropped
        assert not kept._blocks
        out = np.zeros((10, 3), np.uint16)
        kept.read(f["taxels"], np.array([0]), np.array([10]), out)
        np.testing.assert_array_equal(out, rows[0:10])
