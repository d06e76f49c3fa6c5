"""The guides are tests: every fenced ``sh`` block of README.md, docs/my-sensor.md and docs/guides/*.md (and the
``python`` blocks and named files they build on) runs as written, in order, in one shell per page in an empty folder
(tests/guides.py), at the small sizes the pages' own markers give; a block that fails or prints a traceback fails
its page's test. What does not run here is marked in the page and listed below, each with its reason. Each page is
a unit of its own for the parallel run (tests/conftest.py: SPLIT_BY_PARAM)."""

from __future__ import annotations

import os
import re
import shlex
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from rigctl.cli import main

from .conftest import require_lsl
from .guides import PAGES, REPO, BlockRun, ReadmeEnv, blocks, readme_env, run_page
from .launcher import Launcher

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


def _shared_root(tmp_path_factory) -> Path:
    """The folder a run's test workers share (pytest-xdist's workers' temporary folders are beside each other)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture(scope="session")
def readme(tmp_path_factory) -> ReadmeEnv:
    """The README's environment the guides run in (issue 79 item 1: a user's, not the test environment): ``python3
    -m venv`` of this interpreter's Python, the wheel built from the sources, rigctl's dependencies and the guides' own
    extras, no test extras; built once for the run's workers (tests/guides.py readme_env)."""
    env = readme_env(_shared_root(tmp_path_factory), getattr(sys, "_base_executable", sys.executable))
    print(f"README environment: {env.venv} (built in {env.seconds:.0f} s, {env.cpu_s:.0f} CPU-s)")
    return env


@pytest.fixture(scope="session")
def readme_rigctl(readme, tmp_path_factory):
    """The ``rigctl`` client of this worker's preloaded server of the README environment's interpreter (its
    installed rigctl: tests/launcher.py), started once for the worker's guides."""
    launcher = Launcher(tmp_path_factory.mktemp("readme-launcher"), python=readme.python)
    yield launcher.client
    launcher.close()


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
    # in the README's environment (its python, pip and rigctl first on the PATH), a page's rigctl commands through
    # this worker's preloaded server of that environment (started once for the worker's guides)
    readme = request.getfixturevalue("readme")
    runs = run_page(page, tmp_path / "work", readme=readme, client=lambda: request.getfixturevalue("readme_rigctl"))
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


def test_the_guides_environment_is_the_readmes(readme, tmp_path):
    """What a guide's shell finds (tests/guides.py guide_env): the README environment's python with rigctl installed
    from the wheel (not the checkout, not the test environment), the model rig's C shipped in it, the guides' own
    extras, and none of the test extras (pytest, the GUI, dask, rigctl serve's FastAPI, mkdocs)."""
    import json
    import subprocess

    from .guides import guide_env

    code = ("import importlib.util as u, json, sys, rigctl; from rigctl import firmware; "
            "from rigctl.simulation import host_build as h; "
            "print(json.dumps([sys.executable, rigctl.__file__, str(h.shipped('mega', firmware.sources())), "
            "{m: u.find_spec(m) is not None for m in ('pylsl', 'nir', 'pytest', 'PySide6', 'dask', 'fastapi', "
            "'mkdocs')}]))")
    work = tmp_path / "work"  # an empty folder, as a guide's (`python -c` looks in its folder first)
    work.mkdir()
    r = subprocess.run(["bash", "-c", f"python -c {shlex.quote(code)}"], env=guide_env(work, readme), cwd=work,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    python, where, shipped, found = json.loads(r.stdout)
    assert Path(python).parent == readme.bin
    assert Path(where).is_relative_to(readme.venv) and Path(shipped).is_relative_to(readme.venv), (where, shipped)
    assert found == {"pylsl": True, "nir": True, "pytest": False, "PySide6": False, "dask": False, "fastapi": False,
                     "mkdocs": False}, found


def _python_312() -> str | None:
    """A Python 3.12 interpreter on this machine that runs (pyenv's, or ``python3.12`` on the PATH: pyenv's shim there
    runs only where pyenv selects 3.12), else None."""
    import glob
    import shutil
    import subprocess

    for python in (*sorted(glob.glob(os.path.expanduser("~/.pyenv/versions/3.12*/bin/python3.12"))),
                   shutil.which("python3.12")):
        if python and subprocess.run([python, "-c", "import venv"], capture_output=True).returncode == 0:
            return python
    return None


@pytest.mark.slow
# wall: the README's `--sim` rig is a `rigctl sim` process (always paced)
@pytest.mark.realtime
@pytest.mark.timeout(900)
def test_the_first_steps_on_python_3_12(tmp_path_factory, tmp_path):
    """Issue 79 item 1's second Python: the README's first command and the first-recording guide, in a README
    environment of Python 3.12 (its packages from uv's cache, else the package index: cp312 wheels)."""
    python = _python_312()
    if python is None:
        pytest.skip("no Python 3.12 here (python3.12 on the PATH or ~/.pyenv/versions/3.12*)")
    # (numba's kernels compiled by the commands that need them: two pages, and the cache's stamp stays 3.11's)
    env = readme_env(_shared_root(tmp_path_factory), python, name="py312", kernels=False)
    print(f"README environment (3.12): {env.venv} (built in {env.seconds:.0f} s, {env.cpu_s:.0f} CPU-s)")
    assert next((env.venv / "lib").glob("python3.12/site-packages/rigctl/simulation/host_lib/mega"), None)
    for page, check in (GUIDES["readme"], GUIDES["firstrecording"]):
        work = tmp_path / Path(page).stem / "work"
        runs = run_page(page, work, readme=env)  # (a server of the page's own when it runs more than two commands)
        check(runs, work.parent, None)
