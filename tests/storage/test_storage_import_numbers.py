"""Import states what it did to the numbers (issue 52 items 2 and 3): readings that are not whole counts are refused
with the hint unless the user says how to map them; CSV dialects are read or refused by name; --columns and
--time-column pick columns, and a time column puts the readings onto the --rate grid with the jitter stated and the
gaps named; --variable picks a series of NPZ/MAT/NWB and the one read is always named; labels carry units
({speed_mm_min}, {force_N}, ...) converted on import, implausible ones warned with what the windows become. The
section "Other people's files" of docs/my-sensor.md runs as written."""

from __future__ import annotations

import subprocess
from datetime import UTC
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import open_session

from ..guides import guide_env, run_by, script

SECTION_TEST = "tests/storage/test_storage_import_numbers.py::test_other_peoples_files_section"


def _rigctl(*args, cwd: Path):
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return r.exit_code, r.stdout + r.stderr


def _counts(path: Path) -> list[np.ndarray]:
    with open_session(path) as s:
        return [s.trial(i).taxels for i in s.completed_ids()]


def test_fractional_readings_are_refused_unless_mapped(tmp_path, monkeypatch):
    """A CSV of volts became {2, 3} and data in 0..1 became {0, 1} (exit 0): refused now, with the hint."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    volts = 1.73 + 1.42 * rng.random((500, 9))
    np.savetxt("volts.csv", volts, delimiter=",", fmt="%.4f")
    np.savetxt("unit.csv", rng.random((500, 9)), delimiter=",", fmt="%.5f")
    for name in ("volts.csv", "unit.csv"):
        rc, out = _rigctl("import", name, "--rate", 1000, "--texture", "A", "--out", "x.h5", cwd=tmp_path)
        assert rc == 1 and "not whole ADC counts" in out and "--volts-ref" in out and "--scale" in out, out
        assert "Traceback" not in out and not Path("x.h5").exists()
    rc, out = _rigctl("import", "volts.csv", "--rate", 1000, "--texture", "A", "--volts-ref", 5, "--out", "v.h5",
                      cwd=tmp_path)
    assert rc == 0, out
    np.testing.assert_array_equal(_counts(Path("v.h5"))[0], np.rint(np.loadtxt("volts.csv", delimiter=",") / (5 / 1024)))
    rc, out = _rigctl("import", "unit.csv", "--rate", 1000, "--texture", "A", "--scale", 1000, "--out", "u.h5",
                      cwd=tmp_path)
    assert rc == 0, out
    got = _counts(Path("u.h5"))[0]
    np.testing.assert_array_equal(got, np.rint(np.loadtxt("unit.csv", delimiter=",") * 1000))
    assert len(np.unique(got)) > 100  # not {0, 1}
    with h5py.File("u.h5", "r") as f:
        assert '"scale": 1000.0' in f.attrs["import_steps"]


def test_csv_dialects_are_read_or_refused_by_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # (falling: a whole-number column rising at every row is a counter, never a taxel: issue 77 item 2)
    rows = np.arange(40, dtype=float)[::-1].reshape(20, 2) + 100
    Path("trailing.csv").write_text("a,b,\n" + "".join(f"{x:g},{y:g},\n" for x, y in rows))
    Path("comma.csv").write_text("a;b\n" + "".join(f"{x:g},5;{y:g},25\n" for x, y in rows))
    Path("ragged.csv").write_text("1,2\n3,4,5\n6,7\n")
    rc, out = _rigctl("import", "trailing.csv", "--rate", 100, "--texture", "A", "--out", "t.h5", cwd=tmp_path)
    assert rc == 0 and "trailing delimiter dropped" in out, out
    np.testing.assert_array_equal(_counts(Path("t.h5"))[0], rows)
    rc, out = _rigctl("import", "comma.csv", "--rate", 100, "--texture", "A", "--scale", 4, "--out", "c.h5",
                      cwd=tmp_path)
    assert rc == 0 and "';'-separated, decimal comma" in out, out
    np.testing.assert_array_equal(_counts(Path("c.h5"))[0], np.rint((rows + [0.5, 0.25]) * 4))
    rc, out = _rigctl("import", "ragged.csv", "--rate", 100, "--texture", "A", "--out", "r.h5", cwd=tmp_path)
    assert rc == 1 and "ragged rows" in out and "Traceback" not in out, out


def test_columns_and_a_time_column_resampled_onto_the_rate_grid(tmp_path, monkeypatch):
    """44 columns imported as 44 taxels and the time column dropped (taken as evenly spaced): now --columns picks
    the channels and the times put the readings on the grid, the jitter stated and the gap named."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(1)
    n = 2000
    t = np.arange(n) / 1000 + rng.normal(0, 0.0002, n)
    t[1200:] += 0.020  # 20 samples lost at 1.2 s
    signal = np.rint(500 + 100 * np.sin(2 * np.pi * t * 7))[:, None] + np.arange(4)[None, :]
    extra = rng.normal(0, 1, (n, 39))
    head = ",".join(["stamp"] + [f"tx{i}" for i in range(4)] + [f"aux{i}" for i in range(39)])
    np.savetxt("wide.csv", np.column_stack([t, signal, extra]), delimiter=",", fmt="%.6f", header=head,
               comments="")
    rc, out = _rigctl("import", "wide.csv", "--rate", 1000, "--texture", "A", "--out", "w.h5", cwd=tmp_path)
    assert rc == 1 and "not whole ADC counts" in out, out  # 44 columns: the aux ones are not counts
    args = ("import", "wide.csv", "--rate", 1000, "--texture", "A", "--columns", "tx0,tx1,tx2,tx3", "--time-column",
            "stamp", "--time-unit", "s", "--out", "w.h5")
    rc, out = _rigctl(*args, cwd=tmp_path)  # a gap inside the trial: interpolating across it is asked for by name
    assert rc == 1 and "1 gap(s) in the time stamps" in out and "--close-gaps" in out, out
    assert "Traceback" not in out and not Path("w.h5").exists(), out
    rc, out = _rigctl(*args, "--close-gaps", cwd=tmp_path)
    assert rc == 0, out
    assert "ledger: wide.csv: 1 gap(s) in the time column interpolated across (--close-gaps)" in out, out
    assert "time column resampled onto the 1000 Hz grid" in out and "jitter sd" in out, out
    assert "1 gap(s)" in out and "at 1.19" in out, out
    got = _counts(Path("w.h5"))[0]
    assert got.shape == (int(np.floor((t[-1] - t[0]) * 1000)) + 1, 4)
    grid = t[0] + np.arange(got.shape[0]) / 1000
    np.testing.assert_array_equal(got[:, 0], np.rint(np.interp(grid, t, signal[:, 0])))
    with h5py.File("w.h5", "r") as f:
        steps = f.attrs["import_steps"]
        assert '"time_grid"' in steps and '"gaps"' in steps


