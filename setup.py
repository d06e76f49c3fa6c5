"""The wheel's one build step beyond pyproject.toml: the firmware's C compiled for the host into the package.

``build_py`` (a wheel's build, not an editable install) compiles the model rig's libraries (the drum controller's
controller.c, the on-board encoder: rigctl/simulation/host_build.py, loaded here by its path since the build
environment has none of rigctl's dependencies) from the firmware sources the wheel ships into
``rigctl/simulation/host_lib/``, and the wheel is then a platform wheel, ``py3-none-<platform>`` (the libraries are
plain C loaded through cffi's ABI mode: one wheel serves every Python 3). Without a host C compiler the step is
skipped and the wheel is pure, as before: the model rig then builds at first use (cibuildwheel, which sets
``CIBUILDWHEEL=1``, fails instead). An editable install ships nothing: the checkout builds at first use.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

try:
    from setuptools.command.bdist_wheel import bdist_wheel
except ImportError:  # setuptools < 70.1: wheel's own
    from wheel.bdist_wheel import bdist_wheel  # type: ignore[no-redef]

HERE = Path(__file__).resolve().parent


def _host_build():
    spec = importlib.util.spec_from_file_location("_rigctl_host_build", HERE / "rigctl" / "simulation" / "host_build.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@functools.cache
def _has_compiler() -> bool:
    host_build = _host_build()
    try:
        host_build.compiler()
    except host_build.HostBuildError as e:
        if os.environ.get("CIBUILDWHEEL") == "1":
            raise
        print(f"rigctl: {e}; the wheel ships no compiled controller (built at first use)", file=sys.stderr)
        return False
    return True


class build_py_with_host_lib(build_py):
    """build_py, then the host libraries compiled from the copied firmware sources into the build folder."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False) or not _has_compiler():
            return
        package = Path(self.build_lib) / "rigctl"
        written = _host_build().build_into_package(package / "arduino", package / "simulation" / "host_lib")
        print(f"rigctl: built {', '.join(str(p.relative_to(self.build_lib)) for p in written)}", file=sys.stderr)


class HostLibDistribution(Distribution):
    """A distribution with compiled parts (installed to platlib, a platform wheel) when the host libraries are built."""

    def has_ext_modules(self) -> bool:
        return _has_compiler()


class platform_wheel(bdist_wheel):
    """A ``py3-none-<platform>`` wheel when the host libraries are built into it, else the pure wheel."""

    def get_tag(self) -> tuple[str, str, str]:
        python, abi, platform = super().get_tag()
        return (python, abi, platform) if self.root_is_pure else ("py3", "none", platform)


setup(distclass=HostLibDistribution, cmdclass={"build_py": build_py_with_host_lib, "bdist_wheel": platform_wheel})
