"""The runner and the load-cell calibration on the in-process backend (rigctl.rigs.open_rig("inprocess"): the
controller logic and the physical model in this process, on a simulated clock, no ptys): a protocol recorded into a
session file and a calibration with a known mass, each in a few seconds of wall time."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigctl.acquisition import calibration
from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.rig import _Status, recorded_means
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


def test_a_trial_delivered_in_one_burst_carries_the_force_it_was_recorded_at():
    """A host starved for 2.5 s: the board recorded a 2 s trial meanwhile, and its frames arrived within 20 ms after
    the stall; the status read in flight across the stall is stamped halfway (t = 11.25 s), the next one after the
    burst. No read lies within the frames' receive times (the CI run's NaN); the reads while the board recorded
    the trial (its frames' fitted times) give the trial's force and speed, and with no read at all in that window,
    the reads on either side of it."""
    reads = [_Status(t, 500.0 + (t > 11.0) * 4.0, 120.0, 2, 0) for t in np.arange(0.0, 10.0, 0.02)]
    reads += [_Status(11.25, 504.0, 120.0, 2, 0), _Status(12.53, 506.0, 121.0, 2, 0)]
    frames_received = (12.50, 12.52)
    assert not any(frames_received[0] <= r.t <= frames_received[1] for r in reads)
    assert recorded_means(reads, 10.49, 12.49) == {"force_mean_g": 504.0, "speed_mean_mm_s": 120.0}
    assert recorded_means(reads, 9.0, 9.03) == {"force_mean_g": 500.0, "speed_mean_mm_s": 120.0}  # 9.00, 9.02
    got = recorded_means(reads, 11.5, 12.5)  # between 11.25 and 12.53: interpolated at 12.0
    assert got["force_mean_g"] == pytest.approx(504.0 + 2.0 * 0.75 / 1.28)
    assert got["speed_mean_mm_s"] == pytest.approx(120.0 + 0.75 / 1.28)
    assert all(np.isnan(v) for v in recorded_means([], 11.5, 12.5).values())


def test_loadcell_calibration_inprocess(rig, tmp_path):
    cfg = tmp_path / "rig.json"
    place, remove = calibration.simulated_mass(rig)
    rig.home_if_pending()  # the start: opening moved nothing, the calibration needs the actuator at home
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


@pytest.mark.parametrize("counts_per_g", [2150.0, 4300.0, 43.0])
def test_large_and_small_cells_calibrate(tmp_path, counts_per_g):
    """1 kg cells of 1-2 mV/V (~2,150-4,300 counts/g at gain 128) and a 50 kg, 1 mV/V cell (~43 counts/g): beyond
    or near the ends of firmware 1.0's 16-bit register (0.01-655.35 counts/g); the signed 32-bit scale holds them."""
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=counts_per_g))
    with open_rig("inprocess", config=cfg, seed=5, host_config_path=tmp_path / "rig.json") as rig:
        place, remove = calibration.simulated_mass(rig)
        rig.home_if_pending()  # the start (opening moved nothing)
        result = calibration.calibrate_loadcell(rig.drum, 500.0, place_mass=place, remove_mass=remove,
                                                n_readings=10, interval_s=0.0, settle_s=0.1,
                                                config_file=tmp_path / "rig.json")
        assert abs(result.counts_per_g - counts_per_g) / counts_per_g < 0.01
        assert rig.drum.loadcell_scale() == result.scale_x100 / 100
        assert abs(result.check_force_g - 500.0) < 5


def test_a_reversed_cell_is_reported_as_reversed_and_calibrates_negative_on_request(tmp_path):
    """A cell that reads negative under the mass: the calibration says it is reversed (firmware 1.0's host called
    it "did not respond"); asked to, it calibrates it with a negative scale, and the controller then reads the mass
    as a positive force."""
    cfg = RigConfig(mechanics=MechanicsConfig(loadcell_counts_per_g=-TRUE_COUNTS_PER_G))
    with open_rig("inprocess", config=cfg, seed=5, host_config_path=tmp_path / "rig.json") as rig:
        place, remove = calibration.simulated_mass(rig)
        rig.home_if_pending()  # the start (opening moved nothing)
        kw = dict(place_mass=place, remove_mass=remove, n_readings=10, interval_s=0.0, settle_s=0.1,
                  config_file=tmp_path / "rig.json")
        with pytest.raises(calibration.CalibrationError, match="reads negative.*other way round"):
            calibration.calibrate_loadcell(rig.drum, 500.0, **kw)
        result = calibration.calibrate_loadcell(rig.drum, 500.0, allow_negative=True, **kw)
        assert abs(result.counts_per_g + TRUE_COUNTS_PER_G) / TRUE_COUNTS_PER_G < 0.01
        assert abs(result.check_force_g - 500.0) < 5
        assert json.loads((tmp_path / "rig.json").read_text())["loadcell"]["scale_x100"] == result.scale_x100 < 0


