"""encode_session on a small simulated session (the paper's 3x3x2 sensor at 1 kHz): file layout, consistency of
spikes and features, the paper's numerics (no resampling at 1 kHz), Dask == local, and the `rigctl encode` command."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.encoding.pipeline import encode_session
from rigctl.encoding.spikes import SpikeTrains
from rigctl.storage.encoded import ENCODED_SCHEMA_VERSION, MAIN_VARIANTS, open_encoded

PROTOCOL = """
name = "enc_test"
textures = ["A", "L"]
speeds_mm_s = [60, 120]
forces_g = [250, 500, 1000]
trials_per_condition = 2
travel_mm = 60
order = "blocked"
"""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("enc")
    proto = d / "enc_test.toml"
    proto.write_text(PROTOCOL)
    path = d / "session.h5"
    generate_dataset(load_protocol(proto), path, seed=3, workers=0, progress=False)
    return path


@pytest.fixture(scope="module")
def encoded(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("encout") / "enc.h5"
    encode_session(session, out, batch_trials=5, progress=False)
    return out


def test_layout_and_shapes(encoded):
    with open_encoded(encoded) as f:
        assert f.schema_version == ENCODED_SCHEMA_VERSION
        assert f.layout.n_channels == 18 and f.layout.sample_rate_hz == 1000.0
        assert f.textures.labels == tuple("ABCDEFGHIJKLMNOP")  # the paper's set: A and L are in it
        assert f.resampling == {"input_rate_hz": 1000.0, "model_rate_hz": 1000.0, "resampled": False}
        trials = f.trials
        assert trials["trial_id"].size == 24
        assert set(trials["texture"]) == {"A", "L"}
        assert set(trials["group"]) == {"smooth", "waves"}
        assert set(trials["speed_mm_s"]) == {60.0, 120.0}
        # 60 mm of travel: 1 s at 60 mm/s is the longest trial -> 10 windows of 100 ms per train (not a fixed 60)
        np.testing.assert_allclose(trials["duration_s"].max(), 1.0)
        assert f.parameters["n_windows_unscaled"] == 10
        assert f.feature_shape("original") == (24, 36 * 10)
        assert f.feature_shape("force_scaled") == (24, 36 * 10)
        assert f.feature_shape("speed_scaled") == (24, 720)
        assert f.feature_shape("speed_force_scaled") == (24, 720)
        assert f.feature_shape("realtime_speed_scaled") == (24, 180)
        assert f.features("original").dtype == np.float32
        fc = f.force_coefficients()
        st = f.force_fit_stats()
        # 2 textures x 2 speeds x 3 forces x 18 taxels; the 500 g ones are 1
        assert fc.shape == (216,) and st["n_coefficients"] == 216
        assert set(fc["texture"]) == {"A", "L"}
        ref = fc["force_g"] == 500
        np.testing.assert_allclose(fc["coeff"][ref], 1.0)
        assert np.all(fc["coeff"] <= 5.0) and np.all(fc["coeff"] >= 0)
        assert 0 <= st["n_not_converged"] <= 216
        assert f.force_coefficients(label_free=True).shape == (108,)
        # lighter touch needs a larger coefficient than heavier touch (on average over converged taxels)
        ok = fc["converged"]
        assert fc["coeff"][ok & (fc["force_g"] == 250)].mean() > fc["coeff"][ok & (fc["force_g"] == 1000)].mean()
        assert f.normalisation["taxel_max"].shape == (18,)


def test_spikes_and_features_agree(encoded):
    with open_encoded(encoded) as f:
        for v in MAIN_VARIANTS:
            st = SpikeTrains(*f.spikes(v))
            assert st.shape == (24, 36)
            feats = f.features(v)
            n_win = feats.shape[1] // 36
            counts = st.window_counts(0.1, n_win)
            ra_feats = feats.reshape(24, 36, n_win)[:, 18:, :]
            np.testing.assert_allclose(ra_feats, counts[:, 18:, :])  # RA columns are spike counts
        trials = f.trials
        orig = SpikeTrains(*f.spikes("original"))
        scaled = SpikeTrains(*f.spikes("speed_scaled"))
        t = int(np.flatnonzero(trials["speed_mm_s"] == 60)[0])
        np.testing.assert_allclose(scaled.train(t, 0), orig.train(t, 0) * 0.5)
        # eq. 2 exactly as the encoder applies it, although the file keeps only the ticks of the unscaled trains
        assert scaled == orig.scale_times(trials["speed_mm_s"].astype(np.float64) / 120.0)
        # force scaling changes only SA trains
        fs = SpikeTrains(*f.spikes("force_scaled"))
        for j in range(18, 36):
            np.testing.assert_array_equal(fs.train(t, j), orig.train(t, j))


def test_paper_rig_numerics_unchanged(session, encoded):
    """At the paper's 1 kHz nothing is resampled: the pipeline's Original features are those of the batch encoder
    (encode_sa / encode_ra on the raw counts, the dataset's per-taxel range) in 100 ms windows."""
    from rigctl.encoding.features import spike_features
    from rigctl.encoding.izhikevich import encode_ra, encode_sa
    from rigctl.encoding.normalise import TaxelRange
    from rigctl.storage.session import open_session

    with open_session(session) as s:
        readings = [np.asarray(s.trial(t).taxels) for t in s.completed_ids()]
    rng = TaxelRange()
    for x in readings:
        rng.update(x)
    sa = encode_sa(readings, normalise=rng)
    ra = encode_ra(readings, normalise=rng)
    with open_encoded(encoded) as f:
        np.testing.assert_array_equal(f.normalisation["taxel_min"], rng.minimum)
        expected = spike_features(sa, ra, n_windows=10)
        np.testing.assert_array_equal(f.features("original"), expected)
        st = SpikeTrains(*f.spikes("original"))
        np.testing.assert_array_equal(st.select_trains(range(18)).spike_times, sa.spike_times)


def test_window_parameters(session, tmp_path):
    from rigctl.encoding.pipeline import EncodeParams

    out = tmp_path / "w.h5"
    encode_session(session, out, variants=["original", "speed_scaled"], progress=False, store_spikes=(),
                   params=EncodeParams(window_s=0.05, n_windows_unscaled=60, n_windows_scaled=30))
    with open_encoded(out) as f:
        assert f.feature_shape("original") == (24, 36 * 60)  # 60 windows of 50 ms, asked for
        assert f.feature_shape("speed_scaled") == (24, 36 * 30)
        assert f.parameters["window_s"] == 0.05
        assert f.spike_variants == ()
        x = f.features("original").reshape(24, 36, 60)
        assert x[:, :, :20].any() and not x[:, :, 20:].any()  # 1 s trials fill 20 windows of 50 ms


def test_trials_read_again_when_they_do_not_fit_memory(session, encoded, tmp_path):
    """Trials are read once and kept when they fit ``fit_memory_bytes``; when not, the force fit uses a subsample
    per condition and the encode pass reads each batch again: the same features where the fit does not enter."""
    out = tmp_path / "small.h5"
    encode_session(session, out, variants=["original", "force_scaled"], fit_memory_bytes=1, batch_trials=7,
                   store_spikes=("original",), progress=False)
    with open_encoded(out) as a, open_encoded(encoded) as b:
        assert a.force_fit_stats()["n_fit_trials"] == 12  # one trial of each of the 12 conditions
        assert b.force_fit_stats()["n_fit_trials"] == 24
        np.testing.assert_array_equal(a.features("original"), b.features("original"))
        assert SpikeTrains(*a.spikes("original")) == SpikeTrains(*b.spikes("original"))


def test_dask_cluster_by_address_gives_the_same_file(session, encoded, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    out = tmp_path / "dask.h5"
    # a separate scheduler + worker process, reached by its address as a remote cluster would be
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        encode_session(session, out, batch_trials=7, scheduler=c.scheduler_address, progress=False)
    with open_encoded(out) as a, open_encoded(encoded) as b:
        assert a.variants == b.variants
        for v in b.variants:
            np.testing.assert_array_equal(a.features(v), b.features(v))
        assert SpikeTrains(*a.spikes("original")) == SpikeTrains(*b.spikes("original"))


def test_cli_encode(session, tmp_path):
    from rigctl.cli import main

    out = tmp_path / "cli.h5"
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--batch", "8", "--quiet",
                                    "--variant", "original", "--variant", "speed_scaled", "--window-ms", "200",
                                    "--windows-scaled", "10"])
    assert res.exit_code == 0, res.output
    assert "24 trials" in res.output and "18 taxels" in res.output
    with open_encoded(out) as f:
        assert set(f.variants) == {"original", "speed_scaled"}
        assert f.feature_shape("original") == (24, 36 * 5)  # 1 s in 200 ms windows
        assert f.feature_shape("speed_scaled") == (24, 36 * 10)
    again = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--quiet"])
    assert again.exit_code != 0 and "--overwrite" in again.output and "Traceback" not in again.output
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--quiet", "--overwrite",
                                    "--variant", "original", "--windows-unscaled", "3"])
    assert res.exit_code == 0, res.output
    with open_encoded(out) as f:
        assert f.variants == ("original",) and f.feature_shape("original") == (24, 36 * 3)
    # whole trials in scaled time: 60 mm at either speed is 0.5 s at the 120 mm/s reference -> 5 windows
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--quiet", "--overwrite",
                                    "--variant", "speed_scaled", "--windows-scaled", "longest"])
    assert res.exit_code == 0, res.output
    with open_encoded(out) as f:
        assert f.feature_shape("speed_scaled") == (24, 36 * 5) and f.parameters["n_windows_scaled"] == 5
        assert "scaled time" in f.attrs["windows_note"]
    bad = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--windows-scaled", "many"])
    assert bad.exit_code != 0 and "many" in bad.output
    bad = CliRunner().invoke(main, ["encode", str(session), "--variant", "nope"])
    assert bad.exit_code != 0 and "nope" in bad.output


