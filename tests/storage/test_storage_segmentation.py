"""Segmenting continuous press-and-slide recordings (issue 23): 6 generated files, 3 textures, periods 3.8-7.2 s,
press levels 40-200 counts (5x), a start-up transient, NaN runs, 100 Hz, 9 channels, one file with alternating
press strengths and one short file. Every cycle of every file found, trials cut at each press onset, the per-file
table printed, the outlier file named; the threshold method per file level; a file without trials named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.simulation.press_slide import RATE_HZ, write_press_slide_set
from rigctl.storage.recording_files import fill_nan
from rigctl.storage.segmentation import parse_segment, segment
from rigctl.storage.session import open_session

PATTERN = "{texture}__R{recording}"
#: trials must start within 50 ms of the press onset
ONSET_TOLERANCE = int(0.050 * RATE_HZ)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    folder = tmp_path_factory.mktemp("press_slide")
    return folder, write_press_slide_set(folder)


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def run_import(*args):
    return run("import", *args)


def filled(truth):
    x, _ = fill_nan(np.load(truth.path), "interpolate")
    return np.rint(x).astype(np.uint16)


def trials_by_file(path):
    out: dict[str, list] = {}
    with open_session(path) as s:
        for row in s.plan:
            t = s.trial(int(row["trial_id"]))
            out.setdefault(str(t.attrs["source_file"]), []).append((row, t))
    return out


def test_cycles_find_every_cycle_at_its_press_onset_with_a_table_and_the_outlier_named(recordings, tmp_path):
    folder, truth = recordings
    out = tmp_path / "s.h5"
    r = run_import(*[t.path for t in truth], "--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles",
            "--nan", "interpolate", "--out", out)
    assert r.exit_code == 0, r.output
    table = r.stdout.splitlines()
    assert table[0].split()[:4] == ["file", "period", "s", "trials"]
    for t in truth:  # one row per file: its period (within 3 %) and its trial count
        row = next(line.split() for line in table if line.startswith(t.path.name))
        assert float(row[1]) == pytest.approx(t.period_s, rel=0.03) and abs(int(row[2]) - len(t.onsets)) <= 1
    short = truth[-1].path.name
    warned = [line for line in r.stderr.splitlines() if line.startswith("warning:")]
    assert len(warned) == 1 and short in warned[0] and "trial count 8" in warned[0]
    # the flag is carried in the session (issue 77 item 7): info lists it, encode (so analyze) says it
    info = CliRunner().invoke(main, ["info", str(out)])
    assert f"import flagged: {warned[0].removeprefix('warning: ')}" in info.output, info.output
    enc = CliRunner().invoke(main, ["encode", str(out), "--out", str(tmp_path / "e.h5"), "--no-progress",
                                    "--variant", "original"])
    assert enc.exit_code == 0 and "the import flagged 1 file(s) (rigctl info lists them): " + short in enc.output, \
        enc.output
    ana = CliRunner().invoke(main, ["analyze", str(tmp_path / "e.h5"), "--task", "textures", "--repeats", "1",
                                    "--pcs", "1-2", "--no-progress"])  # the encoded file: the session's flag again
    assert ana.exit_code == 0 and ("encoded from s.h5, whose import flagged 1 file(s) (rigctl info s.h5 lists them): "
                                   + short) in ana.output, ana.output
    got = trials_by_file(out)
    assert sorted(got) == sorted(t.path.name for t in truth)
    for t in truth:
        trials, onsets = got[t.path.name], np.asarray(t.onsets)
        assert abs(len(trials) - len(onsets)) <= 1, (t.path.name, len(trials), len(onsets))  # +-1 partial
        data = filled(t)
        matched = []
        for row, trial in trials:
            first, last = int(trial.attrs["source_first_sample"]), int(trial.attrs["source_last_sample"])
            nearest = int(onsets[np.argmin(np.abs(onsets - first))])
            assert abs(first - nearest) <= ONSET_TOLERANCE, (t.path.name, first, nearest)
            matched.append(nearest)
            np.testing.assert_array_equal(trial.taxels, data[first:last + 1])  # the source's samples, exactly
            assert str(row["texture"]) == t.texture and trial.attrs["recording"] == t.path.stem.split("__R")[1]
        assert len(set(matched)) == len(matched)  # one trial per press
        cycles = [int(trial.attrs["cycle_index"]) for _, trial in trials]
        assert cycles == sorted(cycles) and len(set(cycles)) == len(cycles)
    info = json.loads(run("info", out, "--json").stdout)
    first = info["trials"][0]["source"]
    assert first["file"] == truth[0].path.name and first["cycle"] == 0
    assert abs(first["first_sample"] - truth[0].onsets[0]) <= ONSET_TOLERANCE
    text = run("info", out).stdout
    assert f"from {truth[0].path.name} samples {first['first_sample']}-{first['last_sample']} cycle 0" in text


def test_the_period_is_checked_against_its_harmonics(recordings):
    """Alternating strong and weak presses (silk__R1): the former rule (the shortest autocorrelation peak near the
    highest, from sample 0) takes twice the period; the checked period is the press period for every file."""
    _, truth = recordings
    former = {}
    for t in truth:
        x = filled(t)
        cut = segment(x, RATE_HZ, parse_segment("cycles"))
        assert cut.period_s == pytest.approx(t.period_s, rel=0.03), t.path.name
        scores = {round(c["period_s"], 2): c["cycles"] for c in cut.candidates}
        assert max(scores.values()) >= len(t.onsets) - 2  # the winning candidate explains (nearly) every cycle
        former[t.path.name] = segment(x, RATE_HZ, parse_segment("cycles", align="none")).period_s
    wrong = {name: p for (name, p), t in zip(former.items(), truth) if abs(p / t.period_s - 1) > 0.2}
    assert truth[1].path.name in wrong, former  # the control: alternating presses fool the former rule (2x)


def test_pre_onset_margin(recordings):
    _, truth = recordings
    t = truth[2]
    cut = segment(filled(t), RATE_HZ, parse_segment("cycles", pre_ms=200))
    onsets = np.asarray(t.onsets)
    for a, _ in cut.bounds:
        nearest = onsets[np.argmin(np.abs(onsets - (a + 20)))]
        assert abs(a + 20 - nearest) <= ONSET_TOLERANCE


def test_threshold_at_each_files_own_level(recordings, tmp_path):
    """Levels 5x apart: the default threshold (50 % of each file's own swing) finds every press of every file; one
    level in counts for all files finds none in the weakest file, which is an error naming it (not a texture
    silently missing)."""
    _, truth = recordings
    out = tmp_path / "t.h5"
    r = run_import(*[t.path for t in truth], "--rate", 100, "--label-pattern", PATTERN, "--segment", "threshold",
            "--nan", "hold", "--out", out)
    assert r.exit_code == 0, r.output
    got = trials_by_file(out)
    for t in truth:
        onsets = np.asarray(t.onsets)
        trials = got[t.path.name]
        assert abs(len(trials) - len(onsets)) <= 1, (t.path.name, len(trials))
        starts = [int(tr.attrs["source_first_sample"]) for _, tr in trials]
        assert all(np.min(np.abs(onsets - s)) <= 0.2 * RATE_HZ for s in starts)  # a run starts on the ramp
    with open_session(out) as s:
        assert sorted(s.textures.labels) == ["cork", "felt", "silk"]
    out2 = tmp_path / "t2.h5"
    r = run_import(*[t.path for t in truth], "--rate", 100, "--label-pattern", PATTERN, "--segment", "threshold:60",
            "--nan", "hold", "--out", out2)
    assert r.exit_code == 1 and "Traceback" not in r.output and not out2.exists()
    assert truth[0].path.name in r.output and "no trial found" in r.output


def test_a_file_without_cycles_is_named(tmp_path):
    rng = np.random.default_rng(1)
    p = tmp_path / "flat__R0.npy"
    np.save(p, np.rint(500 + rng.normal(0, 2, (3000, 9))))  # whole counts (fractions are refused)
    r = run_import(p, "--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles", "--out", tmp_path / "s.h5")
    assert r.exit_code == 1 and "Traceback" not in r.output and "flat__R0.npy" in r.output
    assert not (tmp_path / "s.h5").exists()


def test_a_period_at_twice_the_median_is_flagged():
    """The outlier rule fires at 2x the median and at half of it, not only beyond (issue 38: a file cut at exactly
    twice its period, one trial per two cycles, passed silently); files within the band are not named."""
    from rigctl.storage.segmentation import outlier_warnings

    rows = [{"file": f"f{i}.npy", "period_s": p, "trials": 40} for i, p in enumerate((5.0, 5.0, 5.0, 10.0, 2.5, 9.9))]
    named = [w.split(":")[0] for w in outlier_warnings(rows)]
    assert named == ["f3.npy", "f4.npy"]


def test_skip_bad_names_every_refused_file_and_imports_the_rest(tmp_path):
    """``--skip-bad``: a flat file (no cycles) and a file with NaN (refused without --nan) are left out, each named
    with its reason on stderr and in the session's import steps; the good files' trials are imported. Without the
    option the first bad file stops the import (issue 38). A long file imported whole gets the hint to segment it."""
    truth = write_press_slide_set(tmp_path, DEFAULT_SET_SHORT, nan=False)
    rng = np.random.default_rng(1)
    np.save(tmp_path / "flat__R7.npy", np.rint(500 + rng.normal(0, 2, (3000, 9))))  # whole counts (fractions are refused)
    nan = np.load(truth[0].path)
    nan[100:110] = np.nan
    np.save(tmp_path / "felt__R8.npy", nan)
    files = sorted(tmp_path.glob("*.npy"))
    args = [*files, "--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles", "--out"]
    stopped = run_import(*args, tmp_path / "stopped.h5")
    assert stopped.exit_code == 1 and not (tmp_path / "stopped.h5").exists()
    r = run_import(*args, tmp_path / "s.h5", "--skip-bad")
    assert r.exit_code == 0, r.output
    refused = [line for line in r.stderr.splitlines() if line.startswith("warning: refused ")]
    assert [line.split()[2].rstrip(":") for line in refused] == ["felt__R8.npy", "flat__R7.npy"], r.stderr
    assert "NaN" in refused[0] and "no presses above the noise" in refused[1]
    with open_session(tmp_path / "s.h5") as s:
        steps = json.loads(s.attrs["import_steps"])
        assert [Path(x["file"]).name for x in steps["refused"]] == ["felt__R8.npy", "flat__R7.npy"]
        sources = {s.trial_attrs(i)["source_file"] for i in s.completed_ids()}
    assert sources == {t.path.name for t in truth}
    whole = run_import(truth[0].path, "--rate", 100, "--texture", "felt", "--out", tmp_path / "whole.h5")
    assert whole.exit_code == 0 and "felt__R0.npy: one trial of" in whole.stderr and "--segment cycles" in whole.stderr


#: three short clean files for the skip-bad test (texture, period_s, level, cycles, alternating)
DEFAULT_SET_SHORT = (("felt", 3.8, 40.0, 17, False), ("silk", 4.5, 200.0, 14, False), ("cork", 5.2, 80.0, 12, False))


def test_overlapping_trials_are_named_per_file():
    """Trials that share samples (a period longer than the press spacing) are counted per file and named."""
    from rigctl.storage.segmentation import Segmentation, outlier_warnings

    cut = Segmentation(bounds=[(0, 600), (400, 1000), (800, 1400), (1500, 1900)], cycle_index=[0, 1, 2, 3])
    assert cut.overlaps() == (2, 400)
    row = cut.row("wood__R3.npy", 100.0)
    assert (row["overlapping"], row["shared_samples"]) == (2, 400)
    (line,) = outlier_warnings([row])
    assert line.startswith("wood__R3.npy: 2 trials run into the next one (400 samples in two trials)")
    clean = Segmentation(bounds=[(0, 400), (400, 800)], cycle_index=[0, 1]).row("ok.npy", 100.0)
    assert clean["overlapping"] == 0 and outlier_warnings([clean]) == []


def test_a_labs_38_recordings_in_one_import(tmp_path):
    """issue 38's case, generated (rigctl.simulation.press_slide.write_lab_set): 38 continuous recordings, 9 channels
    at 100 Hz, 40-42 press cycles each; 4 with NaN runs and 2 flat are refused by name with their reason and the import
    goes on (--skip-bad); the 2 at twice the usual period are flagged; every good file is cut into its cycles."""
    from rigctl.simulation.press_slide import write_lab_set

    written = write_lab_set(tmp_path / "lab")
    r = run_import(*(p for p, _ in written), "--rate", 100, "--layout", "3x3x1", "--label-pattern", PATTERN,
                   "--segment", "cycles", "--skip-bad", "--out", tmp_path / "lab.h5")
    assert r.exit_code == 0, r.output
    refused = {line.split()[2].rstrip(":") for line in r.stderr.splitlines() if line.startswith("warning: refused ")}
    assert refused == {p.name for p, f in written if f.fault in ("nan", "flat")}
    flagged = {line.split()[1].rstrip(":") for line in r.stderr.splitlines() if " period " in line and "outlier" in line}
    assert flagged == {p.name for p, f in written if f.fault == "doubled"}
    assert "run into the next one" not in r.stderr
    with open_session(tmp_path / "lab.h5") as s:  # every trial's source file, in one pass (rigctl info's)
        per_file: dict[str, int] = {}
        for row in s.trial_table(s.completed_ids(), ["source_file"]):
            name = row["source_file"]
            per_file[name] = per_file.get(name, 0) + 1
    good = {p.name: f for p, f in written if f.fault in ("", "doubled")}
    assert set(per_file) == set(good) and len(good) == 32
    for name, f in good.items():  # the partial first/last cycles rejected: every whole cycle a trial
        assert f.n_cycles - 1 <= per_file[name] <= f.n_cycles, (name, per_file[name], f)


def test_a_clearly_periodic_file_passes_the_noise_rule_and_min_swing_sets_it(tmp_path):
    """A file whose presses lift the activity only 6x its noise but repeat clearly (autocorrelation ~0.9) is cut into
    its 40 cycles (issue 38: refused on amplitude alone); the noise rule's ratio is --min-swing, recorded in the
    session; a flat file is still refused, its message naming --min-swing."""
    from rigctl.simulation.press_slide import press_slide_recording

    x, _ = press_slide_recording(5.0, 8.0, 40, nan=False, seed=3)
    np.save(tmp_path / "faint__R0.npy", x)
    common = ["--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles"]
    r = run_import(tmp_path / "faint__R0.npy", *common, "--out", tmp_path / "a.h5")
    assert r.exit_code == 0, r.output
    with open_session(tmp_path / "a.h5") as s:
        assert len(s.completed_ids()) == 40
        assert json.loads(s.attrs["segmentation"])["min_swing"] == 10.0
    rng = np.random.default_rng(2)
    np.save(tmp_path / "flat__R1.npy", np.rint(500 + rng.normal(0, 2, (3000, 9))))  # whole counts (fractions are refused)
    r = run_import(tmp_path / "flat__R1.npy", *common, "--out", tmp_path / "b.h5")
    assert r.exit_code == 1 and "--min-swing (now 10)" in r.output
    r = run_import(tmp_path / "faint__R0.npy", *common, "--min-swing", 4, "--out", tmp_path / "c.h5")
    assert r.exit_code == 0, r.output
    with open_session(tmp_path / "c.h5") as s:
        assert json.loads(s.attrs["segmentation"])["min_swing"] == 4.0


# ---------------------------------------------------------------------------------------------- issue 52 item 5
def test_press_check_counts_presses_cut_one_by_one():
    """Each trial checked against the press phase: a trial per press at its onset passes; every other press cut,
    trials off the onsets and trials holding two presses are counted."""
    from rigctl.storage.segmentation import Segmentation, press_check

    onsets = list(range(100, 4200, 100))  # 41 presses, 100 samples apart, in 4300 samples
    n = 4300
    every = [(o, o + 100) for o in onsets]
    assert press_check(onsets, every, n, pre=0, n_cycles=1) == {"presses": 41, "cut": 41, "missed": 0,
                                                                  "off_onset": 0, "wrong_count": 0, "absent": 0}
    half = every[::2]
    got = press_check(onsets, half, n, pre=0, n_cycles=1)
    assert (got["presses"], got["cut"], got["missed"]) == (41, 21, 20)
    assert Segmentation(half, list(range(len(half))), presses=got).press_problem.startswith(
        "21 of 41 presses cut as trials press by press (20 missed")
    late = [(o + 30, o + 130) for o in onsets]
    assert press_check(onsets, late, n, pre=0, n_cycles=1)["off_onset"] == 41
    double = [(o, o + 200) for o in onsets[::2]]
    got = press_check(onsets, double, n, pre=0, n_cycles=1)
    assert got["wrong_count"] == 20 and got["cut"] == 1


def _weak_every_other(seed: int, period: int = 400, n_presses: int = 41, weak: float = 0.35):
    """A press-and-slide file (100 Hz, 9 channels) whose every other press reaches only ``weak`` of the others'
    level: under half the swing, so the cut passes over them and takes two presses a trial."""
    rng = np.random.default_rng(seed)
    n = 300 + n_presses * period + 200
    x = 500 + rng.normal(0, 1.5, (n, 9))
    length, ramp = int(0.55 * period), 15
    env = np.ones(length)
    env[:ramp], env[-ramp:] = np.linspace(0, 1, ramp), np.linspace(1, 0, ramp)
    vib = 1 + 0.1 * np.sin(2 * np.pi * 12 * np.arange(length) / 100)
    for i in range(n_presses):
        o = 300 + i * period
        x[o:o + length] += (120 * (1 if i % 2 == 0 else weak) * env * vib)[:, None]
    return np.rint(x)


def test_a_file_whose_weaker_presses_are_passed_over_is_flagged_and_skip_bad_drops_it(tmp_path):
    """A file whose weaker presses fall under the cutting level was cut at twice its period, two presses a trial,
    without a word: now its row reads 'n/41 FLAGGED', a warning gives the counts, and --skip-bad leaves it out with
    the reason while a clean file beside it is imported."""
    from rigctl.simulation.press_slide import press_slide_recording

    np.save(tmp_path / "felt__R0.npy", _weak_every_other(5))
    clean, _ = press_slide_recording(4.4, 90.0, 42, nan=False, seed=6)
    np.save(tmp_path / "silk__R1.npy", clean)
    files = (tmp_path / "felt__R0.npy", tmp_path / "silk__R1.npy")
    common = ["--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles"]
    r = run_import(*files, *common, "--out", tmp_path / "a.h5")
    assert r.exit_code == 0, r.output
    rows = {line.split()[0]: line for line in r.stdout.splitlines() if line.startswith(("felt", "silk"))}
    assert rows["felt__R0.npy"].endswith("/41 FLAGGED") and "FLAGGED" not in rows["silk__R1.npy"], r.stdout
    warned = [line for line in r.stderr.splitlines() if "presses cut as trials press by press" in line]
    assert len(warned) == 1 and "felt__R0.npy: 0 of 41 presses" in warned[0] and "--skip-bad" in warned[0], r.stderr
    r = run_import(*files, *common, "--skip-bad", "--out", tmp_path / "b.h5")
    assert r.exit_code == 0 and "refused felt__R0.npy: 0 of 41 presses" in r.stderr, r.output
    with open_session(tmp_path / "b.h5") as s:
        assert {row["source_file"] for row in s.trial_table(s.completed_ids(), ["source_file"])} == {"silk__R1.npy"}


def test_the_38_generated_recordings_press_by_press():
    """The suite's 38 press-and-slide recordings (write_lab_set): 32 cut press by press right (every trial at a press
    onset of the generator's truth, every whole press a trial), none flagged, 6 refused (4 NaN, 2 flat)."""
    import tempfile

    from rigctl.simulation.press_slide import write_lab_set
    from rigctl.storage.recording_files import RecordingImportError, read_recording_file

    right = flagged = refused = 0
    with tempfile.TemporaryDirectory() as tmp:
        for path, truth in write_lab_set(tmp):
            try:
                cut = segment(read_recording_file(path, whole_counts=True)[0][0], RATE_HZ, parse_segment("cycles"))
            except RecordingImportError:
                refused += 1
                assert truth.fault in ("nan", "flat")
                continue
            if cut.press_problem:
                flagged += 1
            else:
                right += 1
                assert cut.presses["cut"] >= truth.n_cycles - 2
    assert (right, flagged, refused) == (32, 0, 6)


# ---------------------------------------------------------------------------------------------- issue 77 item 7
def _rig_file(seed: int, *, absent=(), bumps=(), period: int = 400, n_presses: int = 41):
    """A press-and-slide file (100 Hz, 9 channels) of a rig pressing every ``period`` samples: the presses in
    ``absent`` are not in the file (rest there), and the cycles in ``bumps`` hold a bump at 40 % of a press's level,
    0.72 periods after its onset (a seam brushing the sensor at rest: no press)."""
    rng = np.random.default_rng(seed)
    x = 500 + rng.normal(0, 1.5, (300 + n_presses * period + 200, 9))
    length, ramp, bump = int(0.55 * period), 15, np.hanning(int(0.15 * period))
    env = np.ones(length)
    env[:ramp], env[-ramp:] = np.linspace(0, 1, ramp), np.linspace(1, 0, ramp)
    vib = 1 + 0.1 * np.sin(2 * np.pi * 12 * np.arange(length) / 100)
    for i in range(n_presses):
        o = 300 + i * period
        if i not in absent:
            x[o:o + length] += (120 * env * vib)[:, None]
        if i in bumps:
            b = o + int(0.72 * period)
            x[b:b + bump.size] += (48 * bump)[:, None]
    return np.rint(x)


#: 20 of the rig's 41 presses not in the file; 12 cycles of a clean file with a bump
ABSENT = (1, 3, 4, 7, 9, 10, 13, 15, 17, 18, 21, 23, 25, 26, 29, 31, 33, 34, 36, 38)
BUMPS = (2, 5, 8, 11, 14, 17, 20, 23, 26, 29, 32, 35)


def test_presses_are_counted_against_the_rigs_period_when_it_is_known(tmp_path):
    """Issue 77 item 7: a file lacking 20 of the rig's 41 presses was counted against rigctl's own press finder (20
    presses found, the 20 missing never counted), and a clean file whose finder took 12 bumps for presses was
    flagged. Given the rig's period (--press-period-s, or the file's own press_period_s), the presses are the rig's:
    41, 20 of them not in the file; and the clean file's 41 of 41. Without it, the count says it is the finder's."""
    np.save(tmp_path / "felt__R0.npy", _rig_file(1, absent=ABSENT))
    clean = _rig_file(2, bumps=BUMPS)
    np.save(tmp_path / "silk__R1.npy", clean)
    np.savez(tmp_path / "cork__R2.npz", taxels=clean, press_period_s=4.0)  # the period in the file's metadata
    common = ["--rate", 100, "--label-pattern", PATTERN, "--segment", "cycles"]

    def rows(r):
        return {line.split()[0]: line for line in r.stdout.splitlines() if "__R" in line.split()[0]}

    r = run_import(tmp_path / "felt__R0.npy", tmp_path / "silk__R1.npy", *common, "--out", tmp_path / "a.h5")
    assert r.exit_code == 0, r.output
    warned = {line.split()[1].rstrip(":"): line for line in r.stderr.splitlines() if "press by press" in line}
    assert "of 20 presses cut" in warned["felt__R0.npy"], r.stderr
    assert "; counted against rigctl's press finder: give the rig's press period" in warned["felt__R0.npy"]
    assert "silk__R1.npy" in warned and "counted against rigctl's press finder" in warned["silk__R1.npy"]
    assert r.stdout.splitlines()[-2].startswith("presses cut: counted against rigctl's press finder; give the rig's")

    r = run_import(tmp_path / "felt__R0.npy", tmp_path / "silk__R1.npy", tmp_path / "cork__R2.npz", *common,
                   "--press-period-s", 4, "--out", tmp_path / "b.h5")
    assert r.exit_code == 0, r.output
    got = rows(r)
    assert got["felt__R0.npy"].endswith("/41 FLAGGED") and got["silk__R1.npy"].endswith(" 41/41"), r.stdout
    assert got["cork__R2.npz"].endswith(" 41/41")
    (line,) = [x for x in r.stderr.splitlines() if "press by press" in x]
    assert ("felt__R0.npy: 0 of 41 presses cut as trials press by press (41 missed: 20 not in the file (no press "
            "found at its time)") in line, line
    assert "the period found, 8.00 s, is not the rig's; counted against the rig's period 4.00 s (--press-period-s))" \
        in line
    assert "presses cut: counted against the rig's period 4.00 s (--press-period-s)" in r.stdout
    with open_session(tmp_path / "b.h5") as s:
        segs = {Path(x["file"]).name: x for x in json.loads(s.attrs["import_steps"])["segments"]}
    assert segs["felt__R0.npy"]["presses"]["absent"] == 20 and segs["silk__R1.npy"]["presses"]["cut"] == 41

    r = run_import(tmp_path / "cork__R2.npz", *common, "--out", tmp_path / "c.h5")  # the file's own period
    assert r.exit_code == 0 and rows(r)["cork__R2.npz"].endswith(" 41/41"), r.output
    assert "presses cut: counted against the rig's period 4.00 s (cork__R2.npz's press_period_s)" in r.stdout


def test_a_declared_press_period_is_checked():
    """A period that is not a number > 0, or one given to an import that does not cut cycles at their onsets, is
    refused in one line; a file's own period (the mapping's per-file one, else the file's) goes before the
    import's."""
    from rigctl.storage.importers import ImportOptions, _Import
    from rigctl.storage.recording_files import RecordingImportError

    for bad, spec in ((0, "cycles"), ("soon", "cycles"), (4.0, "threshold")):
        with pytest.raises(RecordingImportError, match="--press-period-s"):
            ImportOptions.resolve({"press_period_s": bad}, segment_spec=spec)
    opts = ImportOptions.resolve({"press_period_s": 4.0, "files": {"felt__R0.npy": {"press_period_s": 5.5}}},
                                 segment_spec="cycles")
    run = _Import(opts)
    assert run.rig_period(Path("felt__R0.npy"), {}) == (5.5, 'the mapping\'s [files."felt__R0.npy"]')
    assert run.rig_period(Path("silk__R1.npz"), {"press_period_s": 6.0}) == (6.0, "silk__R1.npz's press_period_s")
    assert run.rig_period(Path("cork__R2.npy"), {}) == (4.0, "--press-period-s")
    assert _Import(ImportOptions.resolve({}, segment_spec="cycles")).rig_period(Path("x.npz"), {})[0] is None
    with pytest.raises(RecordingImportError, match="x.npz: press_period_s -1"):
        run.rig_period(Path("x.npz"), {"press_period_s": -1.0})
