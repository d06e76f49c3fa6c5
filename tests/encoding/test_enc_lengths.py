"""A label hidden in the trial length (issue 52 item 4): encode and analyze warn when trial durations differ by texture
and give the crop, but not for a handheld session's scans, whose length is the operator's speed (issue 79 item 7);
``encode --crop-s`` cuts every trial to a common length (a trial shorter than it refused, named); analyze names the
textures and cells that set its sample size."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.encoding.lengths import length_imbalance
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import SessionWriter, TrialData


def _session(path, lengths: dict[str, tuple[int, int]], attrs: dict | None = None):
    """Trials of each texture: (count, samples at 1 kHz); ``attrs``: every trial's extra attributes."""
    rng = np.random.default_rng(0)
    plan, data = [], []
    for tex, (n, samples) in lengths.items():
        for _ in range(n):
            plan.append(dict(trial_id=len(plan), texture=tex, speed_mm_s=40.0, force_g=500.0,
                             duration_s=samples / 1000))
            data.append(rng.integers(300, 700, (samples, 18)))
    with SessionWriter.create(path, plan=plan, protocol_source="name = 't'") as w:
        for i, x in enumerate(data):
            w.write_trial(i, TrialData(taxels=x, seq=np.arange(len(x)), force_g=[500.0], force_time_s=[0.0],
                                       speed_mm_s=[40.0], speed_time_s=[0.0], attrs=dict(attrs or {})))
    return path


def _run(*args):
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return r.exit_code, r.stdout + r.stderr


def test_length_imbalance_by_texture():
    tex = np.array(["A"] * 4 + ["B"] * 4)
    assert length_imbalance(tex, np.r_[[6.0] * 4, [8.0] * 4]).startswith("trial durations differ by texture "
                                                                         "(median: A 6.00 s, B 8.00 s)")
    assert "--crop-s 6" in length_imbalance(tex, np.r_[[6.0] * 4, [8.0] * 4])
    assert length_imbalance(tex, np.r_[[8.0] * 4, [7.9] * 4]) is None  # within 5 %


def test_durations_are_compared_at_the_same_speed_and_force():
    """FabricSlide's case (issue 77 item 7): durations differ by texture only through the mix of conditions each
    was recorded at (A mostly slow and long, B mostly fast and short): nothing to say, where the pooled medians
    warned and advised a crop that flipped the paper's result. A real difference within one condition is named
    with that condition, and the crop is never advised without its cost."""
    tex = np.array(["A"] * 4 + ["B"] * 4)
    speed = np.r_[[40.0] * 3, [120.0], [40.0], [120.0] * 3]
    dur = np.where(speed == 40.0, 9.0, 3.0)  # the duration is the speed's, not the texture's
    force = np.full(8, 500.0)
    assert length_imbalance(tex, dur) is not None  # pooled: A 9 s, B 3 s
    assert length_imbalance(tex, dur, speed_mm_s=speed, force_g=force) is None
    dur2 = dur.copy()
    dur2[(tex == "B") & (speed == 120.0)] = 2.0
    line = length_imbalance(tex, dur2, speed_mm_s=speed, force_g=force)
    assert line is not None and "(median: B 2.00 s, A 3.00 s) at the same speed and force (120 mm/s, 500 g)" in line
    assert "--crop-s 2 cuts every trial" in line and "compare the analysis with and without the crop" in line


def test_encode_warns_and_crops_and_analyze_names_what_sets_the_sample_size(tmp_path):
    session = _session(tmp_path / "s.h5", {"A": (6, 600), "B": (10, 800)})
    rc, out = _run("encode", session, "--out", tmp_path / "e.h5", "--no-progress", "--variant", "original")
    assert rc == 0, out
    assert "trial durations differ by texture (median: A 0.60 s, B 0.80 s)" in out and "--crop-s 0.6" in out, out
    rc, out = _run("analyze", tmp_path / "e.h5", "--task", "textures", "--repeats", 1, "--pcs", "1-2",
                   "--no-progress")
    assert rc == 0, out
    assert "trial durations differ by texture" in out, out
    # every trial used, each texture weighted equally (issue 77 item 7; the smallest count was drawn from each)
    assert "the textures hold 6-10 trials (fewest: A (6)); using every trial up to --per-texture 500" in out, out
    rc, out = _run("encode", session, "--out", tmp_path / "c.h5", "--no-progress", "--variant", "original",
                   "--crop-s", 0.6)
    assert rc == 0 and "differ by texture" not in out, out
    with open_encoded(tmp_path / "c.h5") as f:
        assert set(f.trials["n_samples"].tolist()) == {600}
        assert f.parameters["crop_s"] == 0.6
    rc, out = _run("analyze", tmp_path / "c.h5", "--task", "textures", "--repeats", 1, "--pcs", "1-2",
                   "--no-progress")
    assert rc == 0 and "differ by texture" not in out, out
    rc, out = _run("encode", session, "--out", tmp_path / "x.h5", "--no-progress", "--crop-s", 0.7)
    assert rc == 1 and "--crop-s 0.7: trials 0, 1, 2, 3, 4, 5 are shorter" in out and "Traceback" not in out, out
    assert not (tmp_path / "x.h5").exists()