def _nwb(path: Path, series: dict[str, tuple[np.ndarray, float]]) -> Path:
    from datetime import datetime

    from pynwb import NWBHDF5IO, NWBFile, TimeSeries

    with NWBHDF5IO(str(path), "w") as io:
        nwb = NWBFile(session_description="x", identifier="x", session_start_time=datetime.now(UTC))
        for name, (data, rate) in series.items():
            nwb.add_acquisition(TimeSeries(name=name, data=data, unit="counts", rate=rate))
        io.write(nwb)
    return path


def test_series_chosen_by_variable_and_always_named(tmp_path, monkeypatch):
    """An NWB file with several series gave the longest (an accelerometer) silently and then failed naming none."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(2)
    taxels = rng.integers(100, 900, (1000, 9)).astype(float)
    _nwb(tmp_path / "lab.nwb", {"pressure": (taxels, 1000.0), "accel": (rng.normal(0, 1, (4000, 3)), 4000.0)})
    rc, out = _rigctl("import", "lab.nwb", "--texture", "A", "--out", "n.h5", cwd=tmp_path)
    assert rc == 1 and "2 TimeSeries" in out and "accel (4000, 3)" in out and "--variable" in out, out
    rc, out = _rigctl("import", "lab.nwb", "--texture", "A", "--variable", "pressure", "--out", "n.h5", cwd=tmp_path)
    assert rc == 0 and "read 'pressure' of accel, pressure" in out, out
    np.testing.assert_array_equal(_counts(Path("n.h5"))[0], taxels)
    np.savez("two.npz", taxels=taxels, temperature=rng.integers(20, 30, (1000, 1)))
    rc, out = _rigctl("import", "two.npz", "--rate", 1000, "--texture", "A", "--out", "z.h5", cwd=tmp_path)
    assert rc == 0 and "read 'taxels' of taxels, temperature" in out, out
    rc, out = _rigctl("import", "two.npz", "--rate", 1000, "--texture", "A", "--variable", "temperature",
                      "--out", "z2.h5", cwd=tmp_path)
    assert rc == 0 and "read 'temperature'" in out and "1 channels" in out, out


def test_label_units_converted_and_implausible_ones_warned(tmp_path, monkeypatch):
    """Feed rates in mm/min (1200-6000) imported as mm/s without a word; now {speed_mm_min} converts them and
    speeds read in the wrong unit are warned with the windows they give."""
    monkeypatch.chdir(tmp_path)
    # (not one value throughout: samples identical to the one before are held readings, named: issue 77 item 4)
    x = 500 + np.random.default_rng(0).integers(-3, 4, (300, 9))
    for feed in (1200, 6000):
        np.savetxt(f"cnc__A__F{feed}__P2.5.csv", x, delimiter=",", fmt="%d")
    rc, out = _rigctl("import", "cnc__A__F1200__P2.5.csv", "cnc__A__F6000__P2.5.csv", "--rate", 1000,
                      "--label-pattern", "cnc__{texture}__F{speed_mm_min}__P{force_N}.csv", "--out", "u.h5",
                      cwd=tmp_path)
    assert rc == 0 and "warning" not in out, out
    with open_session("u.h5") as s:
        plan = s.plan
        assert sorted(plan["speed_mm_s"]) == [20.0, 100.0]
        assert plan["force_g"][0] == pytest.approx(2.5 * 1000 / 9.80665)
        assert s.trial_attrs(0)["speed_as_labelled"] in ("1200 mm/min", "6000 mm/min")
    rc, out = _rigctl("import", "cnc__A__F1200__P2.5.csv", "cnc__A__F6000__P2.5.csv", "--rate", 1000,
                      "--label-pattern", "cnc__{texture}__F{speed_mm_s}__P{force_g}.csv", "--out", "w.h5",
                      cwd=tmp_path)
    assert rc == 0, out
    assert "speeds 1200-6000 mm/s are outside 1-1000 mm/s" in out and "{speed_mm_min}" in out, out
    assert "a speed-scaled window is 2.00 ms" in out, out
    assert "forces 2.5-2.5 g are outside 10-10000 g" in out and "{force_N}" in out, out


def test_other_peoples_files_section(tmp_path):
    """docs/my-sensor.md "Other people's files": its blocks run as written, each import one command."""
    blocks = run_by(SECTION_TEST)
    assert [b.lang for b in blocks] == ["python", "sh"]
    work = tmp_path / "work"
    work.mkdir()
    path = tmp_path / "section.sh"
    path.write_text(script(blocks, work))
    r = subprocess.run(["bash", str(path)], cwd=work, env=guide_env(work), capture_output=True, text=True,
                       timeout=600)
    out = r.stdout + r.stderr
    assert r.returncode == 0 and "Traceback" not in out, out
    assert "time column resampled onto the 1000 Hz grid" in out and "1 gap(s)" in out, out
    assert "logger__felt.csv: 1 gap(s) in the time stamps" in out and "refused" in out, out
    assert "read 'pressure' of accelerometer, pressure" in out, out
    with open_session(work / "cnc.h5") as s:
        assert sorted(s.plan["speed_mm_s"]) == [20.0, 60.0, 100.0]
    volts = _counts(work / "volts.h5")[0]
    logger = _counts(work / "logger.h5")[0]
    assert volts.shape == (3000, 9) and logger.shape[1] == 9 and abs(float(np.median(volts)) - 500) < 10
