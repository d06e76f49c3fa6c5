"""Time columns by declaration (issue 77 item 2, :mod:`rigctl.storage.time_column`): a ``time_us`` column read as
seconds took 24.3 GB (the OOM killer acted; under a cap "internal error: MemoryError 22.3 GiB") and a ``millis`` or
``Time (ms)`` column became taxel 19 (exit 0). Now the unit is declared or known by name, the implied rate is checked
against ``--rate`` before any allocation, the grid is bounded by the input's rows, a counter is never a taxel, and
repeated stamps are refused or kept-first, counted. The real command, in processes of their own where memory is
capped."""

from __future__ import annotations

import json
import resource
import subprocess
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigctl.storage.session import open_session
from rigctl.storage.time_column import explicit_unit, unit_of_name

RIGCTL: list[str] = []  # this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)
#: the memory cap of the capped runs, bytes (the issue's: 3 GB of address space)
CAP_BYTES = 3 * 10**9


def _csv(path: Path, head: list[str], rows: np.ndarray) -> Path:
    lines = [",".join(head)] + [",".join(f"{v:.0f}" if float(v).is_integer() else f"{v:.6f}" for v in r)
                                for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _taxels(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(300, 700, (n, 4)).astype(float)


def _run(args: list, cwd: Path, cap: bool = False) -> tuple[int, str, float]:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (CAP_BYTES, CAP_BYTES))

    t0 = time.monotonic()
    r = subprocess.run([*RIGCTL, *map(str, args)], capture_output=True, text=True, timeout=300, cwd=cwd,
                       preexec_fn=limit if cap else None)
    return r.returncode, r.stdout + r.stderr, time.monotonic() - t0


def _one_error(out: str) -> str:
    assert "Traceback" not in out and "internal error" not in out and "MemoryError" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, out
    return errors[0]


@pytest.mark.parametrize("name, unit", [
    ("time", "s"), ("t", "s"), ("timestamp", "s"), ("seconds", "s"), ("time_s", "s"), ("Time (s)", "s"),
    ("time_ms", "ms"), ("millis", "ms"), ("Time (ms)", "ms"), ("timestamp_ms", "ms"), ("t [ms]", "ms"),
    ("time_us", "us"), ("micros", "us"), ("Time (µs)", "us"), ("time_ns", "ns"), ("nanos", "ns"),
    ("stamp", None), ("tx0", None), ("temperature", None), ("ms5", None), ("frame", None)])
def test_the_names_rigctl_knows(name, unit):
    assert unit_of_name(name) == unit
    # a plain time/timestamp/t is seconds unless --time-unit says otherwise (no conflict); a spelled unit is its own
    assert explicit_unit(name) == (None if name in ("time", "t", "timestamp") else unit)


def test_a_plain_timestamp_in_ms_takes_time_unit(tmp_path):
    """A lab's ``timestamp`` column in ms (FabricSlide's spelling): read as seconds it disagrees with --rate (refused,
    asking for the unit); --time-unit ms reads it, no conflict with the name."""
    n = 600
    _csv(tmp_path / "lab__A.csv", ["timestamp", "c0", "c1", "c2", "c3"],
         np.column_stack([4000 + 2.0 * np.arange(n), _taxels(n)]))
    rc, out, _ = _run(["import", "lab__A.csv", "--rate", 500, "--texture", "A", "--out", "t.h5"], tmp_path)
    assert rc == 2 and "imply 0.5 Hz (read as s) but --rate is 500 Hz" in _one_error(out), out
    rc, out, _ = _run(["import", "lab__A.csv", "--rate", 500, "--texture", "A", "--time-unit", "ms", "--out", "t.h5"],
                      tmp_path)
    assert rc == 0 and "stamps in ms" in out, out


def test_a_time_us_column_read_as_seconds_is_refused_at_once_under_a_3_gb_cap(tmp_path):
    """3 s at 1 kHz stamped in microseconds. Declared seconds (a column whose name says nothing): the stamps imply
    0.001 Hz against --rate 1000: exit 2 in one line, under a 3 GB address-space cap, well within 60 s. Named
    ``time_us``: read as microseconds and imported (3000 samples), under the same cap; ``--time-unit s`` against
    that name: refused, naming both."""
    n = 3000
    stamps = np.arange(n) * 1000.0  # us
    _csv(tmp_path / "stamp__A.csv", ["stamp", "c0", "c1", "c2", "c3"], np.column_stack([stamps, _taxels(n)]))
    rc, out, took = _run(["import", "stamp__A.csv", "--rate", 1000, "--texture", "A", "--time-column", "stamp",
                          "--time-unit", "s", "--out", "a.h5"], tmp_path, cap=True)
    line = _one_error(out)
    assert rc == 2 and took < 60, (rc, took, out)
    assert "imply 0.001 Hz" in line and "--rate is 1000 Hz" in line and "--time-unit" in line, line
    assert not (tmp_path / "a.h5").exists()
    # without the unit: asked for, never guessed
    rc, out, _ = _run(["import", "stamp__A.csv", "--rate", 1000, "--texture", "A", "--time-column", "stamp",
                       "--out", "a.h5"], tmp_path)
    assert rc == 2 and "give its unit with --time-unit" in _one_error(out), out
    _csv(tmp_path / "us__A.csv", ["time_us", "c0", "c1", "c2", "c3"], np.column_stack([stamps, _taxels(n)]))
    rc, out, took = _run(["import", "us__A.csv", "--rate", 1000, "--texture", "A", "--out", "b.h5"], tmp_path,
                         cap=True)
    assert rc == 0 and "time column resampled onto the 1000 Hz grid (--rate, stamps in us" in out, out
    with open_session(tmp_path / "b.h5") as s:
        (tid,) = s.completed_ids()
        assert s.trial(tid).taxels.shape == (n, 4)
    rc, out, _ = _run(["import", "us__A.csv", "--rate", 1000, "--texture", "A", "--time-unit", "s",
                       "--out", "c.h5"], tmp_path)
    assert rc == 2 and "says us by its name, --time-unit says s" in _one_error(out), out


def test_a_grid_longer_than_the_input_allows_is_refused_before_allocation(tmp_path):
    """A 1e6 s hole in a 2000-row file read at 1 kHz would be a 1e9-sample grid: refused, naming the gap."""
    n = 2000
    t = np.arange(n) / 1000.0
    t[1000:] += 1e6
    _csv(tmp_path / "hole__A.csv", ["time", "c0", "c1", "c2", "c3"], np.column_stack([t, _taxels(n)]))
    rc, out, took = _run(["import", "hole__A.csv", "--rate", 1000, "--texture", "A", "--out", "h.h5"], tmp_path,
                         cap=True)
    line = _one_error(out)
    assert rc == 2 and "at most 4 per row" in line and "the longest gap 1e+06 s" in line, line


@pytest.mark.parametrize("head", ["millis", "Time (ms)"])
def test_a_millis_column_is_the_time_column_not_taxel_19(tmp_path, head):
    n = 500
    ms = 1000 + np.arange(n, dtype=float)  # a board's millis() since power-up
    _csv(tmp_path / "board__A.csv", [head, "c0", "c1", "c2", "c3"], np.column_stack([ms, _taxels(n)]))
    rc, out, _ = _run(["import", "board__A.csv", "--rate", 1000, "--texture", "A", "--json", "--out", "m.h5"],
                      tmp_path)
    assert rc == 0, out
    summary = json.loads(out[out.index("{"):out.rindex("}") + 1])
    assert summary["n_channels"] == 4, summary
    with h5py.File(tmp_path / "m.h5", "r") as f:
        read = json.loads(f.attrs["import_steps"])["read"][0]
    assert read["time_column"] == {"column": head, "unit": "ms", "unit_from": "its name"}, read


def test_a_rising_counter_is_never_a_taxel_unless_named(tmp_path):
    n = 400
    frame = np.arange(n, dtype=float) + 17
    rows = np.column_stack([_taxels(n)[:, :2], frame, _taxels(n, 1)[:, :2]])
    _csv(tmp_path / "ctr__A.csv", ["c0", "c1", "frame", "c2", "c3"], rows)
    rc, out, _ = _run(["import", "ctr__A.csv", "--rate", 1000, "--texture", "A", "--out", "f.h5"], tmp_path)
    line = _one_error(out)
    assert rc == 2 and "column 'frame' rises at every row (17 to 416)" in line and "--columns" in line, line
    # named in --columns: the user says it is a channel
    rc, out, _ = _run(["import", "ctr__A.csv", "--rate", 1000, "--texture", "A", "--columns", "c0,c1,frame,c2,c3",
                       "--bits", 12, "--out", "f.h5"], tmp_path)
    assert rc == 0, out
    # as the time column (ms), declared
    rc, out, _ = _run(["import", "ctr__A.csv", "--rate", 1000, "--texture", "A", "--time-column", "frame",
                       "--time-unit", "ms", "--out", "g.h5"], tmp_path)
    assert rc == 0 and "time column resampled" in out, out


def test_repeated_stamps_are_refused_or_the_first_kept_and_counted(tmp_path):
    n = 1000
    t = np.arange(n) / 1000.0
    t[200:] -= 0.001  # row 200 repeats row 199's stamp; the rows after keep their spacing
    t[600:] -= 0.001  # and again at 600
    x = _taxels(n)
    _csv(tmp_path / "rep__A.csv", ["time", "c0", "c1", "c2", "c3"], np.column_stack([t, x]))
    rc, out, _ = _run(["import", "rep__A.csv", "--rate", 1000, "--texture", "A", "--out", "r.h5"], tmp_path)
    line = _one_error(out)
    assert rc == 2 and "2 repeated time stamp(s), the first at row 200" in line and "keep-first" in line, line
    rc, out, _ = _run(["import", "rep__A.csv", "--rate", 1000, "--texture", "A", "--repeated-stamps", "keep-first",
                       "--out", "r.h5"], tmp_path)
    assert rc == 0 and "2 row(s) of repeated stamps dropped, the first of each kept" in out, out
    with h5py.File(tmp_path / "r.h5", "r") as f:
        steps = json.loads(f.attrs["import_steps"])
    grid = steps["read"][0]["time_grid"]
    assert grid["repeated_stamps"] == {"rows_dropped": 2, "kept": "the first of each"}, grid
    assert grid["samples_in"] == n - 2
