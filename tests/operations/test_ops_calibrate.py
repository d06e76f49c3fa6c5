"""Calibrating through the operator layer on the in-process rig: the load cell with the simulated mass (the result
stored and taken up by the rig at once), and the taxel normalisation from a live capture: refused while the drum is
idle (nothing stored), stored while it turns the textures under the pressed sensor."""

from __future__ import annotations

import pytest

from rigctl.acquisition.calibration import CalibrationError, load_rig_config
from rigctl.operations import RigSource, calibrate_loadcell, open_control, record_taxel_normalisation
from rigctl.simulation.model import MechanicsConfig, RigConfig

TRUE_COUNTS_PER_G = 380.0


@pytest.fixture
def control(tmp_path):
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=TRUE_COUNTS_PER_G))
    with open_control(RigSource("inprocess"), config=cfg, seed=6, host_config_path=tmp_path / "rig.json") as c:
        yield c


def test_loadcell_calibration_is_stored_and_taken_up(control, tmp_path):
    cfg = tmp_path / "rig.json"
    result = calibrate_loadcell(control, 500.0, config_file=cfg)
    assert abs(result.counts_per_g - TRUE_COUNTS_PER_G) / TRUE_COUNTS_PER_G < 0.02
    assert abs(result.check_force_g - 500.0) < 10
    assert load_rig_config(cfg)["loadcell"]["counts_per_g"] == pytest.approx(result.counts_per_g)
    assert control.host_config["loadcell"]["counts_per_g"] == pytest.approx(result.counts_per_g)


def test_taxel_normalisation_refused_idle_and_stored_while_running(control, tmp_path):
    cfg = tmp_path / "rig.json"
    with pytest.raises(CalibrationError, match="was the drum idle"):
        record_taxel_normalisation(control, 1.0, config_file=cfg)
    assert "taxel_normalisation" not in load_rig_config(cfg)
    control.mount_plate("L")
    control.run_at(80.0, 500.0)
    fractions = []
    stored = record_taxel_normalisation(control, 3.0, config_file=cfg, progress=fractions.append)
    control.stop()
    assert stored.norm.n_taxels == control.layout.n_channels and stored.norm.n_trials == 1
    assert fractions and fractions == sorted(fractions) and fractions[-1] <= 1.0
    block = load_rig_config(cfg)["taxel_normalisation"]
    assert block["taxel_min"] == [float(v) for v in stored.norm.taxel_min]
    assert control.taxel_normalisation() == block  # the rig carries it into later sessions
