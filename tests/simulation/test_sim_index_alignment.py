"""Recorded trials start at the drum's index mark (Rig.record_trial on the simulated rig: real ptys, pymodbus,
pyserial), like the simulated dataset's trials: two recordings of one texture line up in their 100 ms windows."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.protocol import PlannedTrial
from rigctl.devices import wire
from rigctl.rigs import open_rig
from rigctl.simulation.dataset import render_trial
from rigctl.simulation.model import RigConfig


def _windows(taxels, taxel=4, window=100):
    x = taxels[:, taxel].astype(float)
    return x[: x.size // window * window].reshape(-1, window).mean(axis=1)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    cfg_path = tmp_path_factory.mktemp("cfg") / "rig.json"
    # unpaced: the rig runs as far as the host's waits grant on its one clock (every wait of the recording is of it)
    with open_rig("sim", config=RigConfig(), seed=11, host_config_path=cfg_path, paced=False) as rig:
        rig.mount_texture("L")
        trials = [rig.record_trial(PlannedTrial(i, "L", 120.0, 500.0, 1.0)) for i in range(2)]
    return trials


def test_recorded_trials_start_at_the_index_frame(recorded):
    for t in recorded:
        assert t.n_samples == 1000
        assert t.attrs["aligned_to_index"] is True and t.attrs["index_wait_frames"] >= 0
        assert t.flags[0] & wire.FrameFlag.SYNC_IN
        # one revolution is 314 mm = 2.6 s at 120 mm/s: no other index pulse within the 1 s trial
        assert int(np.count_nonzero(t.flags & wire.FrameFlag.SYNC_IN)) == 1


def test_recorded_trials_of_a_texture_are_phase_aligned(recorded):
    a, b = (_windows(t.taxels) for t in recorded)
    assert a.std() > 30  # the wave plate modulates the window means
    # the same windows of the same plate: differences are small next to the modulation across windows
    assert np.abs(a - b).mean() < 0.25 * np.abs(a - a.mean()).mean()
    # and they match a simulated-dataset trial of the same condition (which starts at the index too)
    sim = _windows(render_trial("L", 120.0, 500.0, rng=np.random.default_rng(0), duration_s=1.0).taxels)
    assert np.corrcoef(a, sim)[0, 1] > 0.8
