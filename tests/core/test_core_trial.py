"""Trial records: TrialData for any channel count and rate, refusing readings that do not fit the sensor."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core import PAPER_SENSOR, LayoutError, PlannedTrial, SensorLayout, TrialData


def test_nine_channels_at_100_hz():
    lay = SensorLayout.grid(3, 3, 1, sample_rate_hz=100)
    t = TrialData(np.full((250, 9), 512, np.int64), layout=lay)
    assert t.taxels.dtype == np.uint16 and t.n_samples == 250 and t.rate_hz == 100.0 and t.duration_s == 2.5
    np.testing.assert_allclose(t.host_time_s[:3], [0.0, 0.01, 0.02])
    assert t.host_rate_hz() == pytest.approx(100.0)


def test_default_is_the_paper_sensor_and_refuses_other_widths():
    assert TrialData(np.zeros((4, 18), np.uint16)).layout == PAPER_SENSOR
    with pytest.raises(LayoutError, match=r"\(n_samples, 18\)"):
        TrialData(np.zeros((4, 9), np.uint16))


@pytest.mark.parametrize("bad", [np.full((3, 18), 65535, np.uint16), np.full((3, 18), 1024.0),
                                 np.full((3, 18), -1), np.full((3, 18), 0.5)])
def test_refuses_values_outside_the_adc(bad):
    with pytest.raises(LayoutError):
        TrialData(bad)


def test_twelve_bit_sensor_accepts_its_range():
    lay = SensorLayout.grid(1, 4, adc_bits=12)
    assert int(TrialData(np.full((2, 4), 4095), layout=lay).taxels.max()) == 4095


def test_planned_trial_samples_at_rate():
    p = PlannedTrial(0, "Linen", 20.0, 150.0, 2.5)
    assert p.samples_at(1000) == 2500 and p.samples_at(100) == 250 and not p.is_ramp
