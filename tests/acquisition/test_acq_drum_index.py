"""The drum index sensor in every trial's attributes (issue 22 item 3), on the in-process simulated rig: which
source marked the index, the drum speed the sensor measured, and a driver at another microstep setting flagged
(the simulated drum turns by the driver's real setting; rigctl.simulation.model.DrumConfig.driver_microsteps)."""

from __future__ import annotations

import logging
import math

import pytest
from click.testing import CliRunner

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.cli import main as cli
from rigctl.rigs import open_rig
from rigctl.simulation.model import DrumConfig, RigConfig
from rigctl.storage.session import open_session

PROTO = ('name = "index"\ntextures = ["A"]\nspeeds_mm_s = [120]\nforces_g = [300]\ntrials_per_condition = 3\n'
         'duration_s = 3.0\n[settle]\nsettle_time_ms = 50\n')


def _record(tmp_path, drum: DrumConfig):
    out = tmp_path / "s.h5"
    with open_rig("inprocess", config=RigConfig(drum=drum), seed=4, host_config_path=tmp_path / "rig.json") as rig:
        summary = run_protocol(parse_protocol(PROTO), out, rig=rig)
    assert summary.ok
    with open_session(out) as s:
        return out, [s.trial_attrs(t) for t in range(3)]


def test_a_well_set_driver_records_the_index_speed_beside_the_setpoint(tmp_path):
    _, attrs = _record(tmp_path, DrumConfig())
    assert all(a["index_source"] == "sensor" for a in attrs)
    assert all(a["drum_steps_per_rev_index"] == 3200 and not a["drum_speed_mismatch"] for a in attrs)
    assert all(a["drum_speed_index_mm_s"] == pytest.approx(120, rel=0.01) for a in attrs)  # every trial
    assert {a["drum_speed_index_method"] for a in attrs} == {"marks"}  # measured inside every trial


def test_a_driver_at_8_microsteps_is_flagged_and_warned(tmp_path, caplog):
    """Fails without the index sensor: the step count says 120 mm/s whatever the drum does."""
    with caplog.at_level(logging.WARNING, logger="rigctl.acquisition.rig"):
        out, attrs = _record(tmp_path, DrumConfig(driver_microsteps=8))
    assert all(a["drum_speed_mismatch"] for a in attrs)
    assert all(a["drum_steps_per_rev_index"] == pytest.approx(1600, abs=2) for a in attrs)
    assert all(a["drum_speed_index_mm_s"] == pytest.approx(240, rel=0.02) for a in attrs)
    assert "8 microsteps instead of 16" in attrs[0]["drum_speed_warning"]
    assert any("drum turned once every" in r.getMessage() for r in caplog.records)
    res = CliRunner().invoke(cli, ["info", str(out)])
    assert res.exit_code == 0 and "warning: trial 0: drum speed mismatch" in res.output


def test_without_an_index_sensor_the_step_count_is_the_source(tmp_path):
    _, attrs = _record(tmp_path, DrumConfig(index_sensor=False))
    assert all(a["index_source"] == "steps" and a["drum_steps_per_rev_index"] == 0 for a in attrs)
    # the speed-mark disc is a sensor of its own: the speed is still measured inside every trial
    assert all(a["drum_speed_index_method"] == "marks" and not a["drum_speed_mismatch"] for a in attrs)
    (tmp_path / "nodisc").mkdir()
    _, attrs = _record(tmp_path / "nodisc", DrumConfig(index_sensor=False, marks_per_rev=0))
    assert all(math.isnan(a["drum_speed_index_mm_s"]) and a["drum_mark_intervals"] == 0 for a in attrs)


def test_a_10sps_rig_opens_with_the_force_loop_of_its_rig_config(tmp_path, monkeypatch):
    """The rig config's force_loop block (this rig's HX711 rate and gains) reaches the controller when the rig opens;
    without it a 10 SPS board is refused, by name. With it, the HX711_RATE the controller latched at boot (before the
    host wrote the rate) is cleared as part of configuring the rig: logged as resolved by the rig config, not as an
    operator's acknowledgement, and nothing moves until the first press."""
    import json

    from rigctl.acquisition.rig import FaultAtOpen
    from rigctl.acquisition.rigconfig import update_rig_config
    from rigctl.acquisition.safety import Acknowledgement, safety_log_path
    from rigctl.core.drum import DrumState, Fault
    from rigctl.devices.drum import default_force_loop
    from rigctl.simulation.model import MechanicsConfig

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))  # this test's own rig log
    cfg = RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=10.0, contact_stiffness_g_per_mm=1000.0))
    host = tmp_path / "rig.json"
    with pytest.raises(FaultAtOpen, match="HX711_RATE: measured 10 SPS, the force loop set for 80 SPS.*RATE pin"):
        open_rig("inprocess", config=cfg, seed=2, host_config_path=host)
    loop = default_force_loop(10)
    update_rig_config(host, force_loop=loop.to_dict())
    assert json.loads(host.read_text())["force_loop"]["hx711_rate_sps"] == 10
    with open_rig("inprocess", config=cfg, seed=2, host_config_path=host) as rig:
        assert rig.drum.force_loop() == loop
        st = rig.drum.read_status()
        assert st.faults == Fault(0) and st.hx711_rate_sps == pytest.approx(10, rel=0.02)
        (res,) = rig.resolved_at_open
        assert (res.cause, res.by, res.source) == ("hx711-rate", "rig config", str(host))
        assert res.reason == "hx711 rate 10 SPS configured, measured 10 SPS"
        assert rig.safety.latch is None and not any(isinstance(i, Acknowledgement) for i in rig.safety.history)
        logged = [json.loads(line) for line in safety_log_path().read_text().splitlines()]
        assert logged[-1]["kind"] == "resolved" and logged[-1]["by"] == "rig config"
        assert not any(e["kind"] == "acknowledged" for e in logged)
        assert not st.contact_stiffness_g_per_mm  # the first press probes the contact: ~10 s at 10 SPS (spec 2.10)
        rig.press(500, timeout_s=10)  # 12.8 s of which ~10.5 s probe: in time with the allowance (wire.probe_time_s)
        st = rig.drum.read_status()
        assert st.state == DrumState.FORCE_SETTLED and st.contact_stiffness_g_per_mm == pytest.approx(1000, rel=0.1)


