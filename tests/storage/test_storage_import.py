"""``rigctl import``: generated recordings of a 9-taxel sensor at 100 Hz in every format, labelled from file names,
resampled or kept, segmented; the session stores the layout and rate and holds the source samples exactly."""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.importers import RecordingImportError, labels_from_name, parse_segment, read_recording_file, segment
from rigctl.storage.session import open_session

RATE = 100.0
PATTERN = "{texture}__V{speed_mm_s}__{rep}"
CONDITIONS = [("felt", 20.0, 0), ("felt", 40.0, 1), ("HB3", 20.0, 0), ("corduroy_fine", 40.0, 0)]


def recording(i: int, n: int = 300, channels: int = 9) -> np.ndarray:
    """(n, channels) integer counts 0-1023: a different sinusoid mix per file and channel."""
    t = np.arange(n) / RATE
    ch = np.arange(channels)
    x = 512 + 150 * np.sin(2 * np.pi * (1.0 + 0.5 * i) * t[:, None] + ch) + 40 * np.cos(2 * np.pi * 3.0 * t[:, None])
    return np.rint(x).astype(np.int64)


def write(path, data, fmt, header=True):
    import scipy.io

    if fmt == "csv":
        head = ",".join(f"taxel{c}" for c in range(data.shape[1])) if header else ""
        np.savetxt(path, data, fmt="%d", delimiter=",", header=head, comments="")
        if not header:  # savetxt writes an empty first line for an empty header
            path.write_text(path.read_text().lstrip("\n"))
    elif fmt == "npy":
        np.save(path, data)
    elif fmt == "mat":
        scipy.io.savemat(path, {"taxels": data.astype(np.float64), "note": "generated"})
    return path


def make_files(tmp_path, fmt, **kw):
    files, truth = [], {}
    for i, (tex, speed, rep) in enumerate(CONDITIONS):
        p = tmp_path / f"{tex}__V{speed:g}__{rep}.{fmt}"
        data = recording(i)
        write(p, data, fmt, **kw)
        files.append(p)
        truth[p.name] = data
    return files, truth


def run(*args):
    result = CliRunner().invoke(main, ["import", *map(str, args)])
    return result


@pytest.mark.parametrize("fmt", ["csv", "npy", "mat"])
def test_nine_channels_at_100_hz_kept(tmp_path, fmt):
    files, truth = make_files(tmp_path, fmt)
    out = tmp_path / "s.h5"
    r = run(*files, "--rate", 100, "--layout", "3x3x1", "--label-pattern", PATTERN, "--out", out)
    assert r.exit_code == 0, r.output
    assert "4 trials, 9 channels at 100 Hz" in r.output
    with open_session(out) as s:
        assert s.layout.n_channels == 9 and s.layout.sample_rate_hz == 100.0 and s.layout.shape_text == "3x3x1"
        assert list(s.plan["texture"]) == [c[0] for c in CONDITIONS]  # multi-character labels, whole
        assert sorted(s.textures.labels) == sorted({c[0] for c in CONDITIONS})
        np.testing.assert_array_equal(s.plan["speed_mm_s"], [c[1] for c in CONDITIONS])
        np.testing.assert_array_equal(s.plan["repeat"], [c[2] for c in CONDITIONS])
        assert all(math.isnan(f) for f in s.plan["force_g"])
        assert json.loads(s.attrs["resampling"]) == {"method": "none"}
        for row in s.plan:
            t = s.trial(int(row["trial_id"]))
            assert t.rate_hz == 100.0 and t.layout.n_channels == 9
            np.testing.assert_array_equal(t.taxels, truth[t.attrs["source_file"]])  # exactly the source
            assert row["duration_s"] == pytest.approx(3.0)


@pytest.mark.parametrize("fmt", ["csv", "npy", "mat"])
def test_nine_channels_resampled_to_1_khz(tmp_path, fmt):
    from scipy.signal import resample_poly

    files, truth = make_files(tmp_path, fmt)
    out = tmp_path / "s.h5"
    r = run(*files, "--rate", 100, "--channels", 9, "--label-pattern", PATTERN, "--resample", 1000, "--out", out)
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert s.layout.sample_rate_hz == 1000.0 and s.layout.n_channels == 9
        rs = json.loads(s.attrs["resampling"])
        assert (rs["from_hz"], rs["to_hz"], rs["up"], rs["down"]) == (100.0, 1000.0, 10, 1)
        assert "resample_poly" in rs["method"]
        for row in s.plan:
            t = s.trial(int(row["trial_id"]))
            src = truth[t.attrs["source_file"]]
            assert t.n_samples == 10 * src.shape[0] and t.rate_hz == 1000.0
            ref = np.clip(np.rint(resample_poly(src.astype(float), 10, 1, axis=0, padtype="line")), 0, 1023)
            np.testing.assert_array_equal(t.taxels, ref)
            # the samples on the original grid are the recorded ones (to rounding of the FIR)
            assert np.abs(t.taxels[::10].astype(int) - src).max() <= 2


