"""FabricSlide loader, 1 kHz resampling and the importer, on the real files (../shared/data/fabricslide)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.storage.fabricslide import (
    FABRICSLIDE_SENSOR,
    FABRICSLIDE_TEXTURES,
    list_files,
    load_fabricslide,
    parse_name,
    read_recording,
    resample_to_1khz,
    to_adc,
)
from rigctl.storage.session import open_session


def _reference_resample(ts, x):
    """Straightforward per-sample reference: for each ms, the bracketing samples and the linear formula."""
    grid = np.arange(ts[0], ts[-1] + 1e-9, 1.0)
    out = np.empty((grid.size, x.shape[1]))
    j = 0
    for i, t in enumerate(grid):
        while j + 1 < ts.size - 1 and ts[j + 1] <= t:
            j += 1
        w = (t - ts[j]) / (ts[j + 1] - ts[j])
        out[i] = x[j] * (1 - w) + x[j + 1] * w
    return grid, out


def test_parse_names():
    assert parse_name("BeigeCotton_F120_V-100mmps_2.csv") == {
        "label": "BeigeCotton", "force_setpoint": 120.0, "velocity_mm_s": -100.0, "repeat": 2}
    assert parse_name("Board10mm_F150_V-5mmps_0.csv")["velocity_mm_s"] == -5.0
    with pytest.raises(ValueError, match="not a FabricSlide file name"):
        parse_name("notes.csv")


def test_load_real_recordings(fabricslide_dir):
    # all 720 fabric files are found and labelled from their names
    names = [parse_name(p.name) for p in list_files(fabricslide_dir)]
    assert len(names) == 720
    assert {n["label"] for n in names} == {"BeigeCotton", "BrownCotton", "Canvas", "Linen"}
    assert {n["force_setpoint"] for n in names} == {120, 150, 180, 210, 250}
    assert {abs(n["velocity_mm_s"]) for n in names} == {10, 20, 50, 100, 120, 150}
    assert {n["repeat"] for n in names} == {0, 1, 2}
    # one force setpoint read in full (fabrics and the board)
    recs = load_fabricslide(fabricslide_dir, include_board=True, pattern="*_F150_*")
    fabrics = [r for r in recs if r.kind == "fabric"]
    assert len(fabrics) == 144 and all(r.force_setpoint == 150 for r in recs)
    assert recs[-1].kind == "board" and recs[-1].label == "Board10mm"
    assert {r.direction for r in fabrics} == {-1, 1}
    for r in recs:
        assert r.readings.shape == (r.timestamp_ms.size, 16)
        assert np.all(np.diff(r.timestamp_ms) > 0)  # repeated timestamps removed
    # about 28 ms between samples, and the covered travel is about 594 mm whatever the speed
    dt = np.median(np.concatenate([np.diff(r.timestamp_ms) for r in fabrics]))
    assert 25 <= dt <= 31
    travel = [r.speed_mm_s * (r.timestamp_ms[-1] - r.timestamp_ms[0]) / 1000 for r in fabrics]
    assert 500 < np.median(travel) < 700


def test_repeated_timestamps_keep_the_first_sample(tmp_path):
    header = "timestamp, proximity1, proximity2, " + ", ".join(f"channel{i}" for i in range(1, 17))
    rows = [[0] + [0, 0] + [10] * 16, [28] + [0, 0] + [20] * 16, [28] + [0, 0] + [99] * 16,
            [56] + [0, 0] + [40] * 16]
    p = tmp_path / "Felt_F100_V20mmps_0.csv"
    p.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    rec = read_recording(p)
    np.testing.assert_array_equal(rec.timestamp_ms, [0, 28, 56])
    np.testing.assert_array_equal(rec.readings[:, 0], [10, 20, 40])
    grid, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
    assert grid.size == 57 and values[14, 0] == pytest.approx(15.0) and values[42, 0] == pytest.approx(30.0)


def test_resampling_matches_a_per_sample_reference(fabricslide_dir):
    rec = load_fabricslide(fabricslide_dir, pattern="Linen_F180_V50mmps_1.csv")[0]
    grid, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
    ref_grid, ref = _reference_resample(rec.timestamp_ms, rec.readings)
    np.testing.assert_array_equal(grid, ref_grid)
    np.testing.assert_allclose(values, ref, rtol=0, atol=1e-9)
    # on the original sample times the resampled values are the recorded ones
    on_grid = (rec.timestamp_ms - rec.timestamp_ms[0]).astype(int)
    np.testing.assert_array_equal(values[on_grid], rec.readings)
    adc = to_adc(values)
    assert adc.shape == (grid.size, 16) and adc.dtype == np.uint16  # 16 channels as 16 channels: no padding
    np.testing.assert_array_equal(adc[on_grid], rec.readings.astype(np.uint16))


def test_import_writes_fabrics_and_board_in_one_session(fabricslide_dir, tmp_path):
    """The FabricSlide preset: 16 channels as 16, fabrics and the board in one file with their texture set."""
    from rigctl.cli import main

    out = tmp_path / "fs.h5"
    result = CliRunner().invoke(main, ["import-fabricslide", str(fabricslide_dir), "--out", str(out),
                                       "--pattern", "*_F150_V*mmps_0.csv", "--trim", "0.1", "--quiet"])
    assert result.exit_code == 0, result.output
    with open_session(out) as s:
        assert s.kind == "fabricslide"
        assert s.layout == FABRICSLIDE_SENSOR and s.layout.n_channels == 16 and s.layout.sample_rate_hz == 1000
        assert s.textures.labels == FABRICSLIDE_TEXTURES.labels == (
            "BeigeCotton", "BrownCotton", "Canvas", "Linen", "Board10mm")
        assert s.textures.group_of("Linen") == "fabric" and s.textures.group_of("Board10mm") == "board"
        fabrics = s.plan[s.plan["texture"] != "Board10mm"]
        boards = s.plan[s.plan["texture"] == "Board10mm"]
        assert len(fabrics) == 4 * 12  # 4 fabrics x 12 signed velocities, repeat 0, force 150
        assert len(boards) == 4  # the board at -5, -10, -20, -30 mm/s
        assert set(fabrics["speed_mm_s"]) == {10, 20, 50, 100, 120, 150}
        assert set(boards["speed_mm_s"]) == {5, 10, 20, 30}
        assert json.loads(s.attrs["resampling"])["to_hz"] == 1000
        for row in (s.plan[5], boards[0]):
            t = s.trial(int(row["trial_id"]))
            assert t.taxels.shape[1] == 16 and t.layout == FABRICSLIDE_SENSOR
            kind, name = t.attrs["source_file"].split("/")
            rec = read_recording(fabricslide_dir / kind / name)
            assert row["texture"] == rec.label == t.attrs["fabric"]
            assert row["speed_mm_s"] == abs(rec.velocity_mm_s) and t.attrs["velocity_mm_s"] == rec.velocity_mm_s
            assert row["force_g"] == 150
            _, values = resample_to_1khz(rec.timestamp_ms, rec.readings)
            k = int(round(0.1 * values.shape[0]))
            np.testing.assert_array_equal(t.taxels, to_adc(values[k:values.shape[0] - k]))
            assert t.n_samples == round(row["duration_s"] * 1000)
    # the same output again is refused without --overwrite
    again = CliRunner().invoke(main, ["import-fabricslide", str(fabricslide_dir), "--out", str(out),
                                      "--pattern", "Linen_F150_V10mmps_0.csv", "--quiet"])
    assert again.exit_code != 0 and "--overwrite" in again.output and "Traceback" not in again.output


def test_the_folder_is_given_or_named_by_the_environment(fabricslide_dir, tmp_path, monkeypatch):
    """No default inside the installation: DIRECTORY, else $RIGCTL_FABRICSLIDE, else a one-line usage error."""
    from rigctl.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("RIGCTL_FABRICSLIDE", raising=False)
    missing = CliRunner().invoke(main, ["import-fabricslide", "--out", "a.h5", "--quiet"])
    assert missing.exit_code == 2 and "RIGCTL_FABRICSLIDE" in missing.output and "DIRECTORY" in missing.output
    assert not (tmp_path / "a.h5").exists()
    monkeypatch.setenv("RIGCTL_FABRICSLIDE", str(fabricslide_dir))
    named = CliRunner().invoke(main, ["import-fabricslide", "--out", "b.h5", "--pattern", "Linen_F150_V10mmps_0.csv",
                                      "--no-board", "--quiet"])
    assert named.exit_code == 0, named.output
    with open_session(tmp_path / "b.h5") as s:
        assert [t.decode() if isinstance(t, bytes) else t for t in s.plan["texture"]] == ["Linen"]
    monkeypatch.setenv("RIGCTL_FABRICSLIDE", str(tmp_path / "nowhere"))
    wrong = CliRunner().invoke(main, ["import-fabricslide", "--out", "c.h5", "--quiet"])
    assert wrong.exit_code == 1 and "nowhere" in wrong.output and "Traceback" not in wrong.output


def test_gaps_and_clipping_refused_unless_asked_and_every_change_in_the_ledger(tmp_path):
    """The FabricSlide preset changed values without a word (issue 77 item 1): its regridding, repeated stamps, gaps
    interpolated across and readings clipped to the 10-bit map were in no ledger. Now a gap or a reading outside the
    map is refused in one line unless asked for by name (--close-gaps, --clip), and each change is a ledger line."""
    from rigctl.cli import main

    header = "timestamp, proximity1, proximity2, " + ", ".join(f"channel{i}" for i in range(1, 17))
    folder = tmp_path / "fs"
    (folder / "fabric").mkdir(parents=True)
    rng = np.random.default_rng(0)
    ts = np.arange(200) * 28.0
    ts[120:] += 400.0  # a 0.4 s hole
    rows = np.column_stack([ts, np.zeros((200, 2)), rng.integers(100, 200, (200, 16))])
    rows = np.insert(rows, 50, rows[49], axis=0)  # one repeated stamp
    np.savetxt(folder / "fabric" / "Linen_F150_V10mmps_0.csv", rows, delimiter=",", fmt="%g", header=header,
               comments="")

    def run(*extra):
        r = CliRunner().invoke(main, ["import-fabricslide", str(folder), "--out", str(tmp_path / "o.h5"), "--quiet",
                                      "--no-board", "--overwrite", *extra])
        return r.exit_code, r.output

    rc, out = run()
    assert rc == 1 and "1 gap(s) in the time stamps" in out and "--close-gaps" in out and "Traceback" not in out, out
    assert not (tmp_path / "o.h5").exists()
    rc, out = run("--close-gaps")
    assert rc == 0, out
    assert "ledger: time stamps (ms) of 1 files put on the 1 kHz grid by linear interpolation: 201 rows" in out, out
    assert "ledger: 1 row(s) of repeated stamps dropped (the first kept)" in out, out
    assert "ledger: 1 gap(s) in the time stamps interpolated across (--close-gaps)" in out, out
    r = CliRunner().invoke(main, ["info", str(tmp_path / "o.h5")])
    assert "interpolated across (--close-gaps)" in r.output, r.output
    rows[10, 3:] = 4000  # beyond the map
    np.savetxt(folder / "fabric" / "Linen_F150_V10mmps_0.csv", rows, delimiter=",", fmt="%g", header=header,
               comments="")
    rc, out = run("--close-gaps")
    assert rc == 1 and "16 readings map outside the 10-bit range 0..1023" in out and "--clip" in out, out
    rc, out = run("--close-gaps", "--clip")
    assert rc == 0 and "ledger: 16 reading(s) clipped to 0..1023 (--clip)" in out, out