def test_a_rate_chosen_with_hx711_rate_survives_open_and_the_rig_config(tmp_path, monkeypatch):
    """``--hx711-rate 10`` (open_rig's hx711_rate_sps) builds the simulated board at 10 SPS; the force loop the rig is
    configured with at open takes that rate, with no rig config and over a rig config's force_loop for 80 SPS (its
    gains kept): the HX711_RATE the board latched at boot is resolved by ``--hx711-rate``, the controller runs its
    10 SPS gains, the rig config file is left as it was. The old code pushed the config's (or the default's) 80 SPS
    and refused the open: 'HX711_RATE: measured 10 SPS, the force loop set for 80 SPS'."""
    from rigctl.acquisition.rigconfig import update_rig_config
    from rigctl.core.drum import Fault
    from rigctl.devices.drum import default_force_loop

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    host = tmp_path / "rig.json"
    for with_config in (False, True):
        if with_config:
            update_rig_config(host, force_loop={**default_force_loop(80).to_dict(), "kp_10sps_mm_s_per_g": 0.001})
        before = host.read_text() if host.exists() else None
        with open_rig("inprocess", seed=3, host_config_path=host, hx711_rate_sps=10) as rig:
            loop = rig.drum.force_loop()
            assert loop.hx711_rate_sps == 10, with_config
            assert loop.kp_10sps_mm_s_per_g == pytest.approx(0.001 if with_config else 0.0012)
            st = rig.drum.read_status()
            assert st.faults == Fault(0) and st.hx711_rate_sps == pytest.approx(10, rel=0.02)
            (res,) = rig.resolved_at_open
            assert (res.by, res.reason) == ("--hx711-rate", "hx711 rate 10 SPS configured, measured 10 SPS")
        assert (host.read_text() if host.exists() else None) == before


def test_a_rig_config_rate_the_board_does_not_have_still_refuses_at_open(tmp_path, monkeypatch):
    """A force_loop for 10 SPS on a board that runs at 80 SPS: the controller latches HX711_RATE when the host writes
    the rate, the measured rate does not match the config, so nothing clears it: the open is refused in one line naming
    both rates, and nothing is logged as resolved."""
    import json

    from rigctl.acquisition.rig import FaultAtOpen
    from rigctl.acquisition.rigconfig import update_rig_config
    from rigctl.acquisition.safety import safety_log_path
    from rigctl.devices.drum import default_force_loop
    from rigctl.simulation.model import MechanicsConfig

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))  # this test's own rig log
    host = tmp_path / "rig.json"
    update_rig_config(host, force_loop=default_force_loop(10).to_dict())
    cfg = RigConfig(mechanics=MechanicsConfig(hx711_rate_sps=80.0))
    with pytest.raises(FaultAtOpen, match="HX711_RATE: measured 80 SPS, the force loop set for 10 SPS") as err:
        open_rig("inprocess", config=cfg, seed=2, host_config_path=host)
    assert "\n" not in str(err.value) and err.value.latch.cause == "hx711-rate"
    path = safety_log_path()
    kinds = [json.loads(line)["kind"] for line in path.read_text().splitlines()] if path.exists() else []
    assert "resolved" not in kinds and "latched" in kinds


@pytest.mark.hil
def test_under_simavr_a_driver_at_8_microsteps_flags_the_trial(tmp_path):
    """The same check on the real firmware (both boards under simavr): the Mega's index sensor input follows the
    harness's real drum, the trial attributes flag the mismatch."""
    import time

    from rigctl import firmware
    from rigctl.core.drum import DrumState

    try:
        firmware.build()
    except firmware.FirmwareBuildError as exc:
        pytest.skip(f"the firmware or the simavr harness cannot be built here: {exc}")
    proto = parse_protocol('name = "index-hil"\ntextures = ["A"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
                           'trials_per_condition = 1\nduration_s = 1.0\n[settle]\nsettle_time_ms = 50\n')
    out = tmp_path / "s.h5"
    with open_rig("hil", config=RigConfig(drum=DrumConfig(driver_microsteps=8)),
                  host_config_path=tmp_path / "rig.json") as rig:
        # two sensor edges first, so the steps per revolution are known (1.3 s per revolution at 240 mm/s real)
        rig.home_if_pending()  # the start (opening moved nothing): RUN is refused until HOME
        rig.drum.set_force(300)
        rig.drum.set_speed(120)
        rig.drum.run()
        deadline = time.monotonic() + 120  # simavr falls behind real time on a loaded machine
        st = rig.drum.read_status()
        while st.index_count < 2:
            assert time.monotonic() < deadline and st.state == DrumState.RUNNING, st
            time.sleep(0.2)
            st = rig.drum.read_status()
        rig.drum.stop()
        summary = run_protocol(proto, out, rig=rig)
    assert summary.ok
    with open_session(out) as s:
        a = s.trial_attrs(0)
    assert a["index_source"] == "sensor" and a["drum_speed_mismatch"]
    assert a["drum_steps_per_rev_index"] == pytest.approx(1600, abs=2)
    assert a["drum_speed_index_mm_s"] == pytest.approx(240, rel=0.03)
