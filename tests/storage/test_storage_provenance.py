"""Provenance in every file (issue 27 item 4): a quick_check recorded on the in-process rig holds its UUID, rigctl's
version and git state, Python and package versions, host, command line, both boards' firmware against the installed
sources, the protocol text, the rig config and calibration with dates, and seeds; `rigctl info --provenance` prints
them; the encoded file adds the encoder's parameters, the NWB export carries both files' provenance nested."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl import __version__
from rigctl.cli import main
from rigctl.core.provenance import KEY_PACKAGES
from rigctl.storage.provenance import ProvenanceError, read_provenance

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.acquisition.rigconfig import update_rig_config
    from rigctl.acquisition.runner import run_protocol
    from rigctl.rigs import open_rig

    d = tmp_path_factory.mktemp("prov")
    config = d / "rig.json"
    update_rig_config(config, loadcell={"counts_per_g": 400.0, "calibrated_utc": "2026-01-02T03:04:05+00:00"})
    proto = load_protocol(REPO / "protocols" / "quick_check.toml").with_seed(11)
    with open_rig("inprocess", seed=7, host_config_path=config) as rig:
        run_protocol(proto, d / "quick.h5", rig=rig, progress=False)
    return d / "quick.h5"


def test_a_recorded_session_holds_every_item(recorded):
    import h5py

    p = read_provenance(recorded)
    with h5py.File(recorded, "r") as f:
        assert p["session_id"] == f.attrs["session_id"] and len(p["session_id"]) == 36
    assert p["rigctl_version"] == __version__
    assert p["git"] is None or (len(p["git"]["commit"]) == 40 and isinstance(p["git"]["dirty"], bool))
    assert p["python"]["version"] == ".".join(map(str, sys.version_info[:3]))
    assert set(p["packages"]) == set(KEY_PACKAGES) and p["packages"]["numpy"]
    assert p["host"]["node"]
    # recorded in this process: its whole command line (sys.orig_argv; under pytest-xdist sys.argv is only ['-c'])
    import shlex

    assert p["command_line"] == shlex.join(sys.orig_argv) and "python" in p["command_line"]
    fw = p["firmware"]
    from rigctl import firmware

    want = firmware.source_versions()
    assert fw["mega"]["version"] == list(want["mega"]) and fw["mega"]["matches_sources"] is True
    assert fw["uno"]["version"] == list(want["uno"]) and fw["uno"]["matches_sources"] is True
    assert fw["sources_digest"] == firmware.source_digest()
    assert 'name = "quick_check"' in p["protocol"]["source"] and p["protocol"]["seed"] == 11
    assert p["rig"]["seed"] == 7 and p["rig"]["mode"] == "inprocess"
    assert p["rig_config"]["loadcell"]["counts_per_g"] == 400.0
    assert p["rig_config_dates"] == {"loadcell": "2026-01-02T03:04:05+00:00"}


def test_info_prints_it(recorded):
    res = CliRunner().invoke(main, ["info", "--provenance", str(recorded)])
    assert res.exit_code == 0, res.output
    for needle in ("session_id: ", "rigctl_version: ", "git.", "python.version: ", "packages.numpy: ",
                   "host.node: ", "command_line: ", "firmware.mega.version: ", "firmware.uno.matches_sources: True",
                   "protocol.source:", '    name = "quick_check"', "rig_config.loadcell.calibrated_utc: ",
                   "rig.seed: 7"):
        assert needle in res.output, needle
    res = CliRunner().invoke(main, ["info", "--provenance", "--json", str(recorded)])
    assert res.exit_code == 0 and json.loads(res.output)["protocol"]["seed"] == 11


def test_encoded_and_nwb_files_carry_it(recorded, tmp_path):
    from rigctl.encoding.pipeline import encode_session
    from rigctl.storage.nwb import export_nwb

    enc = tmp_path / "quick.enc.h5"
    encode_session(recorded, enc, variants=["original"], progress=False)
    pe = read_provenance(enc)
    assert pe["encoder"]["variants"] == ["original"] and "window_s" in json.dumps(pe["encoder"]["parameters"])
    session = read_provenance(recorded)
    assert pe["source_session"]["provenance"]["session_id"] == session["session_id"]
    nwb = tmp_path / "quick.nwb"
    export_nwb(recorded, nwb, encoded_path=enc)
    pn = read_provenance(nwb)
    assert pn["source_session"]["provenance"] == session
    assert pn["encoded"]["provenance"]["provenance_id"] == pe["provenance_id"]
    assert pn["provenance_id"] not in (session["provenance_id"], pe["provenance_id"])
    res = CliRunner().invoke(main, ["info", "--provenance", str(nwb)])
    assert res.exit_code == 0 and "source_session.provenance.firmware.mega.version" in res.output


def test_imported_and_generated_sessions_carry_it_too(tmp_path):
    rng = np.random.default_rng(1)
    np.save(tmp_path / "A__1.npy", rng.integers(0, 1024, (300, 4)))
    res = CliRunner().invoke(main, ["import", str(tmp_path / "A__1.npy"), "--out", str(tmp_path / "imp.h5"),
                                    "--rate", "500", "--texture", "A", "--quiet"])
    assert res.exit_code == 0, res.output
    p = read_provenance(tmp_path / "imp.h5")
    assert p["kind"] == "imported" and p["rigctl_version"] == __version__ and p["command_line"]
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.simulation.dataset import generate_dataset

    proto = parse_protocol('name = "d"\ntextures = ["A"]\nspeeds_mm_s = [60]\nforces_g = [250]\n'
                           'trials_per_condition = 1\nduration_s = 0.2\n')
    generate_dataset(proto, tmp_path / "ds.h5", seed=1, workers=0, progress=False)
    assert read_provenance(tmp_path / "ds.h5")["kind"] == "simulated-dataset"


def test_a_file_without_provenance_is_said_in_one_line(tmp_path):
    import h5py

    with h5py.File(tmp_path / "old.h5", "w") as f:
        f.attrs["schema_version"] = 2
    with pytest.raises(ProvenanceError, match="holds no provenance"):
        read_provenance(tmp_path / "old.h5")
    res = CliRunner().invoke(main, ["info", "--provenance", str(tmp_path / "old.h5")])
    assert res.exit_code == 1 and res.output.startswith("Error: ") and res.output.count("\n") == 1
