"""The simulators' one-pole noise filter against scipy.signal.lfilter, bit for bit (that rendering a trial imports no
scipy.signal is checked with the RA low-pass's table: tests/encoding/test_enc_filters.py)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from rigctl.simulation.noise import one_pole

# finite and not an exact zero (lfilter's first step adds its zero state: 0 + (-0) is +0, where this keeps -0)
FINITE = st.one_of(st.floats(1e-300, 1e6), st.floats(-1e6, -1e-300))


@settings(max_examples=60, deadline=None)
@given(x=arrays(np.float64, st.integers(0, 300), elements=FINITE), tau_steps=st.floats(1e-3, 1e4), gain=st.floats(1e-3, 1e3))
def test_one_pole_is_lfilter_bit_for_bit(x, tau_steps, gain):
    from scipy.signal import lfilter

    a = math.exp(-1.0 / tau_steps)
    b = math.sqrt(1 - a * a) * gain
    want = lfilter([b], [1.0, -a], x)
    got = one_pole(b, a, x)
    assert got.shape == want.shape and got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_one_pole_on_white_noise_is_the_ou_process():
    # the process the renderer wants: a slow noise of unit variance (b = sqrt(1 - a^2)) and the pole's correlation
    a = math.exp(-1e-3 / 0.05)
    y = one_pole(math.sqrt(1 - a * a), a, np.random.default_rng(3).standard_normal(200_000))
    assert abs(y[1000:].std() - 1.0) < 0.05
    assert abs(np.corrcoef(y[1000:-1], y[1001:])[0, 1] - a) < 0.005

