"""The simulated HX711's rate, chosen from the command line (``--hx711-rate``) or the rig config (issue 55 item 6;
docs/config.md)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from rigctl.acquisition.rigconfig import update_rig_config
from rigctl.cli import main
from rigctl.devices.drum import default_force_loop
from rigctl.operations import RigSource
from rigctl.rigs import open_rig


def test_hx711_rate_from_the_command_line_reaches_the_simulated_board(tmp_path):
    """``rigctl doctor --inprocess --hx711-rate 10``: the simulated HX711 converts at 10 SPS (the controller measures
    it at boot), and with no force_loop in the rig config the controller is set for 80: the check names the RATE pin.
    The default is 80."""
    config = tmp_path / "rig.json"
    args = ["doctor", "--inprocess", "--check", "hx711-rate", "--json", "--config", str(config)]
    r = CliRunner().invoke(main, [*args, "--hx711-rate", "10"])
    check = json.loads(r.stdout)["checks"][0]
    assert check["values"]["hx711_rate_sps"] == pytest.approx(10, rel=0.02), r.output
    assert check["status"] == "fail" and "RATE pin" in check["fix"]
    r = CliRunner().invoke(main, args)
    check = json.loads(r.stdout)["checks"][0]
    assert check["status"] == "pass" and check["values"]["hx711_rate_sps"] == pytest.approx(80, rel=0.02), r.output


def test_hx711_rate_from_the_rig_config(tmp_path):
    """A rig config whose force_loop is for a 10 SPS board makes the simulated board one (the model's rate and what
    the controller measures); an explicit rate or model config wins."""
    from rigctl.simulation.model import RigConfig

    host = tmp_path / "rig.json"
    update_rig_config(host, force_loop=default_force_loop(10).to_dict())
    with open_rig("inprocess", seed=1, host_config_path=host, refuse_fault=False) as rig:
        assert rig.backend.engine.config.mechanics.hx711_rate_sps == 10.0
        assert rig.drum.read_status().hx711_rate_sps == pytest.approx(10, rel=0.02)
    with open_rig("inprocess", seed=1, host_config_path=host, refuse_fault=False, hx711_rate_sps=80) as rig:
        assert rig.backend.engine.config.mechanics.hx711_rate_sps == 80.0
    with open_rig("inprocess", seed=1, host_config_path=host, refuse_fault=False, config=RigConfig()) as rig:
        assert rig.backend.engine.config.mechanics.hx711_rate_sps == 80.0


def test_hx711_rate_is_refused_for_a_real_board(tmp_path):
    """A real board's rate is its RATE pin: --hx711-rate with --drum-port is a usage error in one line (exit 2);
    RigSource refuses it too, and a rate other than 10 or 80."""
    r = CliRunner().invoke(main, ["acquire", "quick_check", "--drum-port", "/dev/null", "--taxel-port", "/dev/null",
                                  "--hx711-rate", "10", "--plates", "skip", "--out", str(tmp_path / "a.h5")])
    assert r.exit_code == 2 and "RATE pin" in r.output and "Traceback" not in r.output, r.output
    r = CliRunner().invoke(main, ["doctor", "--inprocess", "--hx711-rate", "40"])
    assert r.exit_code == 2
    with pytest.raises(ValueError, match="RATE pin"):
        RigSource("hardware", drum_port="a", taxel_port="b", hx711_rate_sps=10)
    with pytest.raises(ValueError, match="10 or 80"):
        RigSource("inprocess", hx711_rate_sps=40)
    assert RigSource("hil", hx711_rate_sps=10).open_options()["hx711_rate_sps"] == 10
