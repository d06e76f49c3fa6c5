"""encode_session on a small simulated session: file layout, consistency of spikes and features, Dask == local,
and the `rigctl encode` command."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.encoding.pipeline import MAIN_VARIANTS, encode_session
from rigctl.encoding.spikes import SpikeTrains

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
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("enc")
    proto = d / "enc_test.toml"
    proto.write_text(PROTOCOL)
    path = d / "session.h5"
    generate_dataset(proto, path, seed=3, workers=0, progress=False)
    return path


@pytest.fixture(scope="module")
def encoded(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("encout") / "enc.h5"
    encode_session(session, out, batch_trials=5, progress=False)
    return out


def test_layout_and_shapes(encoded):
    with h5py.File(encoded, "r") as f:
        trials = f["trials"][()]
        assert trials.size == 24
        assert set(trials["texture"]) == {b"A", b"L"}
        assert set(trials["group"]) == {b"smooth", b"waves"}
        assert set(trials["speed_mm_s"]) == {60.0, 120.0}
        assert f["features/original"].shape == (24, 2160)
        assert f["features/force_scaled"].shape == (24, 2160)
        assert f["features/speed_scaled"].shape == (24, 720)
        assert f["features/speed_force_scaled"].shape == (24, 720)
        assert f["features/realtime_speed_scaled"].shape == (24, 180)
        assert f["features/original"].dtype == np.float32
        fc = f["force_coefficients"]
        # 2 textures x 2 speeds x 3 forces x 18 taxels; the 500 g ones are 1
        assert fc.shape == (216,) and fc.attrs["n_coefficients"] == 216
        ref = fc["force_g"] == 500
        np.testing.assert_allclose(fc["coeff"][ref], 1.0)
        assert np.all(fc["coeff"] <= 5.0) and np.all(fc["coeff"] >= 0)
        assert 0 <= fc.attrs["n_not_converged"] <= 216
        assert f["force_coefficients_label_free"].shape == (108,)
        # lighter touch needs a larger coefficient than heavier touch (on average over converged taxels)
        ok = fc["converged"]
        assert fc["coeff"][ok & (fc["force_g"] == 250)].mean() > fc["coeff"][ok & (fc["force_g"] == 1000)].mean()
        assert f["normalisation/taxel_max"].shape == (18,)


def test_spikes_and_features_agree(encoded):
    with h5py.File(encoded, "r") as f:
        for v in MAIN_VARIANTS:
            st = SpikeTrains.from_hdf5(f["spikes"][v])
            assert st.shape == (24, 36)
            feats = f["features"][v][()]
            n_win = feats.shape[1] // 36
            counts = st.window_counts(0.1, n_win)
            ra_feats = feats.reshape(24, 36, n_win)[:, 18:, :]
            np.testing.assert_allclose(ra_feats, counts[:, 18:, :])  # RA columns are spike counts
        trials = f["trials"][()]
        orig = SpikeTrains.from_hdf5(f["spikes/original"])
        scaled = SpikeTrains.from_hdf5(f["spikes/speed_scaled"])
        t = int(np.flatnonzero(trials["speed_mm_s"] == 60)[0])
        np.testing.assert_allclose(scaled.train(t, 0), orig.train(t, 0) * 0.5)
        # force scaling changes only SA trains
        fs = SpikeTrains.from_hdf5(f["spikes/force_scaled"])
        for j in range(18, 36):
            np.testing.assert_array_equal(fs.train(t, j), orig.train(t, j))


def test_dask_cluster_by_address_gives_the_same_file(session, encoded, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    out = tmp_path / "dask.h5"
    # a separate scheduler + worker process, reached by its address as a remote cluster would be
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        encode_session(session, out, batch_trials=7, scheduler=c.scheduler_address, progress=False)
    with h5py.File(out, "r") as a, h5py.File(encoded, "r") as b:
        for v in b["features"]:
            np.testing.assert_array_equal(a["features"][v][()], b["features"][v][()])
        np.testing.assert_array_equal(a["spikes/original/spike_times"][()], b["spikes/original/spike_times"][()])


def test_cli_encode(session, tmp_path):
    from rigctl.cli import main

    out = tmp_path / "cli.h5"
    res = CliRunner().invoke(main, ["encode", str(session), "--out", str(out), "--batch", "8", "--quiet",
                                    "--variant", "original", "--variant", "speed_scaled"])
    assert res.exit_code == 0, res.output
    assert "24 trials" in res.output
    with h5py.File(out, "r") as f:
        assert set(f["features"]) == {"original", "speed_scaled"}
    bad = CliRunner().invoke(main, ["encode", str(session), "--variant", "nope"])
    assert bad.exit_code != 0 and "nope" in bad.output
