"""``rigctl export nir``: a saved model's readout (PCA + nested-PC LDA) as a NIR graph (issue 79 item 4). The graph,
read back by the ``nir`` package, is ``Input -> Affine -> Output``; its affine map applied to the model's own window
features gives the model's prediction on every trial, with the model's PCs and with fewer; a model of a real-time
variant (SA trains only) too. What it writes and refuses goes through the output policy."""

from __future__ import annotations

import nir  # a test extra: its absence fails the module
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main

PROTOCOL = """
name = "nir"
textures = ["A", "F", "L"]
speeds_mm_s = [60, 100]
forces_g = [250, 500]
trials_per_condition = 4
duration_s = 0.4
"""


@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.analysis.model import trials_of_session
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("nir")
    generate_dataset(parse_protocol(PROTOCOL), d / "s.h5", workers=0, seed=5)
    return d, *trials_of_session(d / "s.h5")


def _model(trials, variant, n_pcs):
    from rigctl.analysis.model import texture_pipeline
    from rigctl.storage.model_file import save_model

    d, x, y = trials
    fitted = texture_pipeline(variant, n_pcs).fit(x, y)
    path = d / f"{variant}.skops"
    if not path.exists():
        save_model(fitted, path, info={"variant": variant})
    return fitted, path


def _graph_predictions(path, features):
    graph = nir.read(str(path))
    assert sorted(graph.nodes) == ["input", "output", "readout"] and sorted(graph.edges) == [("input", "readout"),
                                                                                  ("readout", "output")]
    affine = graph.nodes["readout"]
    assert isinstance(affine, nir.Affine)
    classes = np.array([c.decode() if isinstance(c, bytes) else str(c) for c in graph.metadata["classes"]])
    scores = np.asarray(features, np.float64) @ affine.weight.T + affine.bias
    return classes[np.argmax(scores, axis=1)], graph


@pytest.mark.parametrize("variant, n_pcs, pcs_option", [("speed_scaled", 8, None), ("original", 8, 3),
                                                       ("realtime_speed_scaled", 6, None)])
def test_the_nir_graph_decides_as_the_model(trials, tmp_path, variant, n_pcs, pcs_option):
    fitted, path = _model(trials, variant, n_pcs)
    _, x, _ = trials
    out = tmp_path / "m.nir"
    args = ["export", "nir", str(path), "--out", str(out)] + (["--pcs", str(pcs_option)] if pcs_option else [])
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    features = fitted[:-1].transform(x)
    expected = fitted[-1].predict(features, n_pcs=pcs_option)
    got, graph = _graph_predictions(out, features)
    assert len(set(expected)) > 1  # a model that says one texture for all would prove nothing
    np.testing.assert_array_equal(got, expected)  # 100 % of the trials
    meta = graph.metadata
    assert meta["variant"] == variant and int(meta["n_pcs"]) == (pcs_option or n_pcs)
    n_windows, n_sa, n_ra = int(meta["n_windows"]), int(meta["n_sa_trains"]), int(meta["n_ra_trains"])
    assert (n_sa + n_ra) * n_windows == features.shape[1]
    assert (n_ra == 0) == variant.startswith("realtime")
    assert ("speed-scaled" in meta["time_base"]) == ("speed_scaled" in variant)


def test_the_command_refuses_what_it_must(trials, tmp_path):
    _, path = _model(trials, "speed_scaled", 8)
    out = tmp_path / "m.nir"
    assert CliRunner().invoke(main, ["export", "nir", str(path), "--out", str(out)]).exit_code == 0
    before = out.read_bytes()
    again = CliRunner().invoke(main, ["export", "nir", str(path), "--out", str(out)])  # exists, no --overwrite
    assert again.exit_code != 0 and "Traceback" not in again.output and out.read_bytes() == before
    assert CliRunner().invoke(main, ["export", "nir", str(path), "--out", str(out), "--overwrite"]).exit_code == 0
    too_many = CliRunner().invoke(main, ["export", "nir", str(path), "--out", str(tmp_path / "x.nir"), "--pcs", "999"])
    assert too_many.exit_code == 2 and "--pcs" in too_many.output and not (tmp_path / "x.nir").exists()
    not_a_model = tmp_path / "n.skops"
    not_a_model.write_bytes(b"not a zip")
    bad = CliRunner().invoke(main, ["export", "nir", str(not_a_model), "--out", str(tmp_path / "y.nir")])
    assert bad.exit_code == 1 and "not a rigctl model file" in bad.output and len(bad.output.splitlines()) == 1
    session = trials[0] / "s.h5"  # a session is never replaced by a NIR export
    kept = session.read_bytes()
    r = CliRunner().invoke(main, ["export", "nir", str(path), "--out", str(session), "--overwrite"])
    assert r.exit_code != 0 and session.read_bytes() == kept
