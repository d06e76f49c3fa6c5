"""Trials rendered in worker processes reach the writer through shared-memory slots unchanged, a trial too long
for a slot through the pipe, and the slot file is removed afterwards."""

from __future__ import annotations

import math
import multiprocessing as mp
import os

import numpy as np
import pytest

from rigctl.simulation import dataset, trial_slots
from rigctl.simulation.model import RigConfig
from rigctl.simulation.trial_slots import TrialSlots, init_worker_slots


def test_worker_trials_arrive_unchanged_in_plan_order(tmp_path):
    nan = math.nan
    # 2 s trials (2000 samples) fit a 2500-sample slot; 6 s trials (6000) do not and go through the pipe
    rows = [(i, "ACLP"[i % 4], 120.0 if i % 3 else 40.0, 500.0, 2.0 if i % 3 else 6.0, nan, nan) for i in range(11)]
    cfg = RigConfig().to_dict()
    dataset._init_worker(cfg, 7)
    expected = {r[0]: dataset._render_planned(r)[1] for r in rows}
    with TrialSlots(2500, n_blocks=2, block=3, directory=str(tmp_path)) as slots:
        path = slots.path
        assert os.path.getsize(path) == 2 * 3 * 2500 * (36 + 2 + 1 + 8)
        ctx = mp.get_context("spawn")
        with ctx.Pool(2, initializer=init_worker_slots,
                      initargs=(*slots.initargs, dataset._render_planned, dataset._init_worker, (cfg, 7))) as pool:
            got = []
            for tid, data, _ in slots.results(pool, rows):
                want = expected[tid]
                for name in ("taxels", "seq", "flags", "host_time_s", "force_g", "force_time_s", "speed_mm_s",
                             "speed_time_s"):
                    a, b = getattr(data, name), getattr(want, name)
                    assert a.dtype == b.dtype, name
                    np.testing.assert_array_equal(a, b, err_msg=f"trial {tid} {name}")
                assert data.attrs == want.attrs
                got.append(tid)
    assert got == [r[0] for r in rows]  # plan order, every trial once
    assert not os.path.exists(path)


def test_slot_files_of_dead_generators_are_removed(tmp_path):
    import subprocess
    import sys

    from rigctl.simulation.trial_slots import remove_stale_slot_files

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"rigctl-trials-{int(dead.stdout)}-abc.slots"
    live = tmp_path / f"rigctl-trials-{os.getpid()}-def.slots"
    other = tmp_path / "rigctl-trials-notapid-x.slots"
    for p in (stale, live, other):
        p.write_bytes(b"x")
    with TrialSlots(10, n_blocks=1, block=1, directory=str(tmp_path)) as slots:
        assert os.path.basename(slots.path).startswith(f"rigctl-trials-{os.getpid()}-")
        assert not stale.exists() and live.exists() and other.exists()
    assert remove_stale_slot_files(str(tmp_path)) == []


class _InlinePool:
    """A pool that runs each task at once in this process (the slot file is the same mapping either way)."""

    class _Done:
        def __init__(self, value):
            self.value = value

        def get(self):
            return self.value

    def apply_async(self, fn, args):
        return self._Done(fn(*args))


def test_slots_follow_the_layout_nine_channels_at_100_hz(tmp_path):
    from rigctl.core import SensorLayout, TrialData
    from rigctl.simulation.trial_slots import render_into_slots, sample_bytes

    layout = SensorLayout.grid(3, 3, 1, sample_rate_hz=100.0)
    rng = np.random.default_rng(0)
    made = {}

    def render(row):
        tid, n = row
        made[tid] = TrialData(taxels=rng.integers(0, 1024, (n, 9)), layout=layout, attrs={"k": tid})
        return tid, made[tid]

    rows = [(i, 40 + 7 * i) for i in range(7)]  # trial 6 (82 samples) is longer than a slot: the pipe path
    with TrialSlots(80, n_blocks=2, block=2, directory=str(tmp_path), layout=layout) as slots:
        assert sample_bytes(9) == 29 and os.path.getsize(slots.path) == 2 * 2 * 80 * 29
        init_worker_slots(*slots.initargs, render, lambda: None, ())
        got = []
        for tid, data, _ in slots.results(_InlinePool(), rows):
            assert data.layout == layout and data.rate_hz == 100.0 and data.taxels.shape == (40 + 7 * tid, 9)
            np.testing.assert_array_equal(data.taxels, made[tid].taxels)
            np.testing.assert_array_equal(data.host_time_s, np.arange(data.n_samples) / 100.0)
            assert data.attrs == {"k": tid}
            got.append(tid)
        assert got == list(range(7))
        # a model rendering another channel count than the slots hold is an error, not a garbled trial
        init_worker_slots(*slots.initargs, lambda row: (0, TrialData(taxels=np.zeros((5, 18)))), lambda: None, ())
        with pytest.raises(ValueError, match="18 channels; the slots hold 9"):
            render_into_slots(([0], [(0, 5)]))
        trial_slots._STATE.clear()  # this process's mapping of the slot file