def test_handheld_scans_are_compared_like_with_like():
    """Issue 79 item 7: the handheld guide's calibration block (one scan per texture per cue, lengths 1.42-1.96 s at
    the fast cue: the operator's speed) was told to `--crop-s 1.42`, which cuts a slow scan's plate short. A scan's
    length is the operator's speed over the same stretch of plate: with one scan a texture there is nothing to
    compare with (nothing said), with scans enough the textures must differ beyond their own spread, and the line
    names the operator's speed, never a crop. Profiles of one cue speed (a ramp and a constant scan, both 80 mm/s)
    are no texture's."""
    tex = np.array(list("ABDLN"))
    fast = np.array([1.96, 1.58, 1.42, 1.57, 1.54])  # the guide's cal.h5 at 120 mm/s
    speed, force = np.full(5, 120.0), np.full(5, 500.0)
    assert "--crop-s 1.42" in length_imbalance(tex, fast, speed_mm_s=speed, force_g=force)  # the drum's reading
    assert length_imbalance(tex, fast, speed_mm_s=speed, force_g=force, operator_paced=True) is None
    rng = np.random.default_rng(3)
    tex3 = np.repeat(list("ABDLN"), 3)
    chance = 1.67 / rng.uniform(0.8, 1.2, tex3.size)  # the operator's speed, whatever the texture
    assert length_imbalance(tex3, chance, speed_mm_s=np.full(15, 120.0), force_g=np.full(15, 500.0),
                            operator_paced=True) is None
    slow_on_a = np.where(tex3 == "A", 2.6, 1.6) + rng.uniform(-0.05, 0.05, tex3.size)
    line = length_imbalance(tex3, slow_on_a, speed_mm_s=np.full(15, 120.0), force_g=np.full(15, 500.0),
                            operator_paced=True)
    assert line is not None and line.startswith("scan durations differ by texture") and "A 2.6" in line, line
    assert "operator scanned these textures at different speeds" in line and "--crop-s" not in line, line
    # one cue speed, two profiles (A twice each, B once medium and three times ramped): the ramps are longer
    tex4 = np.repeat(list("AB"), 4)
    profile = np.array(["medium", "medium", "slow-to-fast", "slow-to-fast", "medium"] + ["slow-to-fast"] * 3)
    dur = np.where(profile == "medium", 2.5, 3.3)
    s80, f500 = np.full(8, 80.0), np.full(8, 500.0)
    assert length_imbalance(tex4, dur, speed_mm_s=s80, force_g=f500) is not None  # profiles pooled: B longer
    assert length_imbalance(tex4, dur, speed_mm_s=s80, force_g=f500, profile=profile) is None


def test_encode_and_analyze_of_handheld_scans_say_nothing_of_the_operators_lengths(tmp_path):
    """The same sessions encoded: scans bounded by positions on the plate (a handheld session's, `boundary =
    "position"`) of one per texture get no warning from encode or analyze (the encoded file says `operator_paced`);
    the same lengths from the drum's protocol still do."""
    lengths = {"A": (1, 1960), "B": (1, 1580), "D": (1, 1420)}
    paced = _session(tmp_path / "hand.h5", lengths, attrs={"boundary": "position"})
    rc, out = _run("encode", paced, "--out", tmp_path / "hand.enc.h5", "--no-progress", "--variant", "original")
    assert rc == 0 and "differ by texture" not in out and "--crop-s" not in out, out
    with open_encoded(tmp_path / "hand.enc.h5") as f:
        assert f.attrs["operator_paced"] is True or f.attrs["operator_paced"] == 1
    rc, out = _run("analyze", tmp_path / "hand.enc.h5", "--task", "textures", "--repeats", 1, "--pcs", "1-2",
                   "--no-progress")
    assert "differ by texture" not in out and "--crop-s" not in out, out
    drum = _session(tmp_path / "drum.h5", lengths)
    rc, out = _run("encode", drum, "--out", tmp_path / "drum.enc.h5", "--no-progress", "--variant", "original")
    assert rc == 0 and "--crop-s 1.42" in out, out
    with open_encoded(tmp_path / "drum.enc.h5") as f:
        assert not f.attrs["operator_paced"]