def test_csv_without_header_and_v73_mat(tmp_path):
    import scipy.io

    data = recording(0)
    p = write(tmp_path / "plain.csv", data, "csv", header=False)
    assert not p.read_text().startswith("taxel")
    blocks, rate, meta = read_recording_file(p)
    assert rate is None and meta["format"] == "csv"
    np.testing.assert_array_equal(blocks[0], data)
    # a header with a time column: the time is not a channel; semicolons work too
    q = tmp_path / "timed.csv"
    q.write_text("time;a;b\n" + "\n".join(f"{i / 100};{r[0]};{r[1]}" for i, r in enumerate(data)) + "\n")
    blocks, _, _ = read_recording_file(q)
    np.testing.assert_array_equal(blocks[0], data[:, :2])
    # MATLAB v7.3 is HDF5 with a 512-byte MATLAB header; MATLAB writes arrays column-major (h5py sees (c, n))
    mat = tmp_path / "v73.mat"
    with h5py.File(mat, "w", userblock_size=512) as f:
        f.create_dataset("taxels", data=data.T.astype(np.float64))
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: " + datetime.now(UTC).strftime(
        "%a %b %d %H:%M:%S %Y").encode() + b" HDF5 schema 1.00 ."
    with open(mat, "r+b") as fh:
        fh.write(head.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02" + b"IM")
    with pytest.raises(NotImplementedError):
        scipy.io.loadmat(mat)
    blocks, _, _ = read_recording_file(mat, channels=9)
    np.testing.assert_array_equal(blocks[0], data)


def test_nwb_timeseries(tmp_path):
    from pynwb import NWBHDF5IO, NWBFile, TimeSeries

    data = recording(2)
    nwb = NWBFile(session_description="generated taxels", identifier="rigctl-test",
                  session_start_time=datetime(2026, 1, 1, tzinfo=UTC))
    nwb.add_acquisition(TimeSeries(name="taxels", data=data.astype(np.float64), unit="counts", rate=RATE))
    p = tmp_path / "silk__V30__0.nwb"
    with NWBHDF5IO(str(p), "w") as io:
        io.write(nwb)
    out = tmp_path / "s.h5"
    r = run(p, "--label-pattern", PATTERN, "--out", out)  # the rate comes from the TimeSeries
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert s.layout.sample_rate_hz == RATE and s.layout.n_channels == 9
        assert s.plan["texture"][0] == "silk" and s.plan["speed_mm_s"][0] == 30
        np.testing.assert_array_equal(s.trial(0).taxels, data)
        steps = json.loads(s.attrs["import_steps"])
        assert steps["read"][0]["timeseries"] == "taxels" and steps["read"][0]["format"] == "nwb"


def test_labels_from_file_name_pattern():
    got = labels_from_name("corduroy_fine__V12.5__3.csv", "{texture}__V{speed_mm_s}__{rep}.csv")
    assert got == {"texture": "corduroy_fine", "speed_mm_s": 12.5, "repeat": 3}
    got = labels_from_name("Linen_F150_V-20mmps_2.csv", "{texture}_F{force_g}_V{speed}mmps_{rep}.csv")
    assert got == {"texture": "Linen", "force_g": 150.0, "speed_mm_s": -20.0, "repeat": 2}
    got = labels_from_name("s07_wool_run2.npy", "s{subject}_{texture}_run{rep}")  # other fields kept; stem match
    assert got == {"subject": "07", "texture": "wool", "repeat": 2}
    with pytest.raises(RecordingImportError, match="does not match"):
        labels_from_name("notes.csv", "{texture}__V{speed_mm_s}__{rep}.csv")


def test_mapping_gives_labels_layout_and_texture_set(tmp_path):
    a, b = write(tmp_path / "run1.npy", recording(0, channels=4), "npy"), write(tmp_path / "run2.npy",
                                                                                 recording(1, channels=4), "npy")
    mp = tmp_path / "map.toml"
    mp.write_text('rate_hz = 100\nlayout = "2x2"\n[files."run1.npy"]\ntexture = "silk"\nforce_g = 30\n'
                  '[files."run2.npy"]\ntexture = "wool"\nspeed_mm_s = 15\n'
                  '[texture_set]\ntextures = ["wool", "silk"]\ngroups = { natural = ["wool", "silk"] }\n')
    out = tmp_path / "s.h5"
    r = run(a, b, "--mapping", mp, "--out", out)
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert s.layout.shape_text == "2x2x1" and s.layout.sample_rate_hz == 100
        assert list(s.plan["texture"]) == ["silk", "wool"]
        assert s.textures.labels == ("wool", "silk") and s.textures.group_of("silk") == "natural"
        assert s.plan["force_g"][0] == 30 and s.plan["speed_mm_s"][1] == 15


def test_mapping_with_an_unknown_key_is_refused_by_name(tmp_path):
    a = write(tmp_path / "run1.npy", recording(0), "npy")
    mp = tmp_path / "map.toml"
    mp.write_text('rate = 100\n[defaults]\ntexture = "silk"\n')  # "rate" instead of "rate_hz"
    r = run(a, "--mapping", mp, "--out", tmp_path / "s.h5")
    assert r.exit_code != 0 and "unknown key(s) rate;" in r.output and "rate_hz" in r.output
    assert not (tmp_path / "s.h5").exists()


def continuous(seconds_rest=(1.0, 0.7, 1.2, 0.8), seconds_on=(1.5, 2.0, 1.0)) -> tuple[np.ndarray, list]:
    """Rest at a constant level with bursts of texture signal in between; returns data and the bursts' ranges."""
    parts, bursts, pos = [], [], 0
    rng = np.random.default_rng(3)
    for i, rest in enumerate(seconds_rest):
        n = int(rest * RATE)
        parts.append(500 + rng.integers(-2, 3, (n, 9)))
        pos += n
        if i < len(seconds_on):
            m = int(seconds_on[i] * RATE)
            t = np.arange(m) / RATE
            parts.append(np.rint(500 + 120 * np.sin(2 * np.pi * 4 * t)[:, None] + np.arange(9)).astype(int))
            bursts.append((pos, pos + m))
            pos += m
    return np.concatenate(parts), bursts


def test_continuous_recording_segmented_by_threshold(tmp_path):
    data, bursts = continuous()
    p = write(tmp_path / "felt__V20__0.csv", data, "csv")
    out = tmp_path / "s.h5"
    r = run(p, "--rate", 100, "--label-pattern", PATTERN, "--segment", "threshold:40:0.5", "--out", out)
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert len(s.plan) == 3 and list(s.plan["repeat"]) == [0, 1, 2]
        assert json.loads(s.attrs["segmentation"])["method"] == "threshold"
        for row, (a, b) in zip(s.plan, bursts):
            t = s.trial(int(row["trial_id"]))
            start = round(t.attrs["segment_start_s"] * RATE)
            assert abs(start - a) <= 6 and abs(start + t.n_samples - b) <= 6  # within the 50 ms smoothing
            np.testing.assert_array_equal(t.taxels, data[start:start + t.n_samples])


def test_continuous_recording_segmented_fixed_and_by_cycles(tmp_path):
    n = 1000
    t = np.arange(n) / RATE
    data = np.rint(500 + 100 * np.sign(np.sin(2 * np.pi * t / 0.8))[:, None] * np.ones(9)
                   + 30 * np.sin(2 * np.pi * 5 * t)[:, None]).astype(int)  # one drum revolution per 0.8 s
    cut = segment(data, RATE, parse_segment("cycles:2", align="none"))  # windows from sample 0
    assert cut.period_s == pytest.approx(0.8, abs=0.011)
    assert len(cut.bounds) == 6 and all(b - a == 160 for a, b in cut.bounds)
    assert segment(data, RATE, parse_segment("fixed:2.5")).bounds == [(0, 250), (250, 500), (500, 750), (750, 1000)]
    p = write(tmp_path / "drum.npy", data, "npy")
    out = tmp_path / "s.h5"
    r = run(p, "--rate", 100, "--texture", "ridges", "--segment", "fixed:2:1", "--out", out)
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert len(s.plan) == 9 and set(s.plan["texture"]) == {"ridges"}
        np.testing.assert_array_equal(s.trial(3).taxels, data[300:500])
    for bad in ("fixed", "fixed:-1", "wavelet:3", "threshold:x", "threshold:150%", "cycles:1.5", "cycles:1:5:2"):
        with pytest.raises(RecordingImportError):
            parse_segment(bad)


def test_refusals(tmp_path):
    files, _ = make_files(tmp_path, "npy")
    out = tmp_path / "s.h5"
    out.write_bytes(b"not mine")
    r = run(*files, "--rate", 100, "--label-pattern", PATTERN, "--out", out)
    assert r.exit_code != 0 and "exists" in r.output and "--overwrite" in r.output
    assert out.read_bytes() == b"not mine"
    r = run(*files, "--rate", 100, "--label-pattern", PATTERN, "--out", files[1], "--overwrite")
    assert r.exit_code != 0 and "is one of the input files" in r.output
    np.testing.assert_array_equal(np.load(files[1]), recording(1))
    r = run(*files, "--label-pattern", PATTERN, "--out", tmp_path / "x.h5")
    assert r.exit_code != 0 and "--rate" in r.output and "Traceback" not in r.output
    r = run(*files, "--rate", 100, "--out", tmp_path / "x.h5")
    assert r.exit_code != 0 and "no texture label" in r.output
    r = run(*files, "--rate", 100, "--label-pattern", PATTERN, "--channels", 9, "--layout", "2x2", "--out",
            tmp_path / "x.h5")
    assert r.exit_code != 0 and "channels" in r.output
    big = write(tmp_path / "big__V1__0.npy", recording(0) * 4, "npy")
    r = run(big, "--rate", 100, "--label-pattern", PATTERN, "--out", tmp_path / "x.h5")
    assert r.exit_code != 0 and "10-bit ADC range" in r.output
    r = run(big, "--rate", 100, "--label-pattern", PATTERN, "--bits", 12, "--out", tmp_path / "x.h5")
    assert r.exit_code == 0, r.output


def test_volts_with_a_reference(tmp_path):
    """--volts-ref 5: one count is 5/1024 V (the AVR ADC's step), not 5/1023: known volts land on known counts."""
    counts = recording(0)
    volts = counts * (5.0 / 1024)  # what a 10-bit AVR ADC reading of `counts` means in volts
    volts[:4, 0] = [0.0, 5.0 / 1024, 2.5, 5.0]  # 0 V -> 0, one step -> 1, half the reference -> 512, 5 V -> top
    counts[:4, 0] = [0, 1, 512, 1023]
    p = write(tmp_path / "wool__V10__0.npy", volts, "npy")
    out = tmp_path / "s.h5"
    r = run(p, "--rate", 100, "--label-pattern", PATTERN, "--volts-ref", 5, "--out", out)
    # 5 V itself is one step past 1023: refused (issue 77: volts above the reference were pinned without a word)
    assert r.exit_code != 0 and "1 of 2700 values are outside the 10-bit ADC range" in r.output, r.output
    assert "--clip" in r.output and not out.exists()
    r = run(p, "--rate", 100, "--label-pattern", PATTERN, "--volts-ref", 5, "--clip", "--out", out)
    assert r.exit_code == 0, r.output
    assert "1 of 2700 values clipped to the 10-bit range 0..1023 (--clip)" in r.output, r.output
    with open_session(out) as s:
        np.testing.assert_array_equal(s.trial(0).taxels, counts)
        step = json.loads(s.attrs["import_steps"])["value_scale"]
        assert step["unit"] == "volts" and step["clipped_values"] == 1
    help_text = CliRunner().invoke(main, ["import", "--help"]).output
    assert "V/2^bits" in help_text


def test_nan_samples_refused_by_count_and_position_or_held_or_interpolated(tmp_path):
    """NaN at samples 1-2 (as a lab's logger writes them) and a run at 100-103: refused by default with the file,
    the count and the first positions; --nan hold repeats the last good value, --nan interpolate draws the line."""
    counts = recording(0).astype(np.float64)
    x = counts.copy()
    x[1:3, 0] = np.nan
    x[100:104, 4] = np.nan
    p = write(tmp_path / "wool__V10__0.npy", x, "npy")
    out = tmp_path / "s.h5"
    r = run(p, "--rate", 100, "--label-pattern", PATTERN, "--out", out)
    assert r.exit_code == 1 and "Traceback" not in r.output and not out.exists()
    assert "wool__V10__0.npy" in r.output and "6 NaN values" in r.output and "samples 1, 2, 100, 101, 102" in r.output
    for policy in ("hold", "interpolate"):
        r = run(p, "--rate", 100, "--label-pattern", PATTERN, "--nan", policy, "--out", out, "--overwrite")
        assert r.exit_code == 0, r.output
        with open_session(out) as s:
            got = s.trial(0).taxels.astype(np.float64)
            read = json.loads(s.attrs["import_steps"])["read"][0]
        ok = ~np.isnan(x)
        np.testing.assert_array_equal(got[ok], counts[ok])  # good samples untouched
        if policy == "hold":
            assert list(got[1:3, 0]) == [counts[0, 0]] * 2 and list(got[100:104, 4]) == [counts[99, 4]] * 4
        else:
            line = np.interp(np.arange(100, 104), [99, 104], [counts[99, 4], counts[104, 4]])
            np.testing.assert_array_equal(got[100:104, 4], np.rint(line))
        assert read["nan"] == {"policy": policy, "samples": 6}


def test_fabricslide_preset_fabrics_and_board_in_one_16_channel_file(fabricslide_dir, tmp_path):
    """The FabricSlide preset (real files, read in place): 16 channels as 16 at 1 kHz, fabrics and board in one
    session with the FabricSlide texture set; the same via `rigctl import --preset fabricslide` is refused for two
    folders, and the output is not overwritten."""
    from rigctl.storage.fabricslide import (
        FABRICSLIDE_SENSOR,
        import_fabricslide,
        read_recording,
        resample_to_1khz,
        to_adc,
    )

    out = tmp_path / "fs.h5"
    events = []
    summary = import_fabricslide(fabricslide_dir, out, pattern="*_F150_V-20mmps_0.csv", trim=0.0,
                                 progress=events.append)
    # progress events: 5 files read, then 5 trials written
    assert [(e.stage, e.done, e.total, e.unit) for e in events] == [("FabricSlide import", k, 10, "file")
                                                                    for k in range(11)]
    assert summary["labels"] == ["BeigeCotton", "BrownCotton", "Canvas", "Linen", "Board10mm"]
    with open_session(out) as s:
        assert s.layout == FABRICSLIDE_SENSOR and s.layout.n_channels == 16
        assert list(s.plan["texture"]) == ["BeigeCotton", "BrownCotton", "Canvas", "Linen", "Board10mm"]
        assert [s.textures.group_of(t) for t in s.plan["texture"]] == ["fabric"] * 4 + ["board"]
        assert [s.textures.code(t) for t in s.plan["texture"]] == [0, 1, 2, 3, 4]
        for row in s.plan:
            t = s.trial(int(row["trial_id"]))
            kind, name = t.attrs["source_file"].split("/")
            rec = read_recording(fabricslide_dir / kind / name)
            np.testing.assert_array_equal(t.taxels, to_adc(resample_to_1khz(rec.timestamp_ms, rec.readings)[1]))
    r = run(fabricslide_dir, fabricslide_dir, "--preset", "fabricslide", "--out", tmp_path / "x.h5")
    assert r.exit_code != 0 and "one FILES argument" in r.output
    before = out.stat().st_mtime_ns
    r = run(fabricslide_dir, "--preset", "fabricslide", "--out", out)
    assert r.exit_code != 0 and "--overwrite" in r.output and out.stat().st_mtime_ns == before


def test_npz_stacked_trials_with_their_rate(tmp_path):
    """An NPZ holding (n_trials, n_samples, n_channels) and its rate: one trial per slice, repeats numbered."""
    stack = np.stack([recording(i, n=200) for i in range(4)])
    p = tmp_path / "wool__V25__0.npz"
    np.savez(p, taxels=stack, rate_hz=np.float64(RATE), labels=np.arange(4))
    out = tmp_path / "s.h5"
    r = run(p, "--label-pattern", PATTERN, "--out", out)
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert s.layout.sample_rate_hz == RATE and len(s.plan) == 4
        assert list(s.plan["repeat"]) == [0, 1, 2, 3] and set(s.plan["texture"]) == {"wool"}
        for i in range(4):
            t = s.trial(i)
            assert t.attrs["source_block"] == i
            np.testing.assert_array_equal(t.taxels, stack[i])
