"""The guides are tests: every fenced ``sh`` block of README.md, docs/my-sensor.md and docs/guides/*.md (and the
``python`` blocks and named files they build on) runs as written, in order, in one shell per page in an empty folder
(tests/guides.py), at the small sizes the pages' own markers give; a block that fails or prints a traceback fails
its page's test. What does not run here is marked in the page and listed below, each with its reason. Each page is
a unit of its own for the parallel run (tests/conftest.py: SPLIT_BY_PARAM)."""

from __future__ import annotations

import re
import shlex
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from rigctl.cli import main

from .conftest import require_lsl
from .guides import PAGES, REPO, BlockRun, blocks, run_page

#: every block not run by its page's test: (page, first words) -> marker; a new one must be added here on purpose
NOT_RUN = {
    ("README.md", "bash scripts/test.sh"): "not-run",
    ("README.md", "rigctl sim"): "not-run",
    ("README.md", "python3 -m venv"): "run-by",
    ("docs/guides/first-recording.md", "python3 -m venv"): "run-by",
    ("docs/guides/labrecorder.md", "pip install 'rigctl[lsl]'"): "not-run",
    ("docs/guides/labrecorder.md", "import pyxdf"): "not-run",
    ("docs/guides/labrecorder.md", "rigctl import room.xdf"): "not-run",
    ("docs/guides/real-rig.md", "sudo apt install"): "not-run",
    ("docs/guides/real-rig.md", "avrdude -p m328p"): "not-run",
    ("docs/guides/real-rig.md", "rigctl udev-rules"): "not-run",
    ("docs/guides/real-rig.md", "rigctl gui --drum-port"): "not-run",
    ("docs/guides/real-rig.md", "rigctl acquire quick_check --drum-port"): "not-run",
    ("docs/my-sensor.md", "rigctl sim --replay"): "not-run",
    # "Other people's files": tests/storage/test_storage_import_numbers.py runs the section's two blocks
    ("docs/my-sensor.md", "import numpy as np\nfrom datetime import datetime"): "run-by",
    ("docs/my-sensor.md", "if ! rigctl import logger__felt.csv"): "run-by",
    ("docs/guides/spiking-networks.md", "pip install tonic snntorch"): "not-run",
    ("docs/guides/spiking-networks.md", "# rigctl_tonic.py"): "run-by",
    ("docs/guides/spiking-networks.md", "# tonic_frames.py"): "run-by",
    ("docs/guides/spiking-networks.md", "python tonic_frames.py"): "run-by",
    ("docs/guides/spiking-networks.md", "# snntorch_windows.py"): "run-by",
    ("docs/guides/spiking-networks.md", "python snntorch_windows.py"): "run-by",
    ("docs/guides/spiking-networks.md", "# spikingjelly_frames.py"): "run-by",
    ("docs/guides/spiking-networks.md", "python spikingjelly_frames.py"): "run-by",
    ("docs/guides/spiking-networks.md", "pip install 'rigctl[nir]'"): "not-run",
    ("docs/guides/my-hardware.md", "rigctl acquire quick_check --rig csvboard --rig-option port=/dev/ttyUSB0"):
        "not-run",
}


def _words(text: str) -> set[str]:
    return set(re.findall(r"[A-Za-z][\w-]*", text))


def test_every_block_runs_or_says_why():
    """Markers are sound: every block that does not run says why (and is listed in :data:`NOT_RUN`), a ``run-by``
    names a test that exists, a ``small`` marker's old text is in its block and its new words are in the page; and
    every page has its test below."""
    assert set(PAGES) == {page for page, _ in GUIDES.values()}
    skipped = {}
    for page in PAGES:
        prose = re.sub(r"<!--.*?-->", "", (REPO / page).read_text())
        for b in blocks(page):
            if b.lang not in ("sh", "python") and b.file_name is None:
                continue
            kind = next((k for k in ("not-run", "run-by") if k in b.markers), None)
            if kind:
                assert b.markers[kind], f"{b.name}: a {kind} marker needs its reason or test"
                key = next((k for k in NOT_RUN if k[0] == page and b.text.startswith(k[1])), None)
                assert key is not None, f"{b.name} is not run: list it in NOT_RUN ({b.text[:40]!r})"
                skipped[key] = kind
            if kind == "run-by":
                path, _, name = b.markers["run-by"].partition("::")
                assert f"def {name}(" in (REPO / path).read_text(), f"{b.name}: no test {b.markers['run-by']}"
            for old, new in b.substitutions():
                assert old in b.text, f"{b.name}: the small marker's {old!r} is not in the block"
                missing = _words(new) - _words(old) - _words(prose)
                assert not missing, f"{b.name}: the page does not offer {sorted(missing)} (small marker)"
    assert skipped == NOT_RUN
    print("\n".join(f"{kind:8} {page}: {first}" for (page, first), kind in NOT_RUN.items()))


