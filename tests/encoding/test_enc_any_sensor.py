"""Encoding follows the data: a 9-channel (3x3x1) session recorded at 100 Hz, with multi-character texture labels,
groups of its own, trials of different lengths and no speed for some trials.

- 9 SA + 9 RA trains per trial (features and spikes sized from the session's layout);
- the rate is stored and used: readings are resampled to the model's 1 ms step, so a 1 s trial at 100 Hz has
  spikes up to 1 s (encoded as if it were 1 kHz, its spikes would all lie within 0.1 s);
- unscaled features cover the longest trial by default;
- a NaN speed is fine for Original and Force Scaled, a clear error for Speed Scaled when asked for, skipped with a
  warning by default.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import TrialData
from rigctl.encoding.pipeline import SpeedMissingError, encode_session
from rigctl.encoding.rate import rate_conversion
from rigctl.encoding.spikes import SpikeTrains
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import SessionWriter

RATE_HZ = 100.0
LAYOUT = SensorLayout.grid(3, 3, 1, sample_rate_hz=RATE_HZ)
TEXTURES = TextureSet.from_dict({"name": "lab fabrics", "textures": ["Linen", "HB3", "Denim"],
                                 "groups": {"woven": ["Linen", "Denim"], "board": ["HB3"]}})
#: (texture, speed mm/s (NaN = unknown), force g, duration s)
PLAN = [(tex, 50.0 if tex == "Linen" else math.nan, force, dur)
        for tex in ("Linen", "HB3", "Denim") for force in (250.0, 500.0) for dur in (1.0, 2.5)]
NAN_IDS = [i for i, row in enumerate(PLAN) if math.isnan(row[1])]


def _readings(i: int, texture: str, force: float, duration_s: float) -> np.ndarray:
    """A sine per taxel (frequency from the texture, depth from the force) at 100 Hz, 10-bit counts."""
    n = int(round(duration_s * RATE_HZ))
    t = np.arange(n) / RATE_HZ
    f_hz = {"Linen": 2.0, "HB3": 3.0, "Denim": 1.5}[texture]
    amp = 150.0 + 0.3 * force
    phase = np.linspace(0, np.pi, LAYOUT.n_channels)[None, :]
    x = 480.0 + amp * np.sin(2 * np.pi * f_hz * t[:, None] + phase) + i
    return np.clip(np.round(x), 0, LAYOUT.adc_max).astype(np.uint16)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = tmp_path_factory.mktemp("any_sensor") / "s9.h5"
    plan = [{"trial_id": i, "texture": tex, "speed_mm_s": v, "force_g": f, "duration_s": d}
            for i, (tex, v, f, d) in enumerate(PLAN)]
    w = SessionWriter.create(path, plan=plan, layout=LAYOUT, textures=TEXTURES, durable=False)
    for i, (tex, _v, f, d) in enumerate(PLAN):
        w.write_trial(i, TrialData(_readings(i, tex, f, d), layout=LAYOUT))
    return path


@pytest.fixture(scope="module")
def encoded(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("any_sensor_out") / "s9.enc.h5"
    with pytest.warns(UserWarning, match="no speed"):
        encode_session(session, out, progress=False, batch_trials=5)  # default variants: speed ones skipped
    return out


def test_nine_channels_at_100_hz(encoded):
    with open_encoded(encoded) as f:
        assert f.layout == LAYOUT and f.layout.sample_rate_hz == RATE_HZ
        assert f.textures.labels == TEXTURES.labels
        assert f.resampling == {"input_rate_hz": 100.0, "model_rate_hz": 1000.0, "resampled": True}
        assert "resample_poly" in f.attrs["resampling"]
        assert f.parameters["input_rate_hz"] == 100.0 and f.parameters["fs_hz"] == 1000.0
        tr = f.trials
        assert list(tr["texture"]) == [p[0] for p in PLAN]
        assert list(tr["group"]) == ["woven" if p[0] != "HB3" else "board" for p in PLAN]
        np.testing.assert_array_equal(tr["n_samples"], [int(p[3] * RATE_HZ) for p in PLAN])
        np.testing.assert_allclose(tr["duration_s"], [p[3] for p in PLAN])
        n = len(PLAN)
        # whole trials: 2.5 s is the longest -> 25 windows of 100 ms; 9 SA + 9 RA trains
        assert f.parameters["n_windows_unscaled"] == 25
        assert f.feature_shape("original") == (n, 18 * 25)
        assert f.feature_shape("force_scaled") == (n, 18 * 25)
        assert f.feature_shape("realtime_original") == (n, 9 * 20)  # the single layer's 9 SA trains
        assert f.normalisation["taxel_min"].shape == (9,)
        st = SpikeTrains(*f.spikes("original"))
        assert st.shape == (n, 18)
        for i, (_tex, _v, _f, dur) in enumerate(PLAN):
            times = np.concatenate([st.train(i, j) for j in range(18)])
            assert times.size > 0
            # the rate is used: spikes span the trial's real length (1 s or 2.5 s), not a tenth of it
            assert times.max() < dur and times.max() > 0.8 * dur
        x = f.features("original").reshape(n, 18, 25)
        long_trials = [i for i, p in enumerate(PLAN) if p[3] == 2.5]
        short_trials = [i for i, p in enumerate(PLAN) if p[3] == 1.0]
        assert x[long_trials][:, :, 20:].any()  # the last windows of the long trials hold spikes
        assert not x[short_trials][:, :, 10:].any()  # short trials are zero-padded after 1 s


def test_nan_speed_skips_speed_variants_by_default(encoded):
    with open_encoded(encoded) as f:
        skipped = f.skipped_variants
        assert set(skipped) == {"speed_scaled", "speed_force_scaled", "speed_force_scaled_label_free",
                                "realtime_speed_scaled"}
        assert all(", ".join(map(str, NAN_IDS[:10])) in why for why in skipped.values())
        assert set(f.variants) == {"original", "force_scaled", "force_scaled_label_free", "realtime_original"}


def test_force_scaled_with_nan_speed(encoded):
    with open_encoded(encoded) as f:
        fc = f.force_coefficients()
        assert fc is not None  # fitted: a trial's unknown speed is one condition with its own 500 g reference
        assert set(fc["texture"]) == {"Linen", "HB3", "Denim"}  # full labels, not truncated
        assert np.isnan(fc["speed_mm_s"]).any() and (fc["speed_mm_s"] == 50).any()
        np.testing.assert_allclose(fc["coeff"][fc["force_g"] == 500], 1.0)
        orig, forced = f.features("original"), f.features("force_scaled")
        assert orig.shape == forced.shape and not np.array_equal(orig, forced)


def test_explicit_speed_variant_with_nan_speed_is_refused(session, tmp_path):
    out = tmp_path / "refused.h5"
    with pytest.raises(SpeedMissingError) as err:
        encode_session(session, out, variants=["original", "speed_scaled"], progress=False)
    msg = str(err.value)
    assert "speed_scaled" in msg and f"{len(NAN_IDS)} of {len(PLAN)} trials" in msg
    assert "trials " + ", ".join(map(str, NAN_IDS[:10])) in msg
    assert not out.exists() and not out.with_name(out.name + ".part").exists()


def test_explicit_unscaled_variants_with_nan_speed(session, tmp_path):
    out = tmp_path / "orig.h5"
    encode_session(session, out, variants=["original", "force_scaled"], progress=False)
    with open_encoded(out) as f:
        assert f.variants == ("original", "force_scaled") and f.skipped_variants == {}


def test_cli_speed_error_is_one_line(session, tmp_path):
    from rigctl.cli import main

    out = tmp_path / "cli.h5"
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--quiet",
                                    "--variant", "speed_scaled"])
    assert res.exit_code != 0
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error:") and "no speed" in lines[0], res.output
    assert "Traceback" not in res.output and not out.exists()
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--quiet", "--variant", "original",
                                    "--window-ms", "250"])
    assert res.exit_code == 0, res.output
    assert "100 Hz -> 1000 Hz" in res.output and "9 taxels" in res.output
    with open_encoded(out) as f:
        assert f.feature_shape("original") == (len(PLAN), 18 * 10)  # 2.5 s in 250 ms windows


def test_rate_conversion():
    conv = rate_conversion(1000.0)
    x = np.arange(30, dtype=np.uint16).reshape(10, 3)
    assert not conv.resampled and conv.apply(x) is x  # the paper's rate: the readings reach the model unchanged
    conv = rate_conversion(100.0)
    assert (conv.up, conv.down, conv.model_rate_hz) == (10, 1, 1000.0) and conv.n_out(100) == 1000
    t_in = np.arange(200) / 100.0
    y = conv.apply(np.sin(2 * np.pi * 1.0 * t_in)[:, None])
    t_out = np.arange(2000) / 1000.0
    assert y.shape == (2000, 1)
    inner = slice(100, 1900)  # away from the ends
    np.testing.assert_allclose(y[inner, 0], np.sin(2 * np.pi * t_out[inner]), atol=0.01)
    down = rate_conversion(2000.0)
    assert (down.up, down.down) == (1, 2) and down.apply(np.zeros((100, 2))).shape == (50, 2)
    with pytest.raises(ValueError):
        rate_conversion(0.0)


def test_batch_and_streaming_encoders_use_the_rate():
    """encode_sa / encode_ra at fs=100 resample to the model's 1 kHz (as the pipeline does); the streaming encoder
    at fs=100 resamples chunk by chunk: the same model input away from the stream's start, spike times in s of the
    stream."""
    from rigctl.encoding.izhikevich import StreamingEncoder, encode_ra, encode_sa
    from rigctl.encoding.normalise import TaxelRange
    from rigctl.encoding.rate import StreamResampler

    x = _readings(0, "Linen", 500.0, 3.0)
    rng = TaxelRange().update(x)
    conv = rate_conversion(RATE_HZ)
    sa = encode_sa([x], normalise=rng, fs=RATE_HZ)
    assert sa == encode_sa([conv.apply(x)], normalise=rng)  # the same as resampling first, then 1 kHz
    ra = encode_ra([x], normalise=rng, fs=RATE_HZ)
    assert ra == encode_ra([conv.apply(x)], normalise=rng)
    assert 2.5 < sa.spike_times.max() < 3.0 and 2.5 < ra.spike_times.max() < 3.0  # 3 s, not 0.3 s

    res = StreamResampler(conv, LAYOUT.n_channels)
    y = np.concatenate([res.process(x[i:i + 7]) for i in range(0, x.shape[0], 7)])
    batch = conv.apply(x)
    assert 0 < batch.shape[0] - y.shape[0] <= 100  # the filter's delay (10 input samples) is still in the pipe
    np.testing.assert_allclose(y[200:], batch[200:y.shape[0]], rtol=0, atol=1e-9)

    enc = StreamingEncoder(LAYOUT.n_channels, normalise=rng, fs=RATE_HZ)
    chunks = [enc.process(x[i:i + 4]) for i in range(0, x.shape[0], 4)]
    assert sum(c.n_samples for c in chunks) == x.shape[0] and enc.n_samples == y.shape[0]
    live = SpikeTrains.concat_time([c.sa for c in chunks])
    assert 2.5 < live.spike_times.max() < 3.0
    # the neurons see the same input after the first 100 ms (the stream's last 100 ms are still in the filter):
    # spike counts over 0.2-2.8 s agree closely
    def counts(st):
        return np.array([np.count_nonzero((st.train(0, j) >= 0.2) & (st.train(0, j) < 2.8))
                         for j in range(st.n_trains)])

    np.testing.assert_allclose(counts(live), counts(sa), rtol=0.03)


def test_encode_batch_like_the_file(session, encoded):
    """A new trial encoded with the file's parameters and rate gets the file's feature columns (live
    classification), and the file's own trials reproduce their rows."""
    from rigctl.encoding.normalise import TaxelRange
    from rigctl.encoding.pipeline import EncodeParams, encode_batch
    from rigctl.storage.session import open_session

    with open_encoded(encoded) as f:
        params = EncodeParams.from_dict(f.parameters)
        norm = f.normalisation
        rows = f.features("original")
    offset, scale = TaxelRange(norm["taxel_min"], norm["taxel_max"]).offset_scale()
    with open_session(session) as s:
        short = np.asarray(s.trial(0).taxels)  # 1 s, at 100 Hz
    feats, _ = encode_batch([short], offset=offset, scale=scale, speed_mm_s=[np.nan], variants=["original"],
                            params=params, store_spikes=(), rate_hz=RATE_HZ)
    assert feats["original"].shape == (1, rows.shape[1])  # 25 windows, as the file, not 10
    np.testing.assert_array_equal(feats["original"][0], rows[0])
