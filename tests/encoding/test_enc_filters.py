"""The RA low-pass's coefficient table against scipy.signal, and the RA input with it against the scipy-only one."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from rigctl.core.encoding_model import MODEL_RATE_HZ, RA_CUTOFF_HZ
from rigctl.encoding.filters import RAFilter, lowpass_coefficients, ra_input

# readings as they come (0-1), as a user may pass them (any float: huge, tiny, subnormal), and broken (nan, +-inf)
VALUES = st.one_of(st.floats(0.0, 1.0), st.floats(allow_nan=True, allow_infinity=True),
                   st.floats(-1e-300, 1e-300, allow_subnormal=True), st.floats(-1e6, 1e6))
VALUES32 = st.one_of(st.floats(0.0, 1.0, width=32), st.floats(width=32))
TRIALS_SHAPE = st.tuples(st.integers(1, 3), st.integers(1, 120), st.integers(1, 5))  # (trials, n, taxels)
# inf and huge readings overflow the filter and the derivative: numpy says so, and the results must still agree
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning",
                                        "ignore:invalid value encountered:RuntimeWarning")


def same_bits(x: np.ndarray, y: np.ndarray) -> bool:
    """Same shape, dtype and float64 bit patterns (nan payloads and the signs of zeros and nans included)."""
    return x.shape == y.shape and x.dtype == y.dtype and np.array_equal(x.view(np.uint64), y.view(np.uint64))


def scipy_ra_input(x: np.ndarray, rectify: bool) -> np.ndarray:
    """The RA input with every coefficient from scipy.signal (butter, lfilter_zi), as rigctl had it before the table."""
    from scipy import signal

    x = np.asarray(x, dtype=np.float64)
    b, a = signal.butter(2, RA_CUTOFF_HZ, btype="low", fs=MODEL_RATE_HZ)
    y, _ = signal.lfilter(b, a, x, axis=-2, zi=signal.lfilter_zi(b, a)[:, None] * x[..., :1, :])
    d = np.zeros_like(y)
    d[..., 1:, :] = np.diff(y, axis=-2)
    d *= MODEL_RATE_HZ
    return np.maximum(d, 0.0) if rectify else d


@pytest.mark.parametrize(("cutoff_hz", "fs", "order"), [(RA_CUTOFF_HZ, MODEL_RATE_HZ, 2), (20, 1000, 2),
                                                       (35.0, 1000.0, 2), (20.0, 2000.0, 2), (20.0, 1000.0, 4)])
def test_coefficients_are_scipys(cutoff_hz, fs, order):
    from scipy import signal

    b, a, zi = lowpass_coefficients(cutoff_hz, fs, order)
    sb, sa = signal.butter(order, cutoff_hz, btype="low", fs=fs)
    assert same_bits(b, sb) and same_bits(a, sa) and same_bits(zi, signal.lfilter_zi(sb, sa))
    with pytest.raises(ValueError, match="cutoff_hz"):
        lowpass_coefficients(fs / 2, fs, order)


def test_encoder_and_renderer_filters_do_not_import_scipy_signal():
    # the encoders' RA low-pass (the default filter's table) and the dataset renderer's noise (one_pole), in one
    # fresh interpreter: neither may load scipy.signal (nor scipy.stats, which it loads)
    code = ("import sys, numpy as np\n"
            "from rigctl.encoding.filters import lowpass_coefficients\n"
            "from rigctl.simulation.dataset import render_trial\n"
            "lowpass_coefficients(); lowpass_coefficients(20, 1000.0)\n"
            "render_trial('A', 80.0, 100.0, rng=np.random.default_rng(0), duration_s=0.3)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('scipy.signal', 'scipy.stats'))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@settings(max_examples=100, deadline=None)
@given(x=st.one_of(arrays(np.float64, TRIALS_SHAPE, elements=VALUES), arrays(np.float32, TRIALS_SHAPE, elements=VALUES32)),
       trials=st.booleans(), rectify=st.booleans())
def test_ra_input_is_the_scipy_one_bit_for_bit(x, trials, rectify):
    x = x if trials else x[0]  # (trials, n, taxels) or (n, taxels)
    assert same_bits(ra_input(x, rectify=rectify), scipy_ra_input(x, rectify))


@settings(max_examples=60, deadline=None)
@given(x=arrays(np.float64, st.tuples(st.integers(1, 150), st.integers(1, 4)), elements=VALUES),
       cuts=st.lists(st.integers(0, 150), max_size=6), rectify=st.booleans())
def test_streaming_is_the_scipy_one_bit_for_bit(x, cuts, rectify):
    f = RAFilter(x.shape[1], rectify=rectify)
    parts = [f.process(chunk) for chunk in np.split(x, sorted(c for c in cuts if c <= x.shape[0]))]
    assert same_bits(np.concatenate(parts), scipy_ra_input(x, rectify))
    f.reset()  # a new trial starts at the steady state of its own first sample
    assert same_bits(f.process(x[::-1]), scipy_ra_input(x[::-1], rectify))
