"""The model rig's controller.c for the host (rigctl.simulation.mega_c): built once under a lock into the folder it is
told (never the checkout), loaded through cffi; without a C compiler the model rig says so in one line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

_BUILD = ("import sys; from rigctl.simulation import mega_c; ffi, lib = mega_c.open_library(mega_c.build()); "
          "c = ffi.new('ctl_t *'); lib.ctl_init(c, 0, 0); print(c.state, mega_c.build_dir())")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "CC"}
    env.update(extra)
    return env


def test_parallel_first_uses_build_once_into_the_folder_they_are_told(tmp_path):
    """Two processes that find no library build it into $RIGCTL_HOST_BUILD together: one compiles, the other waits on
    the lock and loads the same library; both run ctl_init (NOT_HOMED = 6). Nothing is written into the checkout."""
    out = tmp_path / "host"
    before = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--ignored", "rigctl/arduino"],
                            capture_output=True, text=True).stdout
    procs = [subprocess.Popen([sys.executable, "-c", _BUILD], env=_env(RIGCTL_HOST_BUILD=str(out)),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    for p, (stdout, stderr) in zip(procs, results, strict=True):
        assert p.returncode == 0, stderr
        assert stdout.split() == ["6", str(out)], stdout
    assert sorted(p.name for p in out.iterdir()) == [".lock", "ctl_t.cdef", "digest", "libmega_controller.so"]
    after = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--ignored", "rigctl/arduino"],
                           capture_output=True, text=True).stdout
    assert after == before


def test_no_c_compiler_is_one_line_and_nothing_written(tmp_path):
    """No cc, gcc or clang on the PATH and none built yet: the model rig's command ends in one line naming them and
    the package to install, exit 1, no output file."""
    out = tmp_path / "q.h5"
    proc = subprocess.run([sys.executable, "-m", "rigctl", "acquire", "quick_check", "--inprocess", "--out", str(out),
                           "--quiet"], env=_env(PATH=str(tmp_path / "no-bin"), RIGCTL_HOST_BUILD=str(tmp_path / "host")),
                          capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert proc.returncode == 1 and len(lines) == 1, (proc.returncode, lines)
    assert "no host C compiler (cc, gcc or clang)" in lines[0] and "apt-get install gcc" in lines[0], lines
    assert not out.exists()


def test_a_shipped_library_is_loaded_only_for_the_sources_it_was_built_from(tmp_path, monkeypatch):
    """What a platform wheel's build puts in the package (host_build.build_into_package, as setup.py calls it) is
    found by host_build.shipped for the same sources, and opens; one changed byte of a source and it is not (the model
    rig then builds from the sources it runs, as an sdist or editable install does)."""
    import shutil

    from rigctl import firmware
    from rigctl.simulation import host_build, mega_c

    src = tmp_path / "arduino"
    shutil.copytree(firmware.sources(), src)
    package = tmp_path / "host_lib"
    written = host_build.build_into_package(src, package)
    assert sorted(p.relative_to(package).as_posix() for p in package.rglob("*") if p.is_file()) == sorted(
        p.relative_to(package).as_posix() for p in written)
    assert {"mega/libmega_controller.so", "onboard/libonboard_encoder.so", "mega/sources.sha256"} <= {
        p.relative_to(package).as_posix() for p in written}
    monkeypatch.setattr(host_build, "SHIPPED", package)
    for name in host_build.LIBRARIES:
        assert host_build.shipped(name, src) == package / name
    ffi, lib = mega_c.open_library(package / "mega")
    c = ffi.new("ctl_t *")
    lib.ctl_init(c, 0, 0)
    assert c.state == 6  # NOT_HOMED
    steprate = src / "mega_drum" / "steprate.c"
    steprate.write_text(steprate.read_text() + "\n")
    assert host_build.shipped("mega", src) is None and host_build.shipped("onboard", src) == package / "onboard"


def test_setup_py_loads_host_build_with_the_standard_library_only():
    """setup.py loads rigctl/simulation/host_build.py by its path in a build environment without rigctl's
    dependencies: it imports nothing but the standard library."""
    import ast

    tree = ast.parse((REPO / "rigctl" / "simulation" / "host_build.py").read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module}
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported
