"""Clipping is asked for by name or refused (issue 77 item 1): ``--resample`` made a 10-bit range refusal exit 0
with 92 % of another lab's values pinned to 0/1023, the count only in an attribute nothing printed; volts above
``--volts-ref`` and 12-bit values at the default 10 bits were pinned the same way. Now each is refused in one line
naming how many values, and with ``--clip`` pinned, counted on the terminal and in the import steps."""

from __future__ import annotations

import json

import h5py
import numpy as np
from click.testing import CliRunner

from rigctl.cli import main


def _run(*args):
    r = CliRunner().invoke(main, ["import", *map(str, args)])
    return r.exit_code, r.output


def test_resampled_values_outside_the_range_are_refused_unless_clip(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.integers(0, 4096, (400, 4))  # a 12-bit board's counts, imported at the default 10 bits
    p = tmp_path / "lab__A.csv"
    np.savetxt(p, x, fmt="%d", delimiter=",")
    out = tmp_path / "s.h5"
    rc, text = _run(p, "--rate", 500, "--resample", 1000, "--texture", "A", "--out", out)
    n_out = int((x > 1023).sum())
    assert rc == 1 and "outside the 10-bit ADC range 0..1023" in text and "--clip" in text, text
    assert "Traceback" not in text and not out.exists()
    rc, text = _run(p, "--rate", 500, "--resample", 1000, "--texture", "A", "--clip", "--out", out)
    assert rc == 0, text
    line = [ln for ln in text.splitlines() if "clipped to the 10-bit range" in ln]
    assert len(line) == 1 and "(--clip)" in line[0], text
    clipped = int(line[0].split("lab__A.csv: ", 1)[1].split(" of ")[0])
    assert clipped >= n_out * 2 * 0.9  # the resampled file holds twice the samples, most of the 12-bit ones out
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["import_steps"])["value_scale"]["clipped_values"] == clipped


def test_volts_above_the_reference_are_refused_unless_clip(tmp_path):
    volts = np.full((300, 2), 2.0)
    volts[10:20, 1] = 5.5  # above a 5 V reference
    p = tmp_path / "v__A.npy"
    np.save(p, volts)
    rc, text = _run(p, "--rate", 1000, "--volts-ref", 5, "--texture", "A", "--out", tmp_path / "v.h5")
    assert rc == 1 and "10 of 600 values are outside" in text and "--volts-ref 5 V" in text, text
    rc, text = _run(p, "--rate", 1000, "--volts-ref", 5, "--texture", "A", "--clip", "--out", tmp_path / "v.h5")
    assert rc == 0 and "10 of 600 values clipped" in text, text


def test_one_ledger_printed_by_import_and_shown_by_info(tmp_path):
    """Every value-changing step in one ledger (issue 77 item 1): the import prints it, --json holds it, rigctl info
    shows it for the session (text and --json); a file imported as it is has an empty one."""
    rng = np.random.default_rng(3)
    x = rng.integers(0, 4096, (400, 4))
    p = tmp_path / "lab__A.csv"
    np.savetxt(p, x, fmt="%d", delimiter=",")
    out = tmp_path / "s.h5"
    rc, text = _run(p, "--rate", 500, "--resample", 1000, "--texture", "A", "--clip", "--out", out)
    assert rc == 0, text
    ledger = [ln for ln in text.splitlines() if ln.startswith("ledger: ")]
    assert ledger[0].startswith("ledger: resampled 500 -> 1000 Hz") and "value(s) clipped to 0..1023" in ledger[1], text
    rc, text = _run(p, "--rate", 500, "--resample", 1000, "--texture", "A", "--clip", "--json", "--overwrite",
                    "--out", out)
    doc = json.loads(text[text.index("{"):text.rindex("}") + 1])
    assert [e["step"] for e in doc["ledger"]] == ["resample", "clip"], doc["ledger"]
    info = CliRunner().invoke(main, ["info", str(out)])
    assert "ledger: resampled 500 -> 1000 Hz" in info.output and "clipped to 0..1023 (--clip)" in info.output, \
        info.output
    info = CliRunner().invoke(main, ["info", str(out), "--json"])
    assert [e["step"] for e in json.loads(info.output)["ledger"]] == ["resample", "clip"]
    np.savetxt(tmp_path / "plain__A.csv", rng.integers(100, 900, (400, 4)), fmt="%d", delimiter=",")
    rc, text = _run(tmp_path / "plain__A.csv", "--rate", 500, "--texture", "A", "--out", tmp_path / "p.h5")
    assert rc == 0 and "ledger:" not in text, text
    info = CliRunner().invoke(main, ["info", str(tmp_path / "p.h5"), "--json"])
    assert json.loads(info.output)["ledger"] == []
