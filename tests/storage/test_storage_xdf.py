"""XDF import (issue 27 item 1's inlet): a file written by rigctl.storage.xdf.write_xdf (the XDF
1.0 chunks LabRecorder writes; pyxdf reads it back) imports with `rigctl import` as a session: another lab's
16-channel device beside a marker stream as one labelled recording, its stream picked by name; a file pyxdf cannot
read is one line. (A rigctl run recorded through LSL and imported back: tests/acquisition/test_acq_lsl.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import open_session
from rigctl.storage.xdf import XdfStream, stream_info_xml, write_xdf

pytest.importorskip("pyxdf")


def test_another_labs_device_imports_as_a_session(tmp_path):
    rng = np.random.default_rng(4)
    n = 1500
    taxels = rng.integers(0, 1024, (n, 16))
    stamps = 1000.0 + np.arange(n) / 500.0
    pads = rng.integers(0, 1024, (n // 5, 2))
    write_xdf(tmp_path / "rec.xdf", [
        XdfStream(stream_info_xml("pads", "Force", 2, 100.0, "float32", "pads-1"), "float32", pads,
                  1000.0 + np.arange(n // 5) / 100.0),
        XdfStream(stream_info_xml("fingertip", "Tactile", 16, 500.0, "int16", "tip-1", [f"t{k}" for k in range(16)]),
                  "int16", taxels, stamps, clock_offsets=[(1000.0, 0.25), (1003.0, 0.25)]),
        XdfStream(stream_info_xml("Markers", "Markers", 1, 0.0, "string", "mk-1"), "string", [["go"], ["stop"]],
                  [1000.5, 1002.5]),
    ])
    res = CliRunner().invoke(main, ["import", str(tmp_path / "rec.xdf"), "--out", str(tmp_path / "s.h5"),
                                    "--texture", "Canvas", "--quiet"])
    assert res.exit_code == 0, res.output
    with open_session(tmp_path / "s.h5") as s:
        assert s.layout.n_channels == 16 and s.layout.sample_rate_hz == 500.0
        (tid,) = s.completed_ids()
        assert str(s.plan["texture"][0]) == "Canvas"
        assert np.array_equal(s.trial(tid).taxels, taxels)
    # the stream chosen by name (the mapping's variable): the pads (2 channels at 100 Hz)
    (tmp_path / "m.toml").write_text('variable = "pads"\n')
    res = CliRunner().invoke(main, ["import", str(tmp_path / "rec.xdf"), "--out", str(tmp_path / "p.h5"),
                                    "--mapping", str(tmp_path / "m.toml"), "--texture", "x", "--quiet"])
    assert res.exit_code == 0, res.output
    with open_session(tmp_path / "p.h5") as s:
        assert s.layout.n_channels == 2 and s.layout.sample_rate_hz == 100.0
        assert np.array_equal(s.trial(s.completed_ids()[0]).taxels, pads)
    (tmp_path / "m.toml").write_text('variable = "nope"\n')
    res = CliRunner().invoke(main, ["import", str(tmp_path / "rec.xdf"), "--out", str(tmp_path / "n.h5"),
                                    "--mapping", str(tmp_path / "m.toml"), "--texture", "x", "--quiet"])
    assert res.exit_code != 0 and "no numeric stream named 'nope'" in res.output and "fingertip" in res.output


def test_a_broken_file_is_one_line(tmp_path):
    (tmp_path / "bad.xdf").write_bytes(b"XDF:\x01\x05garbage")
    res = CliRunner().invoke(main, ["import", str(tmp_path / "bad.xdf"), "--out", str(tmp_path / "s.h5"),
                                    "--texture", "A", "--quiet"])
    assert res.exit_code in (1, 2) and res.output.startswith("Error: ") and res.output.count("\n") == 1, res.output
    assert not (tmp_path / "s.h5").exists()