def _datasets(path) -> dict[str, np.ndarray]:
    import h5py

    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_the_range_from_the_validators_extremes_gives_the_file_a_full_read_gives(session, tmp_path, monkeypatch):
    """A session whose batches the encode pass reads again takes its per-taxel range from the extremes the validator
    found in the same counts (no second read of every sample in pass 1; only the force fit's subsample): every dataset
    of the encoded file (features, spike trains, the normalisation, the force coefficients) is the full read's, bit
    for bit; and the shortcut was taken."""
    import rigctl.encoding.pipeline as pipeline

    taken = []
    shortcut = pipeline._range_from_extremes
    monkeypatch.setattr(pipeline, "_range_from_extremes", lambda *a: taken.append(1) or shortcut(*a))
    kw = dict(fit_memory_bytes=20_000, batch_trials=7, store_spikes=("original", "force_scaled"), progress=False)
    encode_session(session, tmp_path / "short.h5", **kw)
    assert taken, "the range was read again from every sample"
    monkeypatch.setattr(pipeline, "_extremes_known", lambda *a: None)  # the full read of pass 1
    encode_session(session, tmp_path / "full.h5", **kw)
    assert len(taken) == 1
    a, b = _datasets(tmp_path / "short.h5"), _datasets(tmp_path / "full.h5")
    assert a.keys() == b.keys() and any(k.startswith("features/") for k in a)
    with open_encoded(tmp_path / "short.h5") as f:
        assert 0 < f.force_fit_stats()["n_fit_trials"] < 24  # a subsample: the encode pass read the batches again
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("fit_memory_bytes", [20_000, 1e9])  # a subsample (the encode pass reads again); every trial
def test_pass_1_takes_the_counts_the_validator_read(session, tmp_path, monkeypatch, fit_memory_bytes):
    """The force fit's counts (every trial's when they all fit ``fit_memory_bytes``, which the encode pass then uses
    too) are the ones the validator read, handed over as it passed them (``KeptTaxels``): pass 1 reads no taxels of
    its own (before, it read the fit's subsample again, or every trial), and every dataset of the encoded file is
    the one reading them again gives, bit for bit."""
    import rigctl.encoding.pipeline as pipeline
    from rigctl.storage.session_reader import SessionReader
    from rigctl.storage.validate import KeptTaxels

    reads: list[int] = []
    real = SessionReader.read_taxels
    monkeypatch.setattr(SessionReader, "read_taxels",
                        lambda self, ids, **kw: reads.append(len(ids)) or real(self, ids, **kw))
    kw = dict(fit_memory_bytes=fit_memory_bytes, batch_trials=7, store_spikes=("original", "force_scaled"),
              progress=False)
    encode_session(session, tmp_path / "handed.h5", **kw)
    handed = list(reads)
    monkeypatch.setattr(pipeline, "_kept_for_fit", lambda s, *a: KeptTaxels(s, ()))  # nothing kept: pass 1 reads
    reads.clear()
    encode_session(session, tmp_path / "read.h5", **kw)
    batches = [7, 7, 7, 3]
    if fit_memory_bytes < 1e6:  # only the encode pass's batches; before, the subsample's reads in pass 1 too
        assert handed == batches and len(reads) > len(batches), (handed, reads)
    else:  # every batch from the validator's read; before, pass 1 read them
        assert handed == [] and reads == batches, (handed, reads)
    a, b = _datasets(tmp_path / "handed.h5"), _datasets(tmp_path / "read.h5")
    assert a.keys() == b.keys() and any(k.startswith("spikes/") for k in a)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_the_validators_taxel_extremes_are_each_trials_counts_extremes(session):
    """TrialReport.taxel_extremes: each usable trial's per-taxel minimum and maximum count, as its taxels read."""
    from rigctl.storage.session import open_session
    from rigctl.storage.validate import usable_trials

    with open_session(session) as s:
        report = usable_trials(s)
        assert set(report.taxel_extremes) >= set(report.ids) and report.ids
        for t in report.ids:
            counts = s.read_taxels([t]).data
            ext = report.taxel_extremes[t]
            assert ext.dtype == np.uint16 and ext.shape == (2, counts.shape[1])
            np.testing.assert_array_equal(ext, np.stack([counts.min(axis=0), counts.max(axis=0)]))
