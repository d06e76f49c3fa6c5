"""Trials encoded on the finger's board (the handheld rig's ``--onboard-encoder``): the writer stores the board's record
(spikes per taxel, counts frame, applied speeds, flags) instead of raw taxels and marks the trial; the reader gives it
back; the one validator measures such a trial by the samples the board encoded, and only such a trial: 0 frames
without the mark, a mark with a broken record, or a record whose length contradicts the plan stay excluded."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from rigctl.core.onboard import OnboardEncoding
from rigctl.core.sensor import PAPER_FINGER
from rigctl.core.trial import PlannedTrial, TrialData
from rigctl.storage.session import SessionWriter, open_session
from rigctl.storage.validate import usable_trials

N = 2500  # samples the board encoded (the plan: 2.5 s at 1 kHz)


def _onboard(rng: np.random.Generator, samples: int = N) -> OnboardEncoding:
    raster = (rng.random((samples, 9)) < 0.01).astype(np.uint8)
    return OnboardEncoding.from_raster(raster, counts=rng.integers(0, 30, (9, 20)), speeds_mm_s=rng.uniform(40, 120, 25),
                                       held_windows=[3], dropped_samples=0, queue_max=4)


def _write(path, encs: list[OnboardEncoding | None]) -> None:
    rng = np.random.default_rng(2)
    plan = [PlannedTrial(i, "BL"[i % 2], 80.0, 500.0, N / 1000.0, "fast") for i in range(len(encs))]
    with SessionWriter.create(path, plan=plan, layout=PAPER_FINGER, protocol_source="x", durable=False) as w:
        for i, e in enumerate(encs):
            taxels = np.zeros((0, 9), np.uint16) if e is not None else rng.integers(0, 1000, (N, 9))
            w.write_trial(i, TrialData(taxels=taxels, layout=PAPER_FINGER, speed_mm_s=np.full(4, 80.0),
                                       speed_time_s=np.arange(4) * 0.1, onboard=e))


def test_a_trial_encoded_on_the_board_is_stored_read_and_usable(tmp_path):
    rng = np.random.default_rng(1)
    encs = [_onboard(rng), None, _onboard(rng, N - 300)]
    _write(tmp_path / "s.h5", encs)
    with open_session(tmp_path / "s.h5") as s:
        report = usable_trials(s)
        assert report.ids == [0, 1, 2] and not report.excluded
        for tid, e in enumerate(encs):
            d = s.trial(tid)
            if e is None:
                assert d.onboard is None and d.n_samples == N and "encoded_on_board" not in d.attrs
                continue
            o = d.onboard
            assert o is not None and d.n_samples == 0 and d.attrs["encoded_on_board"]
            for name in ("spike_sample", "spike_taxel", "counts", "speeds_mm_s", "held_windows"):
                assert np.array_equal(getattr(o, name), getattr(e, name)), name
            assert (o.samples, o.dropped_samples, o.queue_max) == (e.samples, 0, 4)
            assert np.array_equal(o.spike_times_s(4), e.spike_sample[e.spike_taxel == 4] / 1000.0)


def _unmark(f: h5py.File) -> None:
    del f["trials/000000"].attrs["encoded_on_board"]


def _no_counts(f: h5py.File) -> None:
    del f["trials/000000/onboard/counts"]


def _float_counts(f: h5py.File) -> None:
    g = f["trials/000000/onboard"]
    c = g["counts"][()]
    del g["counts"]
    g["counts"] = c.astype(np.float32)


def _too_short(f: h5py.File) -> None:
    f["trials/000000/onboard"].attrs["samples"] = 100  # the plan asks 2,500


@pytest.mark.parametrize(("damage", "reason"), [
    (_unmark, "it holds 0 samples (0 missing), its plan asks 2.5 s = 2500 at 1000 Hz"),
    (_no_counts, "it is marked encoded on the board but its onboard record is unreadable"),
    (_float_counts, "it is marked encoded on the board but its onboard record is not the documented one"),
    (_too_short, "it holds 100 samples (0 missing), its plan asks 2.5 s = 2500 at 1000 Hz"),
])
def test_only_a_whole_marked_record_of_the_plans_length_stands_for_taxels(tmp_path, damage, reason):
    _write(tmp_path / "s.h5", [_onboard(np.random.default_rng(3)), _onboard(np.random.default_rng(4))])
    with h5py.File(tmp_path / "s.h5", "r+") as f:
        damage(f)
    with open_session(tmp_path / "s.h5") as s:
        report = usable_trials(s)
    assert report.ids == [1]
    assert report.excluded[0].startswith(reason), report.excluded[0]


def test_nwb_export_refuses_trials_without_taxel_frames_in_one_line(tmp_path):
    pytest.importorskip("pynwb")
    from rigctl.storage.nwb import NwbExportError, export_nwb

    _write(tmp_path / "s.h5", [_onboard(np.random.default_rng(5)), None])
    with pytest.raises(NwbExportError, match=r"trials \[0\] hold no taxel frames \(encoded on the board"):
        export_nwb(tmp_path / "s.h5", tmp_path / "s.nwb")
    assert not (tmp_path / "s.nwb").exists()


def test_info_names_the_trials_encoded_on_the_board_and_their_samples(tmp_path):
    """`rigctl info` (issue 37's follow-up): a scan the board encoded is complete with the samples the board
    encoded (not 0) and says it was encoded on the board; the totals count such trials."""
    from click.testing import CliRunner

    from rigctl.cli import main
    from rigctl.cli.info import session_summary

    rng = np.random.default_rng(4)
    _write(tmp_path / "s.h5", [_onboard(rng), None, _onboard(rng, N - 300)])
    summary = session_summary(tmp_path / "s.h5")
    rows = summary["trials"]
    assert [t["encoded_on_board"] for t in rows] == [True, False, True]
    assert [t["samples"] for t in rows] == [N, N, N - 300]
    assert summary["totals"]["encoded_on_board"] == 2 and summary["totals"]["complete"] == 3
    out = CliRunner().invoke(main, ["info", str(tmp_path / "s.h5")])
    assert out.exit_code == 0, out.output
    lines = [line for line in out.output.splitlines() if line.strip().split(" ", 1)[0] in ("0", "1", "2")]
    assert ["encoded on the board" in line for line in lines] == [True, False, True]
    assert "2 encoded on the board" in out.output
