"""The firmware's C built for the host: the libraries the model rig loads, their compile, and the copies a wheel ships.

Two libraries, each one build of the firmware's own sources (:data:`LIBRARIES`): ``mega``, the drum controller's
``mega_drum/controller.c`` with ``force_pi.c`` and ``steprate.c`` (and the host-only ``host_model/mega_host.c``, which
only batches ticks: :mod:`rigctl.simulation.mega_c` loads it), and ``onboard``, the Uno encoder image's sample ring and
integer SA encoder (:mod:`rigctl.simulation.onboard_c`).

Where a library comes from, first found first:

1. **Shipped in the package**: a platform wheel's build compiles both into ``rigctl/simulation/host_lib/<name>/``
   (setup.py's ``build_py`` step calls :func:`build_into_package`), each with ``sources.sha256``, the digest of the
   sources, headers and flags it was compiled from (:func:`sources_digest`: no compiler in it, since the machine that
   installs the wheel may have none). :func:`shipped` returns that folder only when the digest equals the installed
   sources' (a changed source is never run from an old library).
2. **Built at first use** (an editable install or a source checkout, an sdist built without a compiler, a shipped
   library whose digest does not match): :func:`build_shared` into a cache folder (``rigctl.simulation.mega_c``'s
   ``build_dir``), under the folder's lock.

Only the standard library: setup.py loads this file by its path, in a build environment that has none of rigctl's
dependencies (tests/test_packaging.py checks it imports nothing else).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import NamedTuple

__all__ = ["HostBuildError", "HostLibrary", "LIBRARIES", "SHIPPED", "build_into_package", "build_library",
           "build_shared", "compiler", "digest", "shipped", "sources_digest"]


class HostBuildError(RuntimeError):
    """The firmware's C could not be built for the host (no C compiler, or the compiler failed)."""


class HostLibrary(NamedTuple):
    """One host library: its C ``sources`` and the ``headers`` they include (relative to the firmware source folder,
    both in its digest), compile ``flags``, the library's file name ``lib``, ``what`` it is (for messages) and its
    cffi declarations ``cdef`` (None: read from the headers by the compiler's preprocessor, :func:`_cdef_of`)."""

    sources: tuple[str, ...]
    headers: tuple[str, ...]
    flags: tuple[str, ...]
    lib: str
    what: str
    cdef: str | None = None


_ONBOARD_CDEF = """
typedef struct onboard_host onboard_host_t;
size_t onboard_host_sizeof(void);
void onboard_host_arm(void *b, const uint16_t lo[9], const uint16_t hi[9], uint16_t k);
uint8_t onboard_host_push(void *b, const uint16_t x[9]);
uint16_t onboard_host_begin(void *b, uint16_t from);
uint8_t onboard_host_step(void *b, uint16_t *mask);
int8_t onboard_host_speed(void *b, uint16_t speed_cmm_s);
void onboard_host_finish(void *b, uint16_t speed_cmm_s);
void onboard_host_counts(const void *b, uint16_t counts[180]);
uint32_t onboard_host_samples(const void *b);
uint32_t onboard_host_held(const void *b);
uint16_t onboard_host_dropped(const void *b);
uint8_t onboard_host_depth_max(const void *b);
"""

#: the host libraries by name (the shipped folder's subfolder)
LIBRARIES: dict[str, HostLibrary] = {
    # the firmware's host-test build (RIGCTL_HOST_TEST), float as the AVR computes it (no fused multiply-add the Mega
    # does not have)
    "mega": HostLibrary(
        sources=("mega_drum/controller.c", "mega_drum/force_pi.c", "mega_drum/steprate.c", "host_model/mega_host.c"),
        headers=("host_model/mega_host.h", "mega_drum/controller.h", "mega_drum/force_pi.h", "mega_drum/steprate.h",
                 "mega_drum/drum_config.h", "mega_drum/modbus_slave.h", "common/rigctl_wire.h"),
        flags=("-O2", "-fPIC", "-shared", "-std=c11", "-ffp-contract=off", "-DRIGCTL_HOST_TEST"),
        lib="libmega_controller.so", what="the drum controller's controller.c"),
    # the Uno image's kernel (-DSA_FIXED, plain C products: the same integers as its inline MUL code)
    "onboard": HostLibrary(
        sources=("common/sa_ring.c", "common/sa_encoder.c", "host_model/onboard_host.c"),
        headers=("common/sa_ring.h", "common/sa_encoder.h", "host_model/onboard_host.h"),
        flags=("-O2", "-fPIC", "-shared", "-std=c11", "-DSA_FIXED"),
        lib="libonboard_encoder.so", what="the on-board encoder's sa_ring.c and sa_encoder.c", cdef=_ONBOARD_CDEF),
}

#: where a platform wheel ships the compiled libraries (one subfolder a library); absent in a source checkout
SHIPPED = Path(__file__).resolve().parent / "host_lib"
#: the file of a library's cffi declarations, beside it
CDEF = "ctl_t.cdef"
#: a shipped library's digest of its sources (:func:`sources_digest`), beside it
SOURCES_STAMP = "sources.sha256"


def compiler() -> str:
    """The host C compiler: ``$CC``, else the first of ``cc``, ``gcc``, ``clang`` on the PATH. HostBuildError when
    there is none."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    raise HostBuildError("no host C compiler (cc, gcc or clang) to build the drum controller's controller.c for the "
                         "model rig: install one (Debian: apt-get install gcc)")


def digest(src: Path, cc: str, files: tuple[str, ...], flags: tuple[str, ...]) -> str:
    """SHA-256 (hex) of the compile command (``cc`` and ``flags``) and of ``files`` (paths relative to ``src`` and
    their bytes): names a build folder."""
    h = hashlib.sha256()
    h.update(" ".join((cc, *flags)).encode() + b"\0")
    for rel in files:
        h.update(rel.encode() + b"\0" + (src / rel).read_bytes() + b"\0")
    return h.hexdigest()


def sources_digest(src: Path, library: HostLibrary) -> str:
    """SHA-256 (hex) of ``library``'s sources and headers in ``src`` and its flags, without the compiler (what a
    shipped library is checked against on a machine that may have none)."""
    return digest(src, "", (*library.sources, *library.headers), library.flags)


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
    stamp = digest(src, cc, (*sources, *headers), flags)
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
        (out / CDEF).write_text(text)
        (out / "digest").write_text(stamp)
    return out


def build_library(name: str, src: Path, out: Path) -> Path:
    """:func:`build_shared` of the library ``name`` of :data:`LIBRARIES` from ``src`` into ``out``."""
    lib = LIBRARIES[name]
    return build_shared(src, out, sources=lib.sources, headers=lib.headers, flags=lib.flags, lib=lib.lib,
                        what=lib.what, cdef=lib.cdef)


def build_into_package(src: Path, package_dir: Path) -> list[Path]:
    """Build every library of :data:`LIBRARIES` from the firmware sources ``src`` into ``package_dir/<name>/`` (a
    wheel's copy of :data:`SHIPPED`: the library, its declarations and :data:`SOURCES_STAMP`; no lock or build
    stamp); returns the files written. HostBuildError."""
    written: list[Path] = []
    for name, lib in LIBRARIES.items():
        out = build_library(name, src, package_dir / name)
        for scratch in (".lock", "digest"):
            (out / scratch).unlink(missing_ok=True)
        (out / SOURCES_STAMP).write_text(sources_digest(src, lib) + "\n")
        written += [out / lib.lib, out / CDEF, out / SOURCES_STAMP]
    return written


def shipped(name: str, src: Path) -> Path | None:
    """The folder of the library ``name`` the installed package ships, when there is one built from the sources in
    ``src`` (its :data:`SOURCES_STAMP` equal to :func:`sources_digest` of them); else None."""
    lib = LIBRARIES[name]
    folder = SHIPPED / name
    try:
        stamp = (folder / SOURCES_STAMP).read_text().strip()
    except OSError:
        return None
    if not (folder / lib.lib).is_file() or not (folder / CDEF).is_file():
        return None
    return folder if stamp == sources_digest(src, lib) else None
