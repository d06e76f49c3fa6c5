"""The encoder's outputs, bit for bit, against those of the code before issue 57's speed work (main at 60840c4):
SHA-256 digests of the spike times, counts, carried-over state, force coefficients and features on fixed inputs.

A speed change of the kernels (rigctl.encoding.fused, the force bisection) must leave every number as it was; a
change that moves any of them fails here. Should a change of the *model* ever be intended, the digests are
recomputed with :func:`digests` and the reason given in the commit (this file says what they were computed from).
"""

from __future__ import annotations

import hashlib

import numpy as np

from rigctl.encoding.batch_encode import encode_batch
from rigctl.encoding.force import ForceCoefficients, fit_scalers
from rigctl.encoding.fused import FusedState, run_fused
from rigctl.encoding.izhikevich import Ragged, as_ragged, encode_sa
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.pipeline import EncodeParams

#: computed with :func:`digests` on main at 60840c4 (before issue 57's kernel changes)
EXPECTED = {
    "fused_sa2_ra": "99a77cb99c8f1136e3b7b830f95aea74e72229793a12a21c884ff402f9bd43c5",
    "fused_f64": "9dcb3e0b00f096f083f9b4e598f2a079fd99db4c2251995833a28ac6ba23a0d9",
    "fused_float_input": "8baec34f78bf5dbe2534f547fb1e07e9c8e1fd44a40a0820a3c4590f882b3607",
    "fused_stream": "067fa0c9007231285325725d9fff6959f71793824142fb85aa7a35da818ae9c8",
    "fused_active": "717df5d1693d6c21bc4e23f1ba2b0f18bcfac9436f8619e2c4e7d5ed06adb8b7",
    "encode_sa": "2fdb25f54c1a1f9d83cda4bcf4b48ec40ada7c8e705241ca61e1619a065e9122",
    "force_fit": "e3c29264abd01caca268a4e2e1f29c0a55ee32bfb114fce91073fc731bae72fd",
    "encode_batch": "13e7bb9a97ab5ffed2783d04cf7d0fa3350f464e2a55cc8e7c4940195be88465",
}


def _raw(n_trials: int, lengths: list[int], n_ch: int = 18, seed: int = 57) -> Ragged:
    """Texture-like 10-bit counts (slow sinusoids + noise), trials of the given lengths."""
    rng = np.random.default_rng(seed)
    trials = []
    for t in range(n_trials):
        n = lengths[t % len(lengths)]
        tt = np.arange(n)[:, None] / 1000.0
        f = rng.uniform(2, 20, size=(1, n_ch))
        base = rng.uniform(0.1, 0.6, size=(1, n_ch))
        x = base + 0.3 * np.sin(2 * np.pi * f * tt) + 0.02 * rng.standard_normal((n, n_ch))
        trials.append(np.round(100 + 800 * np.clip(x, 0.0, 1.0)).astype(np.uint16))
    return as_ragged(trials)


def _h(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _trains(*trains) -> list[np.ndarray]:
    out = []
    for t in trains:
        out += [t.spike_times, t.counts()]
    return out


def digests() -> dict[str, str]:
    """Digest of each output on its fixed input (see the module docstring)."""
    lengths = [0, 1, 31, 32, 33, 700, 1500, 2999, 3001, 64, 65, 950]
    rg = _raw(27, lengths)  # ragged, more than three blocks of trials, empty and one-sample trials
    tr = TaxelRange().update(rg.data)
    off, scl = tr.offset_scale()
    n, n_ch = rg.n_trials, rg.n_channels
    rng = np.random.default_rng(5)
    g1 = rng.uniform(0.5, 2.0, (n, n_ch))
    out: dict[str, str] = {}
    r = run_fused(rg.data, rg.starts, offset=off, scale=scl, sa_gains=(1.0, g1), n0=7)
    out["fused_sa2_ra"] = _h(*_trains(*r.sa, r.ra), r.counts)
    r = run_fused(rg.data, rg.starts, offset=off, scale=scl, sa_gains=(g1,), dtype=np.float64)
    out["fused_f64"] = _h(*_trains(*r.sa, r.ra), r.counts)
    xf = (rg.data.astype(np.float64) - off) * scl
    r = run_fused(xf, rg.starts, sa_gains=(1.0,), ra_dtype=np.float32)
    out["fused_float_input"] = _h(*_trains(*r.sa, r.ra), r.counts)
    # streaming: two calls, the state carried over (every trial cut at the same sample)
    cut = 40
    short = np.minimum(rg.lengths, cut)
    first = as_ragged([rg.trial(t)[:cut] for t in range(n)])
    second = as_ragged([rg.trial(t)[cut:] for t in range(n)])
    st = FusedState.rest(2, n, n_ch)
    a = run_fused(first.data, first.starts, offset=off, scale=scl, sa_gains=(1.0, g1), state=st)
    b = run_fused(second.data, second.starts, offset=off, scale=scl, sa_gains=(1.0, g1), state=st, n0=short)
    out["fused_stream"] = _h(*_trains(*a.sa, a.ra, *b.sa, b.ra), st.v, st.u, st.filt, st.fresh)
    active = rng.random(n) < 0.6
    r = run_fused(rg.data, rg.starts, offset=off, scale=scl, sa_gains=(1.0, g1, 0.7), ra=False, want_times=False,
                  active=active)
    out["fused_active"] = _h(r.counts)
    out["encode_sa"] = _h(*_trains(encode_sa(rg, normalise=tr, coeff=g1)))
    # the force bisection (per texture and label free), on trials long enough to converge
    fr = _raw(48, [900, 1200, 1500, 2000], seed=58)
    ftr = TaxelRange().update(fr.data)
    fo, fs_ = ftr.offset_scale()
    texture = np.repeat(np.array(["a", "b", "c", "d"]), 12)
    speed = np.tile(np.repeat([40.0, 80.0], 6), 4)
    force = np.tile([250.0, 500.0, 1000.0], 16)
    scalers = [ForceCoefficients(), ForceCoefficients(label_free=True)]
    assert fit_scalers(scalers, fr, texture, speed, force, offset=fo, scale=fs_) == ["", ""]
    fits = [sc.fit_ for sc in scalers]
    out["force_fit"] = _h(*[x for f in fits for x in (f.coeffs, f.converged, f.target_rate, f.rate, np.array(f.n_iter))])
    coeffs = scalers[0].coefficients_for(texture, speed, force)
    coeffs_lf = scalers[1].coefficients_for(texture, speed, force)
    feats, spikes = encode_batch(fr, offset=fo, scale=fs_, speed_mm_s=speed, coeffs=coeffs,
                                 coeffs_label_free=coeffs_lf, params=EncodeParams())
    out["encode_batch"] = _h(*[feats[k] for k in sorted(feats)], *_trains(*[spikes[k] for k in sorted(spikes)]))
    return out


def test_the_encoders_outputs_are_those_before_the_speed_work():
    got = digests()
    assert got == EXPECTED
