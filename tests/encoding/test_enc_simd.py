"""The fused encoder's explicit SIMD code (rigctl.encoding.fused, rigctl.encoding.bitmaps) gives the scalar
expressions' numbers bit for bit: the SA neurons stepped 16 lanes at once against the same float32 operations done
by numpy, the spike times decoded a word at a time against each set bit's time, and the whole kernel built for a CPU
without AVX-512 (the byte-table decoder, the 512-bit vectors split in two) against this machine's build."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from rigctl.encoding import bitmaps
from rigctl.encoding.bitmaps import word_times
from rigctl.encoding.fused import run_fused
from rigctl.encoding.izhikevich import TONIC_SPIKING

#: the paper's tonic-spiking SA neuron (run_fused's default izhikevich parameters)
A, B, C, D, V_PEAK = (TONIC_SPIKING.a, TONIC_SPIKING.b, TONIC_SPIKING.c, TONIC_SPIKING.d, TONIC_SPIKING.v_peak)


def _ragged_readings(seed: int, lengths: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Texture-like uint16 readings of trials of ``lengths`` samples x 18 taxels, flat, and their row starts."""
    rng = np.random.default_rng(seed)
    starts = np.concatenate(([0], np.cumsum(lengths))).astype(np.int64)
    walk = np.cumsum(rng.integers(-40, 41, (int(starts[-1]), 18)), axis=0) + 500
    return np.clip(walk, 0, 1023).astype(np.uint16), starts


def _numpy_sa(raw, starts, off, scl, gains, fs=1000.0):
    """The float32 SA step of rigctl.encoding.fused (the folded constants, no contraction) by numpy, every taxel of
    a trial at once: per trial and taxel the spike times (s). gains (n_trials, n_ch) float32 = k_sa * C."""
    f = np.float32
    h, q, fv, e = 0.5, 0.04, 5.0, 140.0
    kc0, kc4, kc5, kc6 = f(h), f(h * q), f(1.0 + h * fv), f(h * e)
    kc7, kc8 = f(1.0 - A), f(A * B)
    out = []
    for t in range(starts.size - 1):
        x = (raw[starts[t]:starts[t + 1]].astype(f) - off) * scl
        v = np.full(raw.shape[1], f(C), f)
        u = (f(B) * v).astype(f)
        spikes: list[list[float]] = [[] for _ in range(raw.shape[1])]
        for n in range(x.shape[0]):
            i_in = x[n] * gains[t]
            w = kc6 + kc0 * (i_in - u)
            v1 = v * (kc4 * v + kc5) + w
            v2 = v1 * (kc4 * v1 + kc5) + w
            u1 = kc7 * u + kc8 * v2
            s = v2 >= f(V_PEAK)
            v = np.where(s, f(C), v2)
            u = np.where(s, u1 + f(D), u1)
            for ch in np.flatnonzero(s):
                spikes[ch].append(n * (1.0 / fs))
        out.append(spikes)
    return out


@pytest.mark.parametrize("per_lane", [False, True], ids=["one gain", "a gain per taxel and trial"])
def test_sa_vectors_equal_the_float32_steps_done_by_numpy(per_lane):
    # 11 trials (a block of 8, then 3: 54 lanes, padded to 64), ragged, so trials end inside a vector
    lengths = [37, 300, 301, 64, 290, 5, 299, 180, 33, 250, 120]
    raw, starts = _ragged_readings(3, lengths)
    off = raw.min(axis=0).astype(np.float32)
    scl = (1.0 / (raw.max(axis=0) - raw.min(axis=0))).astype(np.float32)
    rng = np.random.default_rng(4)
    coeff = rng.uniform(0.6, 2.4, (len(lengths), 18)) if per_lane else 1.7
    res = run_fused(raw, starts, offset=off, scale=scl, sa_gains=[coeff], k_sa=100.0, ra=False)
    gains = np.broadcast_to(np.asarray(100.0 * np.asarray(coeff, np.float64), np.float32), (len(lengths), 18))
    want = _numpy_sa(raw, starts, off, scl, gains)
    trains = res.sa[0]
    assert trains.counts().sum() > 500  # the input spikes: the comparison has something to compare
    for t in range(len(lengths)):
        for ch in range(18):
            np.testing.assert_array_equal(trains.train(t, ch), np.asarray(want[t][ch], np.float64),
                                          err_msg=f"trial {t}, taxel {ch}")


@numba.njit
def _bin_count(w):  # pragma: no cover - compiled by numba
    n = 0
    while w:
        n += 1
        w &= w - np.uint32(1)
    return n


