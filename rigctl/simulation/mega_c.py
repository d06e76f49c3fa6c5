"""The drum controller's own C logic built for the host and loaded through cffi: what the model rig runs.

The Mega's ``arduino/mega_drum/controller.c`` (with ``force_pi.c`` and ``steprate.c``, and the host-only
``arduino/host_model/mega_host.c``, which only batches ticks) is compiled with the host's C compiler into a shared
library at first use and loaded in cffi's ABI mode (:func:`load`): one build of the rules, which the Mega runs and the
model rig runs. Nothing of it is copied into Python: :class:`rigctl.simulation.controller.MegaController` is the
glue ``mega_drum.cpp`` is on the board.

Where the library goes (:func:`build_dir`): ``$RIGCTL_HOST_BUILD`` if set, else a user cache folder
``$XDG_CACHE_HOME/rigctl/host/<version>-<digest>`` (default ``~/.cache``), the digest being that of the C sources and
the compile command: changed sources build into a new folder; never into the checkout or the installed package. A
build runs under the folder's lock (parallel test workers wait for the first), writes to a temporary name and renames
it whole. The compiler: ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the PATH; none is :class:`HostBuildError` in one
line that names them (Debian: ``apt-get install gcc``).

The declaration cffi needs of ``ctl_t`` is the compiler's own: the header run through its preprocessor (array sizes
from ``rigctl_wire.h``), and checked against the compiled library's ``sizeof`` and an ``offsetof`` at load.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from rigctl import firmware
from rigctl.core.version import __version__

__all__ = ["HostBuildError", "SOURCES", "build", "build_dir", "build_shared", "compiler", "load", "open_library"]

#: the C sources of the library, relative to the firmware source folder (:func:`rigctl.firmware.sources`)
SOURCES = ("mega_drum/controller.c", "mega_drum/force_pi.c", "mega_drum/steprate.c", "host_model/mega_host.c")
#: the headers they include (in the digest too)
_HEADERS = ("host_model/mega_host.h", "mega_drum/controller.h", "mega_drum/force_pi.h", "mega_drum/steprate.h", "mega_drum/drum_config.h",
            "mega_drum/modbus_slave.h", "common/rigctl_wire.h")
#: compile flags: the firmware's host-test build (RIGCTL_HOST_TEST), float as the AVR computes it (no fused
#: multiply-add the Mega does not have)
_FLAGS = ("-O2", "-fPIC", "-shared", "-std=c11", "-ffp-contract=off", "-DRIGCTL_HOST_TEST")
_LIB = "libmega_controller.so"
_CDEF = "ctl_t.cdef"

class HostBuildError(RuntimeError):
    """The drum controller's C logic could not be built for the host (no C compiler, or the compiler failed)."""


def compiler() -> str:
    """The host C compiler: ``$CC``, else the first of ``cc``, ``gcc``, ``clang`` on the PATH. HostBuildError when
    there is none."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    raise HostBuildError("no host C compiler (cc, gcc or clang) to build the drum controller's controller.c for the "
                         "model rig: install one (Debian: apt-get install gcc)")


def _digest(src: Path, cc: str, files: tuple[str, ...] = (*SOURCES, *_HEADERS), flags: tuple[str, ...] = _FLAGS) -> str:
    h = hashlib.sha256()
    h.update(" ".join((cc, *flags)).encode() + b"\0")
    for rel in files:
        h.update(rel.encode() + b"\0" + (src / rel).read_bytes() + b"\0")
    return h.hexdigest()


def build_dir(src: Path | None = None, *, files: tuple[str, ...] = (*SOURCES, *_HEADERS),
              flags: tuple[str, ...] = _FLAGS) -> Path:
    """The folder of the library built from ``src`` (default the installed firmware sources; ``files`` the sources
    and headers it is built from, ``flags`` the compile flags: the drum controller's by default); only computes it."""
    override = os.environ.get("RIGCTL_HOST_BUILD")
    if override:
        return Path(override)
    src = src or firmware.sources()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rigctl" / "host" / f"{__version__}-{_digest(src, compiler(), files, flags)[:16]}"


def _cdef_of(src: Path, cc: str) -> str:
    """``force_pi_t``, ``ctl_t`` and the functions of ``controller.h`` and ``mega_host.h`` as the compiler's
    preprocessor sees them (the sizes of the arrays expanded); not ``ctl_bind_modbus`` (the Modbus slave's type)."""
    proc = subprocess.run([cc, "-E", "-P", "-DRIGCTL_HOST_TEST", "-I", str(src), "-x", "c", "-"],
                          input='#include "host_model/mega_host.h"\n', capture_output=True, text=True)
    if proc.returncode != 0:
        raise HostBuildError(f"{cc} could not preprocess controller.h: {proc.stderr.strip()}")
    text = proc.stdout
    structs = {m.group(1): m.group(0) for m in re.finditer(r"typedef struct\s*\{[^{}]*\}\s*(\w+)\s*;", text)}
    missing = [name for name in ("force_pi_t", "ctl_t") if name not in structs]
    if missing:
        raise HostBuildError(f"controller.h declares no {', '.join(missing)} that cffi can read")
    functions = [m.group(0) for m in re.finditer(r"^[\w ]+[ *](?:ctl|mega_host)_\w+\([^;{]*\);", text, re.M)
                 if "mb_slave_t" not in m.group(0)]
    return "\n".join([structs["force_pi_t"], structs["ctl_t"], *functions]) + "\n"


def build_shared(src: Path, out: Path, *, sources: tuple[str, ...], headers: tuple[str, ...],
                 flags: tuple[str, ...], lib: str, what: str, cdef: str | None = None) -> Path:
    """Build the firmware ``sources`` (relative to ``src``; ``headers`` in the digest too) with ``flags`` into the
    shared library ``out/lib`` unless it is there from the same sources, and write ``cdef`` (the compiler's
    preprocessed declarations, :func:`_cdef_of`, when None) beside it; returns ``out``. Concurrent builds into one
    folder wait for each other; the library is written to a temporary name and renamed whole. HostBuildError
    (``what``: the firmware part, for its message)."""
    cc = compiler()
    out.mkdir(parents=True, exist_ok=True)
    stamp = _digest(src, cc, (*sources, *headers), flags)
    with open(out / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (out / "digest").is_file() and (out / "digest").read_text() == stamp and (out / lib).is_file():
            return out
        text = cdef if cdef is not None else _cdef_of(src, cc)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out)
        os.close(fd)
        try:
            proc = subprocess.run([cc, *flags, "-I", str(src), *(str(src / s) for s in sources), "-o", tmp, "-lm"],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                raise HostBuildError(f"{cc} failed to build {what} for the host:\n{proc.stderr.strip()}")
            os.replace(tmp, out / lib)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        (out / _CDEF).write_text(text)
        (out / "digest").write_text(stamp)
    return out


def build(src: Path | None = None, out: Path | None = None) -> Path:
    """Build the library (and its ``ctl_t`` declaration) into ``out`` (default :func:`build_dir`) unless it is there;
    returns the folder. Concurrent builds into one folder wait for each other. HostBuildError."""
    src = src or firmware.sources()
    return build_shared(src, out or build_dir(src), sources=SOURCES, headers=_HEADERS, flags=_FLAGS, lib=_LIB,
                        what="the drum controller's controller.c")


@functools.cache
def load() -> tuple[Any, Any]:
    """``(ffi, lib)``: the library of the installed sources (:func:`build` at first use in the process), opened by
    :func:`open_library`. HostBuildError, RuntimeError."""
    return open_library(build())


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
