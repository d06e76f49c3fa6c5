"""Progress as typed events (rigctl.core.progress): each long function of the library reports its stages to a
``progress`` callback, in order, done counts rising from 0 to the total; the CLI draws them with tqdm (the only
place tqdm is used); the GUI reads no text (no regular expression over tqdm's output is left)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from rigctl.core.progress import ProgressEvent, Stage, as_callback

PROTOCOL = """
name = "progress"
textures = ["A", "L"]
speeds_mm_s = [80]
forces_g = [500]
trials_per_condition = 3
duration_s = 0.3
"""


def done_counts(events, stage):
    return [e.done for e in events if e.stage == stage and e.total is not None]


def test_events_are_frozen_and_a_stage_counts_up():
    events = []
    bar = Stage(events.append, "work", 3, unit="file")
    bar.advance(1)
    bar.note("half way")
    bar.advance(2, "last two")
    assert done_counts(events, "work") == [0, 1, 3]
    assert events[2] == ProgressEvent("work", 1, None, "half way", "file")
    assert [e.fraction for e in events] == [0.0, pytest.approx(1 / 3), None, 1.0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        events[0].done = 2
    assert as_callback(None)(events[0]) is None and as_callback(False)(events[0]) is None
    with pytest.raises(TypeError, match="callable"):
        as_callback(True)


def test_the_cli_adapter_draws_one_tqdm_bar_per_stage(capsys):
    from rigctl.cli.progress import TqdmProgress, bars

    with TqdmProgress() as bar:
        Stage(bar, "range pass", 2).advance(2)
        bar(ProgressEvent("force fit", 0, None, "fitting force coefficients"))
        Stage(bar, "encoding", 4).advance(4)
    err = capsys.readouterr().err
    assert "range pass" in err and "2/2" in err and "encoding" in err and "4/4" in err
    assert "fitting force coefficients" in err
    with bars(False) as none:
        assert none is None


def test_dataset_encoding_import_and_analyses_report_their_stages(tmp_path):
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.analysis.synthetic import synthetic_features
    from rigctl.analysis.tasks import run_cv, run_extrapolation
    from rigctl.encoding.pipeline import encode_session
    from rigctl.simulation.dataset import generate_dataset
    from rigctl.storage.importers import import_recordings

    events: list[ProgressEvent] = []
    session = tmp_path / "s.h5"
    generate_dataset(parse_protocol(PROTOCOL), session, workers=0, progress=events.append)
    assert done_counts(events, "dataset s.h5") == [0, 1, 2, 3, 4, 5, 6]

    events.clear()
    encode_session(session, tmp_path / "e.h5", variants=["original"], store_spikes=(), batch_trials=4,
                   progress=events.append)
    assert done_counts(events, "reading trials") == [0, 4, 6]  # read in blocks of batch_trials
    assert done_counts(events, "encoding") == [0, 4, 6]  # batches of 4 trials
    assert [e.stage for e in events if e.total is not None] == ["reading trials"] * 3 + ["encoding"] * 3  # in order

    events.clear()
    files = []
    for i, label in enumerate(["AA", "BB", "CC"]):
        files.append(tmp_path / f"{label}_{i}.npy")
        np.save(files[-1], np.random.default_rng(i).integers(0, 1023, (200, 4)).astype(np.uint16))
    import_recordings(files, tmp_path / "imp.h5", rate_hz=1000, label_pattern="{texture}_{repeat}.npy",
                      progress=events.append)
    assert done_counts(events, "reading recordings") == [0, 1, 2, 3]
    assert done_counts(events, "writing trials") == [0, 1, 2, 3]

    fs = synthetic_features(4, n_textures=3, n_channels=2, speeds=(40.0, 80.0), forces=(250.0, 500.0), seed=1)
    events.clear()
    with pytest.warns(UserWarning):
        run_cv(fs, ("textures",), variants=["original"], n_pcs=3, repeats=2, per_texture=8, k=2,
               progress=events.append)
        run_extrapolation(fs, train_speeds=(40,), train_forces=(500,), variants=["original", "speed_scaled"], n_pcs=3,
                          repeats=2, progress=events.append)
    # PCA fits, counted per finished repetition (repetitions run side by side)
    assert done_counts(events, "textures/groups") == [0, 2, 4]  # 2 repeats x (2 folds x 1 variant)
    assert done_counts(events, "extrapolation") == [0, 2, 4]  # 2 repeats x (1 split x 2 variants)
    assert {e.unit for e in events} == {"fit"}


def test_no_text_parsing_of_progress_is_left():
    """The GUI's worker reads events, not tqdm's text: no regular expression, no stderr capture."""
    import rigctl_gui.workers as workers

    source = Path(workers.__file__).read_text()
    assert "re.compile" not in source and "_QueueText" not in source and "sys.stderr" not in source
    root = Path(__file__).resolve().parents[2] / "rigctl"
    users = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                   if "from tqdm" in p.read_text() or "import tqdm" in p.read_text())
    assert users == ["cli/progress.py"]  # tqdm only in the CLI's adapter
