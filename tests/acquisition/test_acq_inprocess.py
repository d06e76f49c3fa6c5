"""The runner and the load-cell calibration on the in-process backend (rigctl.rigs.open_rig("inprocess"): the
controller logic and the physical model in this process, on a simulated clock, no ptys): a protocol recorded into a
session file and a calibration with a known mass, each in a few seconds of wall time."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigctl.acquisition import calibration
from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core import PAPER_SENSOR, DrumController, MassPlacer, PlateMounter, RigBackend, TaxelSource
from rigctl.devices.wire import FrameFlag, HoldingRegister
from rigctl.rigs import open_rig
from rigctl.simulation.model import MechanicsConfig, RigConfig
from rigctl.storage.session import open_session

TRUE_COUNTS_PER_G = 380.0


@pytest.fixture
def rig(tmp_path):
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=TRUE_COUNTS_PER_G))
    with open_rig("inprocess", config=cfg, seed=5, host_config_path=tmp_path / "rig.json") as r:
        yield r


def test_the_inprocess_backend_implements_the_seams(rig):
    assert isinstance(rig.backend, RigBackend) and isinstance(rig.backend, MassPlacer)
    assert isinstance(rig.drum, DrumController) and isinstance(rig.stream, TaxelSource)
    assert isinstance(rig.backend.mounter, PlateMounter)
    assert rig.mode == "inprocess" and rig.layout == PAPER_SENSOR


def test_a_protocol_recorded_inprocess(rig, tmp_path):
    proto = parse_protocol('name = "inproc"\ntextures = ["A", "L"]\nspeeds_mm_s = [60, 120]\nforces_g = [300]\n'
                           'trials_per_condition = 2\nduration_s = 0.5\n[settle]\nsettle_time_ms = 50\n')
    out = tmp_path / "s.h5"
    events = []
    summary = run_protocol(proto, out, rig=rig, progress=events.append)
    assert summary.ok and summary.recorded == 8 and summary.dropped_frames == 0
    # progress events: the protocol's stage, a message as each trial starts (done unchanged), then its count
    assert {e.stage for e in events} == {"inproc"} and {e.total for e in events} == {8}
    assert [e.done for e in events] == [0] + [n for k in range(8) for n in (k, k + 1)]
    assert events[1].message == "A 60 mm/s 300 g"
    with open_session(out) as s:
        assert [str(t) for t in s.plan["texture"]] == ["A"] * 4 + ["L"] * 4
        assert s.layout == PAPER_SENSOR
        for tid in range(8):
            t = s.trial(tid)
            assert t.taxels.shape == (500, 18)
            assert t.flags[0] & FrameFlag.SYNC_IN  # the trial starts at the drum's index mark
            assert np.all(np.diff(t.seq.astype(int)) == 1)
            assert abs(t.attrs["force_mean_g"] - 300) < 15
            assert abs(t.attrs["speed_mean_mm_s"] - s.plan["speed_mm_s"][tid]) < 3
        smooth, wave = s.trial(0).taxels.astype(float), s.trial(4).taxels.astype(float)
    # the wave plate modulates the taxels along the plate; the smooth plate does not
    assert wave[:, :9].std(axis=0).mean() > 3 * smooth[:, :9].std(axis=0).mean()


def test_loadcell_calibration_inprocess(rig, tmp_path):
    cfg = tmp_path / "rig.json"
    place, remove = calibration.simulated_mass(rig)
    rig.drum.set_loadcell_scale(400.0)
    result = calibration.calibrate_loadcell(rig.drum, 500.0, place_mass=place, remove_mass=remove,
                                            n_readings=10, interval_s=0.0, settle_s=0.1, config_file=cfg)
    assert abs(result.counts_per_g - TRUE_COUNTS_PER_G) / TRUE_COUNTS_PER_G < 0.01
    assert rig.drum.read_holding(HoldingRegister.LOADCELL_SCALE_X100) == result.scale_x100
    assert abs(result.check_force_g - 500.0) < 5
    rig.drum.clock.sleep(0.1)  # the mass is off: the HX711 settles 4 conversion periods later (50 ms at 80 SPS)
    assert abs(rig.drum.read_status().force_g) < 5
    assert json.loads(cfg.read_text())["loadcell"]["scale_x100"] == result.scale_x100


def test_labels_outside_the_rigs_set_are_refused(rig):
    with pytest.raises(ValueError, match="not in the texture set"):
        rig.mount_texture("Z")
