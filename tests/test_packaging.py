"""The package outside the repo: the wheel holds every package, the built-in protocols, the firmware sources, py.typed
and the licence (no top-level ``gui``), and the wheel installed (not editable) into a fresh virtual environment runs
the main commands from an empty folder: the protocols found by name, and ``--hil`` building the firmware from the
sources installed with it into the user cache folder."""

from __future__ import annotations

import json
import os
import re
import shutil
import site
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import rigctl

from .guides import copy_of_the_sources

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


def _installed_files(v: "ReadmeInstall") -> list[str]:
    """What the wheel the README's ``pip install .`` built put into the environment: its RECORD (the wheel's own file
    list, as pip installed it, paths relative to site-packages), without the byte code pip compiles on install and
    the console scripts pip writes outside site-packages."""
    (record,) = v.site_packages.glob("rigctl-*.dist-info/RECORD")
    names = [line.split(",")[0] for line in record.read_text().splitlines() if line.strip()]
    return [n for n in names if "__pycache__/" not in n and not n.startswith("..")]


@pytest.mark.packaging
def test_the_wheel_holds_every_package_and_the_data(venv):
    """The wheel the README's install built and installed (no second build: its RECORD is the wheel's file list)."""
    names = _installed_files(venv)
    assert all((venv.site_packages / n).exists() for n in names)
    tops = {n.split("/")[0] for n in names}
    assert "gui" not in tops and {"rigctl", "rigctl_gui"} <= tops
    subpackages = {p.parent.relative_to(REPO).as_posix() for p in (REPO / "rigctl").rglob("__init__.py")}
    assert subpackages <= {n.rsplit("/", 1)[0] for n in names if n.endswith("/__init__.py")}
    for f in (REPO / "protocols").iterdir():
        if f.suffix in (".toml", ".py"):
            assert f"rigctl/protocols/{f.name}" in names
    # every firmware source of the repo's arduino/ (both boards, common headers, Makefile, harness), no build output
    firmware = {f"rigctl/arduino/{p.relative_to(REPO / 'arduino').as_posix()}" for p in (REPO / "arduino").rglob("*")
                if p.is_file() and "build" not in p.relative_to(REPO / "arduino").parts and p.name != ".gitignore"}
    assert {"rigctl/arduino/Makefile", "rigctl/arduino/common/rigctl_wire.h",
            "rigctl/arduino/simavr/rigctl_simavr.c"} <= firmware
    assert firmware == {n for n in names if n.startswith("rigctl/arduino/")}
    assert {"rigctl/py.typed", "rigctl_gui/py.typed", "rigctl/__main__.py"} <= set(names)
    # rigctl serve's /docs page runs from the Swagger UI files shipped with rigctl (rigctl.server.apidocs)
    assert {f"rigctl/server/static/swagger-ui/{f}" for f in ("swagger-ui-bundle.js", "swagger-ui.css", "LICENSE",
                                                              "NOTICE")} <= set(names)
    assert any(n.endswith("LICENSE") for n in names)


def _test_environment_paths() -> list[str]:
    """The site folders of the environment running the tests (and those its own .pth files chain in)."""
    seen = [p for p in sys.path if p.rstrip("/").endswith(("site-packages", "dist-packages"))]
    return list(dict.fromkeys(site.getsitepackages() + seen))


