"""``rigctl calibrate loadcell``: the command the fault advice sends an operator to (a zero that moved, a wrong
scale: docs/safety.md) exists and does what the GUI's calibration tab does, on the in-process rig (simulated time);
bad input is one line, exit 2, and the rig config untouched."""

from __future__ import annotations

import hashlib
import json
import re

import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.core.drum import FAULT_WORDS


def test_a_load_cell_is_calibrated_and_stored(tmp_path):
    config = tmp_path / "rig.json"
    r = CliRunner().invoke(main, ["calibrate", "loadcell", "--mass-g", "200", "--inprocess", "--config", str(config)])
    assert r.exit_code == 0, r.output
    m = re.search(r"calibrated with 200 g: ([\d.]+) counts/g, the mass reads ([\d.]+) g .* stiffness (\d+) g/mm",
                  r.stdout)
    assert m is not None, r.stdout
    counts_per_g, reads_g, stiffness = float(m.group(1)), float(m.group(2)), float(m.group(3))
    assert counts_per_g == pytest.approx(420.0, rel=0.05)  # the simulated cell's scale (MechanicsConfig)
    assert reads_g == pytest.approx(200.0, abs=5.0)
    assert stiffness > 0
    stored = json.loads(config.read_text())
    assert stored["loadcell"]["mass_g"] == 200.0
    assert stored["loadcell"]["counts_per_g"] == pytest.approx(counts_per_g, rel=1e-3)


@pytest.mark.parametrize("args,says", [
    (["--mass-g", "0", "--inprocess"], "--mass-g"),
    (["--mass-g", "nan", "--inprocess"], "--mass-g"),
    (["--inprocess"], "--mass-g"),
    (["--mass-g", "200", "--drum-port", "/dev/null"], "--taxel-port"),
    (["--mass-g", "200", "--drum-port", "/dev/null", "--taxel-port", "/dev/null"], "terminal"),
    (["--mass-g", "200", "--sim", "--inprocess"], "choose one"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, says):
    config = tmp_path / "rig.json"
    config.write_text("{}")
    before = hashlib.sha256(config.read_bytes()).hexdigest()
    r = CliRunner().invoke(main, ["calibrate", "loadcell", *args, "--config", str(config)])
    assert r.exit_code == 2 and says in r.stderr and "Traceback" not in r.output, r.output
    assert hashlib.sha256(config.read_bytes()).hexdigest() == before


def test_a_config_that_is_not_a_rig_config_is_refused_untouched(tmp_path):
    config = tmp_path / "rig.json"
    config.write_text("not json at all\n")
    r = CliRunner().invoke(main, ["calibrate", "loadcell", "--mass-g", "200", "--inprocess", "--config", str(config)])
    assert r.exit_code == 2 and "--config" in r.stderr, r.output
    assert config.read_text() == "not json at all\n"


def test_every_command_the_advice_names_exists():
    """The fault advice names `rigctl ...` commands for the operator to run: each one is a command of this rigctl
    (the advice said `rigctl calibrate` before the command existed)."""
    from rigctl.acquisition.safety import CAUSES

    texts = [w.advice for w in FAULT_WORDS.values()] + [remedy for _, remedy in CAUSES.values()]
    named = {m for t in texts for m in re.findall(r"rigctl ([a-z][a-z-]*(?: [a-z][a-z-]*)?)", t)}
    assert "calibrate loadcell" in named, named
    for words in sorted(named):
        first, *rest = words.split()
        r = CliRunner().invoke(main, [first, "--help"])
        assert r.exit_code == 0, (words, r.output)
        if "Commands:" in r.output:  # a group: the word after it names one of its commands
            assert rest and CliRunner().invoke(main, [first, rest[0], "--help"]).exit_code == 0, words
