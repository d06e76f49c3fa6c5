"""The drum controller's own C logic built for the host and loaded through cffi: what the model rig runs.

The Mega's ``arduino/mega_drum/controller.c`` (with ``force_pi.c`` and ``steprate.c``, and the host-only
``arduino/host_model/mega_host.c``, which only batches ticks) is compiled with the host's C compiler into a shared
library (by a platform wheel's build, which ships it in the package, else at first use) and loaded in cffi's ABI mode
(:func:`load`): one build of the rules, which the Mega runs and the
model rig runs. Nothing of it is copied into Python: :class:`rigctl.simulation.controller.MegaController` is the
glue ``mega_drum.cpp`` is on the board.

Which library :func:`load` opens: the one the installed package ships (``rigctl/simulation/host_lib/mega``, built with
the wheel from the same sources: :func:`rigctl.simulation.host_build.shipped` checks their digest), else one built
here. Where that goes (:func:`build_dir`): ``$RIGCTL_HOST_BUILD`` if set, else a user cache folder
``$XDG_CACHE_HOME/rigctl/host/<version>-<digest>`` (default ``~/.cache``), the digest being that of the C sources and
the compile command: changed sources build into a new folder; never into the checkout or the installed package. A
build runs under the folder's lock (parallel test workers wait for the first), writes to a temporary name and renames
it whole. The compiler: ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the PATH; none is :class:`HostBuildError` in one
line that names them (Debian: ``apt-get install gcc``).

The declaration cffi needs of ``ctl_t`` is the compiler's own: the header run through its preprocessor (array sizes
from ``rigctl_wire.h``), and checked against the compiled library's ``sizeof`` and an ``offsetof`` at load.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

from rigctl import firmware
from rigctl.core.version import __version__
from rigctl.simulation import host_build
from rigctl.simulation.host_build import HostBuildError, build_shared, compiler

__all__ = ["HostBuildError", "SOURCES", "build", "build_dir", "build_shared", "compiler", "load", "open_library"]

_MEGA = host_build.LIBRARIES["mega"]
#: the C sources of the library, relative to the firmware source folder (:func:`rigctl.firmware.sources`)
SOURCES = _MEGA.sources
#: the headers they include (in the digest too)
_HEADERS = _MEGA.headers
#: compile flags (:data:`rigctl.simulation.host_build.LIBRARIES`)
_FLAGS = _MEGA.flags
_LIB = _MEGA.lib
_CDEF = host_build.CDEF


def build_dir(src: Path | None = None, *, files: tuple[str, ...] = (*SOURCES, *_HEADERS),
              flags: tuple[str, ...] = _FLAGS) -> Path:
    """The folder of the library built from ``src`` (default the installed firmware sources; ``files`` the sources
    and headers it is built from, ``flags`` the compile flags: the drum controller's by default); only computes it."""
    override = os.environ.get("RIGCTL_HOST_BUILD")
    if override:
        return Path(override)
    src = src or firmware.sources()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rigctl" / "host" / f"{__version__}-{host_build.digest(src, compiler(), files, flags)[:16]}"


def build(src: Path | None = None, out: Path | None = None) -> Path:
    """Build the library (and its ``ctl_t`` declaration) into ``out`` (default :func:`build_dir`) unless it is there;
    returns the folder. Concurrent builds into one folder wait for each other. HostBuildError."""
    src = src or firmware.sources()
    return host_build.build_library("mega", src, out or build_dir(src))


@functools.cache
def load() -> tuple[Any, Any]:
    """``(ffi, lib)``: the library the installed package ships for its sources, else that of :func:`build` (at first
    use in the process), opened by :func:`open_library`. HostBuildError, RuntimeError."""
    return open_library(host_build.shipped("mega", firmware.sources()) or build())


def open_library(folder: Path) -> tuple[Any, Any]:
    """``(ffi, lib)``: the library :func:`build` put in ``folder``, with ``ctl_t`` declared. RuntimeError when the
    declaration does not fit the library (a compiler whose preprocessor and compiler disagree)."""
    import cffi

    ffi = cffi.FFI()
    ffi.cdef((folder / _CDEF).read_text())
    lib = ffi.dlopen(str(folder / _LIB))
    if ffi.sizeof("ctl_t") != lib.mega_host_sizeof_ctl() or \
            ffi.offsetof("ctl_t", "drum_slip") != lib.mega_host_offsetof_drum_slip():
        raise RuntimeError(f"the ctl_t cffi read from controller.h ({ffi.sizeof('ctl_t')} bytes) is not the compiled "
                           f"one ({lib.mega_host_sizeof_ctl()} bytes)")
    return ffi, lib