class ReadmeInstall:
    """The README's first command exactly as written (first-recording.md's install is the same ``pip install .``), in a
    copy of the sources: a virtual environment in ``.venv``, ``pip install .`` (not editable: the package as a wheel
    installs it), a simulated recording and ``rigctl info``. Then :meth:`rigctl` runs the installed console script from
    an empty folder.

    Offline and without a download: the new environment sees the test environment's packages behind its own (a
    ``sitecustomize`` appends them to ``sys.path``, so pip finds the dependencies installed and uninstalls the
    environment's own rigctl, never the test environment's), and pip builds without an isolated build environment.
    pip skips its closing check of every installed distribution's requirements (``--no-warn-conflicts``: it only
    warns, and here it would read the hundreds of the test environment's, ~0.7 CPU-s an install). numba's cache and
    the firmware build go to the user cache folder, ``$XDG_CACHE_HOME`` (here inside the test's folder)."""

    def __init__(self, root: Path):
        from .guides import run_by, script

        self.blocks = run_by("tests/test_packaging.py::test_the_readme_install_then_the_docs_extra")
        assert [b.page for b in self.blocks] == ["README.md", "docs/guides/first-recording.md"]
        self._script = script
        self.root = root
        self.src = copy_of_the_sources(root)
        hook = root / "hook"
        hook.mkdir()
        (hook / "sitecustomize.py").write_text(f"import sys\nsys.path.extend({_test_environment_paths()!r})\n")
        self.cache, self.work = root / "cache", root / "empty"
        self.work.mkdir()
        self.env = {k: v for k, v in os.environ.items()
                    if k not in ("PYTHONPATH", "VIRTUAL_ENV", "NUMBA_CACHE_DIR", "RIGCTL_FIRMWARE_BUILD",
                                 "RIGCTL_HOST_BUILD")}
        self.env.update(PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", PYTHONPATH=str(hook),
                        # --no-build-isolation and --no-warn-conflicts store False: pip takes the variable's value
                        # as the option's, so "0" turns them on
                        PIP_NO_INDEX="1", PIP_NO_BUILD_ISOLATION="0", PIP_NO_WARN_CONFLICTS="0",
                        XDG_CACHE_HOME=str(self.cache),
                        RIGCTL_CONFIG=str(root / "rig.json"), PYTHONUNBUFFERED="1")
        self.readme_output = self.shell(self.blocks[0].text)
        self.venv = self.src / ".venv"
        self.python = self.venv / "bin" / "python"
        self.site_packages = next((self.venv / "lib").glob("python3*/site-packages"))
        # the installed console script's environment: the activated virtual environment
        self.run_env = dict(self.env, VIRTUAL_ENV=str(self.venv), PATH=f"{self.venv / 'bin'}{os.pathsep}{self.env['PATH']}")

    def shell(self, text: str) -> str:
        """``text`` run by bash in the copy of the sources, as the guides' blocks run (a failing command ends it)."""
        step = self.root / "step.sh"
        step.write_text(self._script([], self.src).replace("echo '@@guide-block end'", text))
        r = subprocess.run(["bash", str(step)], cwd=self.src, env=self.env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0 and "Traceback" not in r.stderr, (text, r.stdout[-2000:], r.stderr[-3000:])
        return r.stdout

    def py(self, code: str) -> str:
        r = subprocess.run([str(self.python), "-c", code], capture_output=True, text=True, cwd=self.work,
                           env=self.run_env, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stdout.strip()

    def rigctl(self, *args, timeout=300) -> str:
        r = subprocess.run([str(self.venv / "bin" / "rigctl"), *args], capture_output=True, text=True, cwd=self.work,
                           env=self.run_env, timeout=timeout)
        assert r.returncode == 0, (args, r.stdout[-1000:], r.stderr[-2000:])
        return r.stdout


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    """The README's install (:class:`ReadmeInstall`), shared by the tests of the installed package below; the last
    test of this file (the docs extra) turns it into an editable install, so it runs last."""
    v = ReadmeInstall(tmp_path_factory.mktemp("readme"))
    # what the installed package says of itself, asked once: where it is, its firmware sources, its version and their
    # digest (the firmware's build folder) and where it finds the built-in quick_check
    where = json.loads(v.py("import json, rigctl, rigctl_gui, rigctl.firmware as f; "
                            "from rigctl.acquisition.builtin import find_protocol; "
                            "print(json.dumps([rigctl.__file__, rigctl_gui.__file__, str(f.sources()), "
                            "str(find_protocol('quick_check')), rigctl.__version__, f.source_digest()]))"))
    for path in where[:4]:  # the installed package, not the sources it was installed from nor the checkout
        assert Path(path).is_relative_to(v.site_packages), where
    v.sources, v.quick_check = Path(where[2]), Path(where[3])
    v.version, v.digest = where[4], where[5]
    return v


@pytest.fixture(scope="module")
def sim_session(venv):
    """The README's ``rigctl acquire quick_check --sim`` (the protocol found by name) from the installed package."""
    assert "trials complete: 6/6" in venv.readme_output
    return venv.src / "quick_check.h5"


@pytest.mark.slow
@pytest.mark.packaging
@pytest.mark.timeout(900)  # a bound on a hang: under load (CI run beside two CPU hogs) the chain took over 300 s
def test_the_installed_wheel_runs_from_an_empty_folder(venv, sim_session):
    """info, a tiny simulated dataset, encode, analyze and the NWB export, all from the installed wheel."""
    assert "complete" in venv.rigctl("info", str(sim_session))
    venv.rigctl("sim", "dataset", "quick_check", "--trials-per-condition", "6", "--out", "d.h5")
    venv.rigctl("encode", "d.h5", "--out", "d.enc.h5")
    assert "Individual Textures" in venv.rigctl("analyze", "d.enc.h5", "--task", "textures", "--repeats", "2",
                                                "--pcs", "1-3", "--no-progress")
    venv.rigctl("export", "nwb", str(sim_session), "--out", "q.nwb", "--no-progress")
    assert {"d.enc.h5", "d.h5", "q.nwb"} <= {p.name for p in venv.work.iterdir()}


@pytest.mark.packaging
def test_the_wheel_ships_the_compiled_controller_and_runs_with_no_compiler(venv, tmp_path):
    """The README's ``pip install .`` built a platform wheel (``py3-none-linux_*``: the firmware's C compiled for the
    host by setup.py's build step, not at first use) holding the drum controller's and the on-board encoder's
    libraries with the digest of the sources they were built from; installed, it runs the model rig with no C
    compiler on the PATH (nor $CC, nor $RIGCTL_HOST_BUILD) and never builds one into the user cache folder."""
    wheel = next(venv.site_packages.glob("rigctl-*.dist-info")) / "WHEEL"
    meta = wheel.read_text()
    assert "Root-Is-Purelib: false" in meta and re.search(r"^Tag: py3-none-linux_\w+$", meta, re.M), meta
    names = set(_installed_files(venv))
    for name, lib in (("mega", "libmega_controller.so"), ("onboard", "libonboard_encoder.so")):
        assert {f"rigctl/simulation/host_lib/{name}/{f}" for f in (lib, "ctl_t.cdef", "sources.sha256")} <= names
    bare = str(venv.venv / "bin")  # the environment's own commands only: python, pip, rigctl
    assert not any(shutil.which(cc, path=bare) for cc in ("cc", "gcc", "clang"))
    env = {k: v for k, v in venv.run_env.items() if k not in ("CC", "RIGCTL_HOST_BUILD")}
    env["PATH"] = bare
    r = subprocess.run([str(venv.venv / "bin" / "rigctl"), "acquire", "quick_check", "--inprocess", "--out",
                        str(tmp_path / "q.h5"), "--quiet"], capture_output=True, text=True, cwd=venv.work, env=env,
                       timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, (r.stdout[-1000:], r.stderr[-2000:])
    loaded = subprocess.run([str(venv.python), "-c", "from rigctl.simulation import host_build, mega_c, onboard_c; "
                             "mega_c.load(); onboard_c.load(); from rigctl import firmware; "
                             "print([str(host_build.shipped(n, firmware.sources())) for n in host_build.LIBRARIES])"],
                            capture_output=True, text=True, cwd=venv.work, env=env, timeout=120)
    assert loaded.returncode == 0, loaded.stderr[-2000:]
    assert loaded.stdout.strip() == str([str(venv.site_packages / "rigctl" / "simulation" / "host_lib" / n)
                                         for n in ("mega", "onboard")])
    assert not (venv.cache / "rigctl" / "host").exists()  # nothing built at first use, the README's run included
    with h5py.File(tmp_path / "q.h5", "r") as f:
        assert len(f["trials"]) == 6


def _layout(path) -> dict[str, tuple]:
    """``{dataset path: (dtype, trailing shape)}`` of trial 0 plus the root's attributes and datasets."""
    out = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = tuple(sorted(f.attrs))
        out["plan"] = (str(f["plan"].dtype),)
        for name, ds in f["trials"][sorted(f["trials"])[0]].items():
            out[name] = (str(ds.dtype), ds.shape[1:])
    return out


@pytest.mark.slow
@pytest.mark.packaging
@pytest.mark.hil
@pytest.mark.timeout(900)  # a bound on a hang (see above)
def test_hil_quick_check_from_the_wheel_builds_the_installed_firmware(venv, sim_session, build_tools):
    """``rigctl firmware`` and ``rigctl acquire quick_check --hil`` from the installed wheel: both build from the
    sources installed with it into the user cache folder (the harness's debug info names the folder it was compiled
    in), and the recorded session looks like the one from the Python simulated rig."""
    from rigctl.storage.session import open_session

    build = venv.cache / "rigctl" / "firmware" / f"{venv.version}-{venv.digest[:16]}"
    printed = venv.rigctl("firmware")
    assert f"build:   {build}" in printed and f"flash:w:{build / 'mega_drum.hex'}" in printed
    # quick_check's plan with one trial a texture (three plates, 2 s each: what the checks below need), from a file
    shipped = venv.quick_check.read_text()
    one_each = shipped.replace("trials_per_condition = 2", "trials_per_condition = 1")
    assert one_each != shipped
    (venv.work / "one_each.toml").write_text(one_each)
    venv.rigctl("acquire", "one_each.toml", "--hil", "--out", "hil.h5", "--quiet", timeout=600)
    compiled_in = str(venv.sources).encode()
    for product in ("rigctl_simavr", "mega/src/mega_drum/controller.c.o", "uno/src/uno_taxel/taxel_frame.c.o"):
        assert compiled_in in (build / product).read_bytes(), product

    hil = venv.work / "hil.h5"
    with open_session(hil) as s:
        plan = s.plan
        assert len(plan) == 3 and sorted(s.completed_ids()) == list(range(3))
        assert json.loads(s.attrs["rig_config"])["mode"] == "hil"
        trials = [s.trial(i) for i in range(3)]
    stds = {}
    for i, t in enumerate(trials):
        n = int(round(float(plan["duration_s"][i]) * 1000))
        assert t.taxels.shape == (n, 18) and t.dropped_frames == 0 and t.crc_errors == 0
        assert np.all(np.diff(t.seq.astype(np.int64)) % 65536 == 1)
        assert abs(np.median(t.force_g) - 500) < 15 and abs(np.median(t.speed_mm_s) - 120) < 1
        letter = plan["texture"][i].decode() if isinstance(plan["texture"][i], bytes) else plan["texture"][i]
        stds.setdefault(letter, []).append(t.taxels.astype(float).std(axis=0).mean())
    # the taxel readings follow the mounted plate: smooth A is quieter than ridged B and waves L
    assert max(stds["A"]) < 0.5 * min(stds["B"] + stds["L"])
    assert _layout(hil) == _layout(sim_session)


@pytest.mark.slow
@pytest.mark.packaging
def test_the_readme_install_then_the_docs_extra(venv):
    """After the README's install and its simulated recording (the :func:`venv` fixture), numba's cache files are in
    ``$XDG_CACHE_HOME/rigctl/numba``, not in the installed package; then the README's docs step, ``pip install -e
    ".[docs]"``, and ``rigctl --version`` still works (issue 38: numba's cache files in ``site-packages/rigctl``
    outlived the package and shadowed the editable install); then first-recording.md's install over it. Runs last in
    this file: it turns the shared environment into an editable install."""
    kernels = [p.name for p in (venv.site_packages / "rigctl").rglob("*.nb[ic]")]
    assert not kernels, f"numba cached kernels inside the installed package: {kernels[:5]}"
    assert any((venv.cache / "rigctl" / "numba").rglob("*.nbi"))  # the run compiled (and cached) the rig's kernels
    version = f"rigctl, version {rigctl.__version__}"
    where = venv.shell(f'. .venv/bin/activate && pip install -e ".[docs]" && cd {venv.work} && rigctl --version && '
                       'python -c "import rigctl; print(rigctl.__file__)"')
    assert version in where and f"{venv.src / 'rigctl' / '__init__.py'}" in where  # the editable sources
    # first-recording.md's install, over the editable one, then the command again from an empty folder
    where = venv.shell(f"{venv.blocks[1].text}\ncd {venv.work} && rigctl --version && "
                       "python -c 'import rigctl; print(rigctl.__file__)'")
    assert version in where and str(venv.site_packages / "rigctl" / "__init__.py") in where
