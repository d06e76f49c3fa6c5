"""The package outside the repo: the wheel holds every package, the built-in protocols, py.typed and the licence (no
top-level ``gui``), and the installed wheel (not the editable checkout) runs the main commands from an empty folder,
with the protocols found by name."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_protocols_are_listed_and_found_by_name(tmp_path):
    from rigctl.acquisition.builtin import builtin_protocols, find_protocol

    shipped = {p.stem for p in (REPO / "protocols").iterdir() if p.suffix in (".toml", ".py")}
    assert set(builtin_protocols()) == shipped and "quick_check" in shipped
    assert find_protocol("quick_check") == find_protocol("quick_check.toml") == builtin_protocols()["quick_check"]
    own = tmp_path / "quick_check.toml"
    own.write_text("# mine\n")
    assert find_protocol(own) == own  # a user's file of the same name wins when given as a path
    with pytest.raises(FileNotFoundError, match="built-in: .*quick_check"):
        find_protocol("no_such_protocol")
    out = subprocess.run([sys.executable, "-m", "rigctl", "protocols"], capture_output=True, text=True, cwd=tmp_path,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert sorted(line.split()[0] for line in out.stdout.splitlines()) == sorted(shipped)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    d = tmp_path_factory.mktemp("wheel")
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", str(REPO), "-w", str(d)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (whl,) = d.glob("rigctl-*.whl")
    return whl


def test_the_wheel_holds_every_package_and_the_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert "gui" not in tops and {"rigctl", "rigctl_gui"} <= tops
    subpackages = {p.parent.relative_to(REPO).as_posix() for p in (REPO / "rigctl").rglob("__init__.py")}
    assert subpackages <= {n.rsplit("/", 1)[0] for n in names if n.endswith("/__init__.py")}
    for f in (REPO / "protocols").iterdir():
        if f.suffix in (".toml", ".py"):
            assert f"rigctl/protocols/{f.name}" in names
    assert {"rigctl/py.typed", "rigctl_gui/py.typed", "rigctl/__main__.py"} <= set(names)
    assert any(n.endswith("LICENSE") for n in names)


@pytest.mark.slow
def test_the_installed_wheel_runs_from_an_empty_folder(wheel, tmp_path):
    """The wheel installed (not editable) into its own folder, put first on the path, with the dependencies of the
    environment running the tests; every command from an empty folder, the protocol by name."""
    site = tmp_path / "site"
    out = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
                          str(wheel)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    work = tmp_path / "empty"
    work.mkdir()
    env = dict(os.environ, PYTHONPATH=str(site), RIGCTL_CONFIG=str(tmp_path / "rig.json"))

    def rigctl(*args, timeout=300):
        r = subprocess.run([sys.executable, "-m", "rigctl", *args], capture_output=True, text=True, cwd=work,
                           env=env, timeout=timeout)
        assert r.returncode == 0, (args, r.stderr[-2000:])
        return r.stdout

    where = subprocess.run([sys.executable, "-c", "import rigctl; print(rigctl.__file__)"], capture_output=True,
                           text=True, cwd=work, env=env).stdout.strip()
    assert Path(where).is_relative_to(site), where  # the installed wheel, not the checkout
    assert "trials complete: 6/6" in rigctl("acquire", "quick_check", "--sim", "--out", "q.h5")
    assert "complete" in rigctl("info", "q.h5")
    rigctl("sim", "dataset", "quick_check", "--trials-per-condition", "6", "--out", "d.h5")
    rigctl("encode", "d.h5", "--out", "d.enc.h5")
    assert "Individual Textures" in rigctl("analyze", "d.enc.h5", "--task", "textures", "--repeats", "2",
                                           "--pcs", "1-3", "--no-progress")
    rigctl("export", "nwb", "q.h5", "--out", "q.nwb", "--no-progress")
    assert sorted(p.name for p in work.iterdir()) == ["d.enc.h5", "d.h5", "q.h5", "q.nwb"]