def test_an_unexpected_reset_latches_and_the_acknowledgement_rehomes_and_retares(rig):
    """The controller resets while pressing (a brown-out): the next press is refused, the reset latched as such
    (boot count changed: docs/safety.md); the operator's acknowledgement homes and tares it again, and the press
    after it loads the cell with the asked force, not twice it."""
    from rigctl.acquisition.safety import LatchedFault
    from rigctl.devices import wire
    from rigctl.devices.wire import ResetCause

    ctl = rig.backend.controller
    rig.press(800)
    pressed_g = rig.backend.model.force_g  # (this rig's cell is not calibrated: 800 g read is not 800 g true)
    boot0 = rig.drum_boot_count
    ctl.reset(ResetCause.BROWN_OUT)  # under load: the actuator stays where it is
    # the controller latches it itself (RESET, firmware 1.5: a cold boot loaded against its stored zero, judged at its
    # first reading once the HX711's rate is timed; issue 76)
    rig.drum.clock.sleep(0.2)
    st = rig.drum.read_status()
    assert (st.state.name, st.faults) == ("FAULT", wire.Fault.RESET) and rig.backend.model.force_g > 600
    with pytest.raises(LatchedFault, match="reset"):
        rig.press(800)
    with pytest.raises(LatchedFault, match="PRESS refused"):
        rig.press(800)  # latched: refused until acknowledged
    assert rig.drum_resets == 1 and rig.safety.latch.cause == "reset"
    rig.acknowledge("brown-out checked", by="pytest")
    rig.press(800)
    st = rig.drum.read_status()
    assert rig.drum_boot_count == st.boot_count == wire.boot_count_after(boot0, ResetCause.BROWN_OUT)  # a cold boot
    assert st.reset_cause == ResetCause.BROWN_OUT and st.homed
    assert abs(rig.backend.model.force_g - pressed_g) < 30  # the same true force as before the reset, not twice it


def test_a_reset_between_the_open_and_the_first_home_is_latched_not_homed_over(rig):
    """The controller resets after the rig read it at open and before its first start's HOME (the outlives-face
    machine's `plan --ack` face, 2 of 5 runs: HOME took the new boot count for the rig's own, the reset was forgotten,
    and the start homed and pressed 0.66-1.29 mm towards the sensor after a reset nobody acknowledged): the start is
    refused as a reset, nothing moves (no HOME, no press), and it stays refused until acknowledged."""
    from rigctl.acquisition.safety import LatchedFault
    from rigctl.devices.wire import ResetCause

    ctl, model = rig.backend.controller, rig.backend.model
    assert rig.home_pending and not rig.homed_once  # opened: nothing moved, the first start HOMEs
    ctl.reset(ResetCause.EXTERNAL)
    act0, steps0 = model.actuator_mm, model.stepper_travel_mm
    with pytest.raises(LatchedFault, match="reset"):
        rig.press(300)
    assert rig.safety.latch.cause == "reset" and rig.drum_resets == 1
    with pytest.raises(LatchedFault, match="refused"):
        rig.press(300)
    assert model.actuator_mm == act0 and model.stepper_travel_mm == steps0 and rig.drum.read_status().state.name \
        == "NOT_HOMED"  # no HOME, no press
    rig.acknowledge("reset checked", by="pytest")
    rig.press(300)  # the start after the acknowledgement homes and presses


def test_a_reset_while_the_rig_opens_is_latched(tmp_path, monkeypatch):
    """A reset after the rig first read the controller and before its open ends (as its force loop is written): the
    boot count the rig keeps is the first one read, so the reset is latched, not taken for the controller's own
    (its start would have homed and pressed after a reset nobody acknowledged); refused at open where faults are."""
    from rigctl.acquisition.rig import FaultAtOpen, Rig
    from rigctl.devices.wire import ResetCause

    real = Rig._apply_force_loop

    def reset_then_apply(self):
        self.backend.controller.reset(ResetCause.EXTERNAL)
        real(self)

    monkeypatch.setattr(Rig, "_apply_force_loop", reset_then_apply)
    with open_rig("inprocess", seed=5, host_config_path=tmp_path / "rig.json", refuse_fault=False) as rig:
        assert rig.safety.latch is not None and rig.safety.latch.cause == "reset", rig.safety.latch
        assert "while the rig was opened" in rig.safety.latch.detail
    with pytest.raises(FaultAtOpen):
        open_rig("inprocess", seed=5, host_config_path=tmp_path / "rig.json", refuse_fault=True)


def test_bad_eeprom_and_a_calibration_mismatch_are_warned_on_open(tmp_path):
    """Opening a rig whose controller runs on default calibration (blank or bad EEPROM), with a rig config whose
    load-cell calibration differs from the controller's scale: both are warned about, by name."""
    cfg_file = tmp_path / "rig.json"
    cfg_file.write_text(json.dumps({"loadcell": {"counts_per_g": 380.0}}))
    with open_rig("inprocess", seed=5, host_config_path=cfg_file, factory_calibrated=False) as rig:
        text = " ".join(rig.warnings)
        assert "EEPROM calibration is missing or failed its checksum" in text
        assert "load-cell scale is 420 counts/g but the rig config's calibration is 380 counts/g" in text