# ----------------------------------------------------------------------------------------- what each page shows
def _first_recording(runs: list[BlockRun], tmp_path, request) -> None:
    assert "trials complete: 6/6" in runs[0].output
    assert "Individual Textures" in runs[-1].output


def _readme(runs, tmp_path, request) -> None:
    assert (tmp_path / "work" / "quick.h5").is_file()


def _paper(runs, tmp_path, request) -> None:
    assert (tmp_path / "work" / "fig3.png").is_file()
    assert "untrained" in runs[-1].output.lower()


def _real_rig(runs, tmp_path, request) -> None:
    assert "mega_drum.hex" in runs[0].output


def _my_sensor(runs, tmp_path, request) -> None:
    section5 = next(r for r in runs if "write_press_slide_set" in r.block.text)
    out = section5.output
    assert "file" in out and "period" in out and out.count(".npy") >= 6
    assert "cork__R5.npy: trial count 8 is an outlier" in out
    assert "from felt__R0.npy samples" in out
    # the page's claim: the recording-grouped folds score far below the random ones on these files
    grouped = section5.block.text.strip().splitlines()[-1]
    assert grouped.startswith("rigctl analyze") and grouped.endswith("--cv-groups recording")
    monkeypatch = request.getfixturevalue("monkeypatch")
    monkeypatch.chdir(tmp_path / "work")
    random = CliRunner().invoke(main, shlex.split(grouped)[1:-2])
    assert random.exit_code == 0, random.output

    def textures_row(text):
        row = next(line for line in text.splitlines() if line.startswith("Individual Textures"))
        return float(row.split()[4])  # Original, mu (%)

    assert textures_row(out) < textures_row(random.stdout) - 20


def _my_hardware(runs, tmp_path, request) -> None:
    """The plugin installed, listed beside rigctl's own rigs, and recording quick_check from a pty and a file."""
    listed = next(r for r in runs if "rigctl rigs" in r.block.text).output
    assert "csvboard" in listed and "rigctl-csvboard 0.1.0" in listed and "sim" in listed, listed
    bench = next(r for r in runs if "bench.h5" in r.block.text).output
    assert "6 trials, 2400 samples of 4 taxels" in bench, bench
    assert "trials complete: 6/6" in runs[-1].output or "6/6" in runs[-1].output, runs[-1].output


def _handheld(runs, tmp_path, request) -> None:
    """The finger's taxel board beside a tracker stream: the scan recorded, the sensor from the board's banner; the
    same scan encoded on the board under simavr and classified."""
    board = next(r for r in runs if "--taxel-port" in r.block.text).output
    assert "trials complete: 1/1" in board and "sensor 3x3x1: 9 channels" in board, board
    onboard = next(r for r in runs if "--onboard-encoder" in r.block.text).output
    assert "predicted: " in onboard and "totals: 1/1 trials complete, 1 encoded on the board, 0 failed" in onboard, \
        onboard
    # issue 79 item 7: the scans' lengths are the operator's speed: no warning advises cutting them to the shortest
    advice = [r.block.name for r in runs if "--crop-s" in r.output or "differ by texture" in r.output]
    assert not advice, advice


