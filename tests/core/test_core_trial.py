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


def _stamps(rate_hz: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A device at ``rate_hz`` seen by a host that delivers frames in 4-frame bursts with exponential delays."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    true_t = 100.0 + k / rate_hz
    burst_end = true_t[np.minimum((k // 4) * 4 + 3, n - 1)]
    host_t = burst_end + rng.exponential(0.0005, n)
    return (k & 0xFFFF).astype(np.uint16), host_t


@pytest.mark.parametrize("rate_hz", [999.0, 1000.0, 1000.5])
def test_host_rate_is_exact_under_random_delivery_delays(rate_hz):
    from rigctl.core.trial import lower_envelope_rate_hz

    seq, t = _stamps(rate_hz, 8000, seed=3)
    assert lower_envelope_rate_hz(seq, t, 1000.0) == pytest.approx(rate_hz, abs=0.05)


def test_host_rate_ignores_a_stalled_reader_at_the_start_of_the_history():
    """A loaded host's reader stalled while the stream started: the whole first 40 % of the frames arrive late in
    bursts (up to 1.7 s late). The least-delayed frame of the first third was then a late one and the old estimate
    read ~1,390 Hz (CI, quick_check trial 1); the lower hull's edge over the middle is on time."""
    from rigctl.core.trial import lower_envelope_rate_hz

    seq, t = _stamps(1000.0, 6000, seed=4)
    late = np.arange(len(t)) < 2400
    stall_release = t[2399] + 0.05  # everything queued behind the stall is read at once
    t[late] = np.maximum(t[late], stall_release)
    assert lower_envelope_rate_hz(seq, t, 1000.0) == pytest.approx(1000.0, abs=0.05)
    # a dropped-frame gap in the sequence is counted, not mistaken for a slow clock
    keep = np.ones(len(t), bool)
    keep[4000:4010] = False
    assert lower_envelope_rate_hz(seq[keep], t[keep], 1000.0) == pytest.approx(1000.0, abs=0.05)


@pytest.mark.parametrize("late_fraction", [0.6, 0.85])
def test_host_rate_ignores_a_reader_that_stalled_for_most_of_the_history(late_fraction):
    """The reader stalled for more than half of the history, then read the queue at once (CI at load 8-10: a
    quick_check trial read 2,268 Hz for a 1 kHz board): the hull's edge over the middle is the catch-up, whose slope
    is no clock's; the on-time stretch after it still gives the rate."""
    from rigctl.core.trial import lower_envelope_rate_hz

    seq, t = _stamps(1000.0, 6000, seed=5)
    n_late = int(late_fraction * len(t))
    t[:n_late] = np.maximum(t[:n_late], t[n_late - 1] + 0.05)
    assert lower_envelope_rate_hz(seq, t, 1000.0) == pytest.approx(1000.0, abs=0.2)


@pytest.mark.parametrize("rate_hz", [500.0, 1100.0])
def test_host_rate_still_reads_a_clock_far_off_nominal(rate_hz):
    """A board on the wrong crystal or firmware (every edge beyond the plausible band) is still measured as it is:
    the doctor's uno-clock check must see it fail."""
    from rigctl.core.trial import lower_envelope_rate_hz

    seq, t = _stamps(rate_hz, 8000, seed=6)
    assert lower_envelope_rate_hz(seq, t, 1000.0) == pytest.approx(rate_hz, rel=1e-3)
