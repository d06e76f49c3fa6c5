"""`rigctl analyze`: JSON and table output shapes, plots, and the session-file message."""

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.analysis.synthetic import synthetic_features
from rigctl.cli import main


@pytest.fixture(scope="module")
def encoded(tmp_path_factory, write_schema1):
    fs = synthetic_features(5, n_textures=6, n_channels=4, noise=0.8, seed=5)
    # an unversioned (schema 1) file, as the old pipeline wrote it: 2 taxels x SA/RA
    return write_schema1(fs, tmp_path_factory.mktemp("ana") / "enc.h5", 2)


def test_json_output_shape(encoded, tmp_path):
    png, csv = tmp_path / "fig3.png", tmp_path / "t.csv"
    r = CliRunner().invoke(main, ["analyze", str(encoded), "--task", "all", "--repeats", "2", "--pcs", "1-8",
                                  "--json", "--no-progress", "--plot", str(png), "--csv", str(csv)])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert set(out["tasks"]) == {"textures", "groups", "untrained_speed_force", "untrained_force",
                                 "untrained_speed", "trained"}
    assert out["table_pcs"] == 8
    for task in out["tasks"].values():
        assert set(task["variants"]) == {"original", "speed_scaled", "force_scaled", "speed_force_scaled"}
        for v in task["variants"].values():
            assert len(v["mean"]) == len(v["sd"]) == 8 and v["n_repeats"] == 2
            assert 0 <= v["table"]["mu_pct"] <= 100
        assert {c["variant"] for c in task["comparisons"]} == {"speed_scaled", "force_scaled", "speed_force_scaled"}
    assert out["counts"]["cv"]["per_texture"] == 75
    assert set(out["ordering"]) == {"textures", "groups", "untrained_speed_force", "untrained_force", "untrained_speed"}
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert len(csv.read_text().splitlines()) == 1 + 6 * 4 * 8


def test_table1_layout(encoded):
    r = CliRunner().invoke(main, ["analyze", str(encoded), "--table1", "--repeats", "2", "--pcs", "6",
                                  "--compare-paper", "--no-progress", "--variants", "original,speed_scaled"])
    assert r.exit_code == 0, r.output
    lines = r.stdout.splitlines()
    assert lines[0] == "Classification accuracy with 6 PCs (%)"  # --pcs 6: nobody asked for 50 (the default of
    # --table-pcs), so no "[asked for 50]" (issue 24)
    rows = [ln for ln in lines if ln.startswith(("Individual", "Texture Groups", "Untrained", "Trained"))]
    assert [r_.split("  ")[0] for r_ in rows] == ["Individual Textures (Fig. 3A)", "Texture Groups (Fig. 3B)",
                                                  "Untrained Speed and Force (Fig. 3C)", "Untrained Force (Fig. 3D)",
                                                  "Untrained Speed (Fig. 3E)", "Trained Speed and Force (Fig. 3F)"]
    assert sum("paper (50 PCs)" in ln for ln in lines) == 6
    assert "91.78" in r.stdout  # the paper's Original / Individual Textures
    assert "Speed Scaled" in lines[1] and "Force Scaled" not in lines[1]


def test_speed_extrapolation_with_baseline_both(encoded):
    r = CliRunner().invoke(main, ["analyze", str(encoded), "--task", "speed-extrapolation", "--train-speeds",
                                  "40,60", "--test-speeds", "120", "--baseline", "both", "--repeats", "2", "--pcs",
                                  "5", "--json", "--no-progress"])
    assert r.exit_code == 0, r.output
    tasks = json.loads(r.stdout)["tasks"]
    assert set(tasks) == {"speed_untrained_speed", "speed_trained", "baseline_removed:speed_untrained_speed",
                          "baseline_removed:speed_trained"}
    assert tasks["speed_untrained_speed"]["variants"]["original"]["n_tested"] == 6 * 3 * 1  # 120 mm/s x 3 forces


def test_session_file_is_refused_with_a_hint(tmp_path):
    session = tmp_path / "session.h5"
    with h5py.File(session, "w") as f:
        f.create_group("trials")
        f["plan"] = np.zeros(3)
    r = CliRunner().invoke(main, ["analyze", str(session), "--no-progress"])
    assert r.exit_code != 0
    assert "rigctl encode" in r.output and "session file" in r.output