def _spiking_networks(runs, tmp_path, request) -> None:
    """Events exported with the paper's splits, a rate-coded classifier above chance on untrained speed, and the
    per-trial layout imported back."""
    import json

    work = tmp_path / "work"
    splits = json.loads((work / "events" / "splits.json").read_text())
    assert {"cv", "untrained_speed", "trained"} <= set(splits["tasks"])
    out = next(r for r in runs if "train_rate_code.py" in r.block.text and r.block.lang == "sh").output
    accuracy = {line.split(":")[0]: float(line.split(": ")[1].split("%")[0]) for line in out.splitlines()
                if line.startswith(("trained:", "untrained_speed:"))}
    assert set(accuracy) == {"trained", "untrained_speed"}, out
    assert accuracy["trained"] > 3 * 100 / 16, out  # the trained cells' held-out trials: far above chance (16)
    assert (work / "back.enc.h5").is_file()
    nir = next(r for r in runs if "readout_on_nir.py" in r.block.text and r.block.lang == "sh").output
    assert "same decision as rigctl on 100% of 256 trials" in nir, nir  # issue 79 item 4: the NIR readout


def _nothing(runs, tmp_path, request) -> None:
    pass


#: test id -> (page, what its run must show)
GUIDES: dict[str, tuple[str, Callable]] = {
    "readme": ("README.md", _readme),
    "firstrecording": ("docs/guides/first-recording.md", _first_recording),
    "mysensor": ("docs/my-sensor.md", _my_sensor),
    "paper": ("docs/guides/reproducing-the-paper.md", _paper),
    "labrecorder": ("docs/guides/labrecorder.md", _nothing),
    "realrig": ("docs/guides/real-rig.md", _real_rig),
    "handheld": ("docs/guides/handheld.md", _handheld),
    "config": ("docs/config.md", _nothing),
    "myhardware": ("docs/guides/my-hardware.md", _my_hardware),
    "spikingnetworks": ("docs/guides/spiking-networks.md", _spiking_networks),
}


def test_the_config_reference_lists_every_rig_config_key():
    """docs/config.md's table names every key of the rig config's schema, and nothing else."""
    from rigctl.acquisition.rigconfig import SCHEMA

    text = (REPO / "docs" / "config.md").read_text()
    table = text.split("## The rig config", 1)[1].split("\n## ", 1)[0]
    named = {m for row in table.splitlines() if row.startswith("| `")
             for m in re.findall(r"`(\w+(?:\.\w+)?)`", row.split("|")[1])}
    schema = {f"{block}.{key}" for block, keys in SCHEMA.items() if block != "taxel_normalisation_previous"
              for key in keys} | {"taxel_normalisation_previous"}
    assert named == schema


@pytest.mark.slow
# wall: pages that stream LSL (lab recorder, handheld) and drive `rigctl sim` processes (always paced)
@pytest.mark.realtime
@pytest.mark.timeout(900)
@pytest.mark.parametrize("guide", list(GUIDES))
def test_guide_runs_as_written(guide, tmp_path, request):
    page, check = GUIDES[guide]
    if guide == "paper":  # ../shared/data/fabricslide, as beside a checkout
        (tmp_path / "shared" / "data").mkdir(parents=True)
        (tmp_path / "shared" / "data" / "fabricslide").symlink_to(request.getfixturevalue("fabricslide_dir"))
    if guide in ("labrecorder", "handheld"):  # the handheld page's tracker stream
        require_lsl()
    if guide == "realrig":
        request.getfixturevalue("build_tools")
    # a page's rigctl commands run through this worker's preloaded rigctl (started once for the worker's tests)
    runs = run_page(page, tmp_path / "work", client=lambda: Path(request.getfixturevalue("rigctl_cmd")[-1]))
    print("\n".join(f"{r.seconds:6.1f} s  {r.block.name}" for r in runs))
    check(runs, tmp_path, request)


def test_no_guide_builds_with_the_environments_own_build_tools():
    """A guide's ``pip install`` builds in pip's isolated environment (issue 79 item 1: the my-hardware guide's
    ``--no-build-isolation`` needed the test environment's setuptools >= 70.1 and wheel; the README's environment has
    setuptools 65.5 on Python 3.11 and none on 3.12, so every later step of the guide failed there). The guides' own
    test builds that way too, its build tools from scripts/test.sh's wheelhouse (tests/guides.py guide_env)."""
    uses = [f"{b.page}:{b.line}" for page, _ in GUIDES.values() for b in blocks(page)
            if b.lang == "sh" and "pip" in b.text and "--no-build-isolation" in b.text]
    assert not uses, uses