@numba.njit
def _decode_words(words, bases, dt):  # pragma: no cover - compiled by numba
    total = 0
    for i in range(words.size):
        total += _bin_count(words[i])
    out = np.zeros(total + 64)
    pos = 0
    for i in range(words.size):
        word_times(out, pos, words[i], bases[i], dt)
        pos += _bin_count(words[i])
    return out[:pos]


def test_word_times_gives_every_set_bit_in_order_of_any_word():
    rng = np.random.default_rng(5)
    # every density, with words of more than 16 bits (the second half) and the extremes
    words = np.concatenate([(rng.random((400, 32)) < p) @ (np.uint64(1) << np.arange(32, dtype=np.uint64))
                            for p in (0.02, 0.1, 0.5, 0.9)]).astype(np.uint32)
    words = np.concatenate([words, np.array([0, 0xFFFFFFFF, 1, 0x80000000, 0x0001FFFF], np.uint32)])
    bases = rng.integers(0, 10**9, words.size).astype(np.float64)
    dt = 1.0 / 1000.0
    want = np.concatenate([(bases[i] + np.flatnonzero((int(w) >> np.arange(32)) & 1)) * dt
                           for i, w in enumerate(words)])
    got = _decode_words(words, bases, dt)
    np.testing.assert_array_equal(got, want)


def _build_case() -> dict:
    """The input both builds encode: every SA and RA population's spike times and index as lists (exact in JSON)."""
    raw, starts = _ragged_readings(7, [900, 1200, 77, 1500, 640, 1199, 32, 1000, 800, 450])
    coeff = np.random.default_rng(8).uniform(0.5, 2.5, (10, 18))
    res = run_fused(raw, starts, offset=0.0, scale=1 / 1023, sa_gains=[1.0, coeff], k_sa=200.0)
    return {"has_compress": bitmaps.HAS_COMPRESS,
            "trains": [[tr.spike_times.tolist(), tr.spike_times_index.tolist()] for tr in (*res.sa, res.ra)]}


_OTHER_BUILD = """
import json, sys
sys.path.insert(0, sys.argv[1])
from test_enc_simd import _build_case
print(json.dumps(_build_case()))
"""


@pytest.mark.slow
def test_a_build_without_avx512_gives_the_same_spike_times(tmp_path):
    """The kernel and the decoder compiled for an AVX2 CPU (numba's NUMBA_CPU_NAME / NUMBA_CPU_FEATURES: the
    byte-table decoder, each 16-lane SA vector as two 256-bit halves) in a process of its own, with a numba cache of
    its own, against the same input in this process's build."""
    script = tmp_path / "other_build.py"
    script.write_text(_OTHER_BUILD)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-avx2"), "NUMBA_CPU_NAME": "haswell",
           "NUMBA_CPU_FEATURES": "+avx,+avx2,+fma,+popcnt,+sse4.2,+bmi,+bmi2"}
    done = subprocess.run([sys.executable, str(script), str(Path(__file__).resolve().parent)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    avx2 = json.loads(done.stdout)
    assert avx2["has_compress"] is False
    host = _build_case()
    assert sum(len(t[0]) for t in host["trains"]) > 1000
    assert avx2["trains"] == host["trains"]


def test_blocks_and_decode_units_claimed_by_threads_give_the_one_thread_result():
    """The kernel's blocks and the decode's units are claimed by the call's threads (an atomic counter): every
    population's spike times on all of numba's threads equal those on one, and each unit is decoded once."""
    lengths = [int(n) for n in np.random.default_rng(9).integers(1, 700, 45)]  # 6 blocks, trials of every length
    raw, starts = _ragged_readings(10, lengths)
    coeff = np.random.default_rng(11).uniform(0.5, 2.5, (len(lengths), 18))

    def run():
        res = run_fused(raw, starts, offset=0.0, scale=1 / 1023, sa_gains=[1.0, coeff], k_sa=200.0)
        return [(tr.spike_times, tr.spike_times_index) for tr in (*res.sa, res.ra)], res.counts

    n_threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one, one_counts = run()
    finally:
        numba.set_num_threads(n_threads)
    for _ in range(5):  # (which thread claims which block varies from call to call)
        every, counts = run()
        np.testing.assert_array_equal(counts, one_counts)
        for (t1, i1), (t2, i2) in zip(one, every, strict=True):
            np.testing.assert_array_equal(t2, t1)
            np.testing.assert_array_equal(i2, i1)
    assert one_counts.sum() > 1000
