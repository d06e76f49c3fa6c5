"""End to end from files: 9-taxel recordings at 100 Hz imported from CSV once kept at 100 Hz and once resampled to
1 kHz (`rigctl import --resample`), then encoded (`rigctl encode`): the rate stored in each session is the rate the
encoder uses, so both sessions give the same spike timing (a 100 Hz session is never encoded as if it were 1 kHz)."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.encoding.spikes import SpikeTrains
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import open_session

RATE = 100.0


def _write_csvs(folder):
    """Two textures x 2 repeats, 3 s each: taxel i presses for 0.5 s starting at 0.5 + 0.2 i s (a staircase)."""
    t = np.arange(int(3 * RATE)) / RATE
    for tex in ("felt", "HB3"):
        for rep in range(2):
            x = np.full((t.size, 9), 300.0)
            for i in range(9):
                on = (t >= 0.5 + 0.2 * i) & (t < 1.0 + 0.2 * i)
                x[on, i] = 800.0 if tex == "felt" else 600.0
            np.savetxt(folder / f"{tex}__V40__{rep}.csv", x, fmt="%d", delimiter=",",
                       header=",".join(f"t{i}" for i in range(9)), comments="")


def _run(*args):
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r


def test_kept_and_resampled_imports_encode_to_the_same_timing(tmp_path):
    _write_csvs(tmp_path)
    files = sorted(tmp_path.glob("*.csv"))
    pattern = ["--label-pattern", "{texture}__V{speed_mm_s}__{rep}.csv", "--rate", "100", "--layout", "3x3x1"]
    kept, up = tmp_path / "kept.h5", tmp_path / "up.h5"
    _run("import", *files, *pattern, "--out", kept)
    _run("import", *files, *pattern, "--resample", "1000", "--out", up)
    with open_session(kept) as s:
        assert s.layout.sample_rate_hz == 100.0 and s.trial(0).taxels.shape == (300, 9)
    with open_session(up) as s:
        assert s.layout.sample_rate_hz == 1000.0 and s.trial(0).taxels.shape == (3000, 9)
    firsts = {}
    for name, path in (("kept", kept), ("up", up)):
        out = tmp_path / f"{name}.enc.h5"
        _run("encode", path, "--out", out, "--variant", "original", "--quiet")
        with open_encoded(out) as e:
            assert e.layout.n_channels == 9
            assert e.attrs["input_rate_hz"] == (100.0 if name == "kept" else 1000.0)
            assert e.attrs["resampled"] == (name == "kept")
            sa = SpikeTrains(*e.spikes("original"))
            assert sa.n_trains == 18
            # the RA neuron of taxel i (train 9 + i) first fires when its press starts (0.5 + 0.2 i s), in seconds,
            # whatever the file's rate (SA fires at rest too: the resampled steps overshoot the rest level, and the
            # per-taxel normalisation spans the overshoot)
            firsts[name] = np.array([sa.train(0, 9 + i)[0] for i in range(9)])
            assert e.features("original").shape[1] == 18 * 30  # 3 s trials -> 30 windows of 100 ms per train
    np.testing.assert_allclose(firsts["kept"], 0.5 + 0.2 * np.arange(9), atol=0.03)
    np.testing.assert_allclose(firsts["kept"], firsts["up"], atol=0.02)
