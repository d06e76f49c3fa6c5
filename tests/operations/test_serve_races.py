"""``rigctl serve``'s runs write only inside the data folder, whatever happens to it by name while they run (issue 77
item 3): each run opens its subfolder once, without following links, and writes every file through that descriptor
(:func:`rigctl.storage.outputs.opened_in_folder`). A subfolder flipped to a symlink out of the data folder and back,
100 times and more while runs start and record, sends nothing outside (before: 1 of 5 sessions, checked by name and
then opened by name); a link at a run's sidecar is refused, what it points to unchanged. The in-process rig, the
queue itself (no HTTP: the path handling is the queue's)."""

from __future__ import annotations

import hashlib
import os
import threading
import time
from pathlib import Path

import pytest

from rigctl.operations import RigSource, RunQueue, open_control

from ..conftest import wait_for

PROTOCOL = ('name = "races"\ntextures = ["A", "L"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
            'trials_per_condition = 1\nduration_s = 0.2\n[settle]\nsettle_time_ms = 20\n')
ENDED = ("done", "failed", "stopped")
#: flips of the subfolder at least (the flipper goes on until every run has ended)
MIN_FLIPS = 100


@pytest.fixture
def rig(tmp_path):
    control = open_control(RigSource("inprocess"), seed=3, host_config_path=tmp_path / "rig.json")
    try:
        yield control
    finally:
        control.close()


def _files(root: Path) -> dict[str, Path]:
    """Every file under ``root`` by name (links not followed)."""
    return {f: Path(d) / f for d, _, fs in os.walk(root) for f in fs}


def _flip(data: Path, outside: Path, stop: threading.Event, flips: list[int]) -> None:
    """Swap ``data/mouse1`` for a symlink to ``outside`` and back until ``stop`` is set and MIN_FLIPS are done."""
    sub, aside, i = data / "mouse1", data / "mouse1.real", 0
    while not (stop.is_set() and i >= MIN_FLIPS):
        try:
            os.rename(sub, aside)
        except OSError:
            time.sleep(0.001)
            continue
        try:
            os.symlink(outside, sub, target_is_directory=True)
            time.sleep(0.002 + 0.003 * (i % 3))
            os.unlink(sub)
        except FileExistsError:  # a run starting in the gap made a new mouse1: it stays (inside the data folder)
            aside.rename(data / f"mouse1.kept{i}")
            i += 1
            continue
        os.rename(aside, sub)
        # longer than the link's: most runs start, the others are refused (8-12 ms: a CI run beside two busy loops had
        # all six refused, the scheduler's lateness stretching the link's window as much as this one)
        time.sleep(0.02 + 0.004 * (i % 2))
        i += 1
    flips.append(i)


def test_a_subfolder_flipped_to_a_link_while_runs_start_sends_nothing_outside(rig, tmp_path):
    data, outside = tmp_path / "data", tmp_path / "outside"
    (data / "mouse1").mkdir(parents=True)
    outside.mkdir()
    q = RunQueue(rig, tmp_path / "queue.json", data_dir=data)
    runs = [q.submit(f"mouse1/s{i}.h5", toml=PROTOCOL) for i in range(6)]
    stop, flips = threading.Event(), []
    flipper = threading.Thread(target=_flip, args=(data, outside, stop, flips), daemon=True)
    try:
        flipper.start()
        q.start()
        wait_for(lambda: all(q.get(r.id).state in ENDED for r in runs), timeout_s=600)
    finally:
        stop.set()
        flipper.join(120)
        q.close()
    assert flips and flips[0] >= MIN_FLIPS, flips
    assert _files(outside) == {}, sorted(_files(outside))  # nothing ever written through the link
    inside = _files(data)
    done = [q.get(r.id) for r in runs if q.get(r.id).state == "done"]
    for r in runs:
        run = q.get(r.id)
        name = Path(run.out).name
        if run.state == "done":
            assert name in inside and run.trials_done == 2, (run.state, run.errors, sorted(inside))
        else:  # refused as it started (the subfolder was a link then), or its folder was removed under it (an
            # empty folder it had just made, replaced by the flipper's rename): failed in one line, nothing elsewhere
            assert run.state == "failed" and len(run.errors) == 1 and "\n" not in run.errors[0], run.errors
            assert "/proc/" not in run.errors[0], run.errors
    assert done, [q.get(r.id).errors for r in runs]  # the race was run, not only refused
    for run in done:
        assert "/proc/" not in " ".join(run.summary), run.summary  # messages name the file by its name


@pytest.mark.parametrize("sidecar", [".lock", ".creating"])
def test_a_link_at_a_runs_sidecar_is_refused_and_its_target_kept(rig, tmp_path, sidecar):
    data, outside = tmp_path / "data", tmp_path / "outside"
    (data / "mouse1").mkdir(parents=True)
    outside.mkdir()
    precious = outside / "precious.h5"
    precious.write_bytes(b"another lab's session" * 100)
    digest = hashlib.sha256(precious.read_bytes()).hexdigest()
    q = RunQueue(rig, tmp_path / "queue.json", data_dir=data)
    try:
        run = q.submit("mouse1/s1.h5", toml=PROTOCOL)  # (a link there now is refused at once: 422)
        (data / "mouse1" / ("s1.h5" + sidecar)).symlink_to(precious)  # planted while the run waits
        q.start()
        ended = wait_for(lambda: q.get(run.id).state in ENDED and q.get(run.id), timeout_s=300)
    finally:
        q.close()
    assert ended.state == "failed" and "left as it is" in ended.errors[-1], ended.errors
    assert hashlib.sha256(precious.read_bytes()).hexdigest() == digest
    assert (data / "mouse1" / ("s1.h5" + sidecar)).is_symlink() and not (data / "mouse1" / "s1.h5").exists()
