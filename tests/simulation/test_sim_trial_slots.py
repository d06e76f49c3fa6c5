"""Trials rendered in worker processes reach the writer through shared-memory slots unchanged, a trial too long
for a slot through the pipe, and the slot file is removed afterwards."""

from __future__ import annotations

import math
import multiprocessing as mp
import os

import numpy as np

from rigctl.simulation import dataset
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
            for tid, data in slots.results(pool, rows):
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
