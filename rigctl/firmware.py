"""The rig's firmware, shipped inside the package: both boards' sources, the common headers, the Makefile and the
simavr harness live in ``rigctl/arduino`` (the repo's ``arduino/`` links there), and :func:`build` compiles them
wherever rigctl is installed.

Where the build goes (:func:`build_dir`):

- in a checkout (an editable install: the repo's ``arduino`` link points at the sources) ``arduino/build``, the
  folder ``make -C arduino`` fills, as docs/firmware.md describes;
- in an installed package, a user cache folder ``$XDG_CACHE_HOME/rigctl/firmware/<version>-<digest>`` (default
  ``~/.cache``), the digest being that of the installed sources: changed sources build into a new folder, and
  ``make`` rebuilds what is older than its sources within one;
- ``$RIGCTL_FIRMWARE_BUILD``, if set, overrides both.

The build needs Debian's AVR toolchain and Arduino core (``gcc-avr avr-libc binutils-avr arduino-core-avr make``) and,
for the harness, ``simavr libsimavr-dev libelf-dev pkg-config``.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import subprocess
from importlib import resources
from pathlib import Path

from rigctl.core.version import __version__

__all__ = ["BOARDS", "BOOTLOADER_BAUD", "IMAGES", "BUILD_ID_DIGITS", "BUILD_TOOLS", "REQUIRED_BUILD_ID",
           "FirmwareBuildError", "avrdude_command", "build", "build_dir", "build_id", "build_mismatch", "cache_root",
           "known_versions", "make", "missing_build_tools", "MEGA_SAFETY_FLOOR", "below_safety_floor", "source_digest",
           "source_versions", "sources"]

#: the programs a build needs on the PATH (Debian: make, gcc-avr with avr-libc and arduino-core-avr, pkg-config with
#: libsimavr-dev for the harness)
BUILD_TOOLS = ("make", "avr-gcc", "pkg-config")

#: file names and suffixes that make up the sources (anything else in the folder, e.g. ``build/``, is not hashed)
_SOURCE_SUFFIXES = (".c", ".h", ".cpp")
_SOURCE_NAMES = ("Makefile",)


#: board -> (image, avrdude part, avrdude programmer, extra avrdude flags): the boards' stock bootloaders (Uno:
#: optiboot, spoken to as ``arduino``; Mega: stk500v2, as ``wiring``, ``-D``: its bootloader erases page by page)
BOARDS: dict[str, tuple[str, str, str, tuple[str, ...]]] = {
    "uno": ("uno_taxel", "m328p", "arduino", ()),
    "mega": ("mega_drum", "m2560", "wiring", ("-D",)),
}
#: board -> the images it can be flashed with, the default first: the Uno's taxel streamer, or the same with the
#: on-board SA encoder (``uno_encoder``: docs/firmware.md "The encoder in the Uno image"); the Mega's drum controller
IMAGES: dict[str, tuple[str, ...]] = {"uno": ("uno_taxel", "uno_encoder"), "mega": ("mega_drum",)}
#: both stock bootloaders talk at 115200 baud
BOOTLOADER_BAUD = 115200
#: the oldest drum-controller firmware (major, minor) whose safety rules this rigctl's host rules and docs/safety.md
#: assume (1.4: HOME creeps off the switch and proves it opens, the ratchet guard, the force loop's limit governor,
#: the contact stiffness range, EN read back; 1.5: the controller latches a reset away from home itself, RESET in
#: FAULT_BITS_HI: docs/wire-protocol.md 2.5 and 2.7; 1.6: the reading's scale checked against the contact's stiffness
#: stored with the calibration, LOADCELL_SCALE: 2.12; 1.7: the reading's zero judged off the contact at each press's
#: start and the probe's steps, LOADCELL_ZERO: 2.13; 1.8: the zero's bounded follow at a press's start: 2.13; 1.9: a
#: press with no force rise past a located contact, CONTACT_MISSING: 2.13): an image below it is never run,
#: ``--allow-firmware-mismatch`` or not
#: (:func:`below_safety_floor`). A change to controller.c's safety rules raises the Mega's minor version and this
#: floor with it (docs/firmware.md)
MEGA_SAFETY_FLOOR: tuple[int, int] = (1, 9)
#: hex digits of :func:`source_digest` a build gives the firmware as its BUILD_ID (the Uno's banner ``build=``, the
#: Mega's 48-bit BUILD_ID_0 .. _2 input registers: docs/wire-protocol.md 1.4 and 2.2)
BUILD_ID_DIGITS = 12


def avrdude_command(board: str, port: str, hex_file: Path | str) -> list[str]:
    """The avrdude command that flashes ``hex_file`` onto ``board`` ("uno" | "mega") through its bootloader on the
    serial ``port``. Raises KeyError for another board."""
    _, part, programmer, extra = BOARDS[board]
    return ["avrdude", "-p", part, "-c", programmer, "-P", str(port), "-b", str(BOOTLOADER_BAUD), *extra,
            "-U", f"flash:w:{hex_file}:i"]


class FirmwareBuildError(RuntimeError):
    """``make`` failed (the message holds its output), e.g. because the AVR toolchain or libsimavr-dev is missing."""


def sources() -> Path:
    """The firmware source folder inside the installed package (``Makefile``, ``common/``, ``uno_taxel/``,
    ``mega_drum/``, ``simavr/``, ``host_tests/``)."""
    return Path(str(resources.files("rigctl") / "arduino"))


def _source_files(src: Path) -> list[Path]:
    # in the byte order of the relative paths, as the Makefile's `LC_ALL=C sort` orders them (its BUILD_ID)
    return sorted((p for p in src.rglob("*") if p.is_file() and "build" not in p.relative_to(src).parts
                   and (p.suffix in _SOURCE_SUFFIXES or p.name in _SOURCE_NAMES)),
                  key=lambda p: p.relative_to(src).as_posix().encode())


def source_digest(src: Path | str | None = None) -> str:
    """SHA-256 (hex) of the firmware sources: every source file's path relative to ``src`` and its bytes.

    Raises
    ------
    FileNotFoundError
        ``src`` holds no Makefile (not a firmware source folder).
    """
    src = Path(src) if src is not None else sources()
    if not (src / "Makefile").is_file():
        raise FileNotFoundError(f"{src} is not the rig's firmware source folder (no Makefile)")
    h = hashlib.sha256()
    for p in _source_files(src):
        h.update(p.relative_to(src).as_posix().encode() + b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


#: the boards that must report a build id: the drum controller, which holds the sensor's protection (an image
#: without one, from the Arduino IDE or ``make BUILD_ID=``, cannot be told from any other sources). The Uno's missing
#: ``build=`` is named by the doctor, not refused: taxel sources other than rigctl's Uno report none
REQUIRED_BUILD_ID = ("mega",)


def known_versions(src: Path | str | None = None) -> str:
    """The firmware this rigctl knows, in words: ``"mega firmware 1.4 build f3310eaea3e2, uno firmware 1.0 build
    f3310eaea3e2"`` (the installed sources' :func:`source_versions` and :func:`build_id`; their errors)."""
    versions, bid = source_versions(src), build_id(src)
    return ", ".join(f"{board} firmware {'.'.join(map(str, v))} build {bid}" for board, v in versions.items())


def build_mismatch(builds: dict[str, str | None], src: Path | str | None = None, *,
                   versions: dict[str, tuple[int, ...] | None] | None = None) -> str | None:
    """One line naming each board whose firmware build (``builds``: board "mega"/"uno" -> the build id it reports,
    None for none: build 0) differs from the installed sources' build id, the versions this rigctl knows
    (:func:`known_versions`) and the flash command; None when all agree. A drum controller (:data:`REQUIRED_BUILD_ID`)
    reporting build 0 (the Arduino IDE, ``make BUILD_ID=``) is refused too; a taxel streamer reporting none is not (a
    simulated or other taxel source). ``versions``: board -> the firmware version it reports, for the line.
    Errors of :func:`source_digest`."""
    digest = source_digest(src)
    versions = versions or {}
    wrong = {b: None if v is None else str(v).lower() for b, v in builds.items()
             if (v is None and b in REQUIRED_BUILD_ID) or (v is not None and not digest.startswith(str(v).lower()))}
    if not wrong:
        return None

    def runs(board: str, v: str | None) -> str:
        version = versions.get(board)
        what = f"firmware {'.'.join(map(str, version))}" if version else "firmware"
        return (f"the {board.capitalize()} runs {what} build {v}" if v is not None else
                f"the {board.capitalize()} runs {what} build 0 (no build id: the Arduino IDE or make BUILD_ID=)")

    flash = " and ".join(f"rigctl firmware --flash PORT --board {board}" for board in wrong)
    return (f"{'; '.join(runs(b, v) for b, v in wrong.items())}; this rigctl knows {known_versions(src)}: flash it "
            f"({flash}), or pass --allow-firmware-mismatch to run anyway")


def below_safety_floor(versions: dict[str, tuple[int, ...] | None]) -> str | None:
    """One line naming a drum controller (``versions["mega"]``: the firmware version it reports, (major, minor); None
    or missing: it reported none) whose firmware is below :data:`MEGA_SAFETY_FLOOR`, with the flash command; None when
    it is at or above the floor (or no Mega is named: a rig without a drum controller). Refused even where
    ``--allow-firmware-mismatch`` allows another build: the host's safety rules rest on the controller's."""
    if "mega" not in versions:
        return None
    version = versions["mega"]
    floor = ".".join(map(str, MEGA_SAFETY_FLOOR))
    if version is not None and tuple(version[:2]) >= MEGA_SAFETY_FLOOR:
        return None
    runs = "reports no firmware version" if version is None else f"runs firmware {'.'.join(map(str, version))}"
    return (f"the Mega {runs}, below the safety floor {floor} of this rigctl (docs/safety.md): flash it (rigctl "
            f"firmware --flash PORT --board mega); --allow-firmware-mismatch never runs an image below the floor")


def build_id(src: Path | str | None = None) -> str:
    """The build id :func:`build` gives the firmware built from ``src`` (default :func:`sources`): the first
    :data:`BUILD_ID_DIGITS` hex digits of :func:`source_digest` (its errors)."""
    return source_digest(src)[:BUILD_ID_DIGITS]


def source_versions(src: Path | str | None = None) -> dict[str, tuple[int, int]]:
    """The firmware versions the sources declare (``common/rigctl_wire.h``: ``RIGCTL_MEGA_FW_MAJOR`` / ``_MINOR``,
    ``RIGCTL_UNO_FW_...``): ``{"mega": (major, minor), "uno": (major, minor)}``; what a board flashed from them
    reports (docs/wire-protocol.md 1.3 and 2.5).

    Raises
    ------
    FileNotFoundError / ValueError
        No ``common/rigctl_wire.h`` in ``src``, or it lacks one of the four defines.
    """
    src = Path(src) if src is not None else sources()
    text = (src / "common" / "rigctl_wire.h").read_text()
    out = {}
    for board in ("mega", "uno"):
        parts = []
        for part in ("MAJOR", "MINOR"):
            m = re.search(rf"^#define\s+RIGCTL_{board.upper()}_FW_{part}\s+(\d+)", text, re.MULTILINE)
            if m is None:
                raise ValueError(f"{src / 'common' / 'rigctl_wire.h'} has no RIGCTL_{board.upper()}_FW_{part}")
            parts.append(int(m.group(1)))
        out[board] = (parts[0], parts[1])
    return out


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/rigctl/firmware`` (default ``~/.cache/rigctl/firmware``): the builds of installed sources."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rigctl" / "firmware"


def _in_checkout(src: Path) -> bool:
    """True for the sources of a repo checkout (its ``arduino`` link, beside the ``rigctl`` package, points here)."""
    link = src.parent.parent / "arduino"
    return link.is_dir() and link.resolve() == src.resolve()


def build_dir(src: Path | str | None = None) -> Path:
    """Where :func:`build` puts the images and the harness for the sources ``src`` (default :func:`sources`); see
    the module docstring. Only computes the path."""
    override = os.environ.get("RIGCTL_FIRMWARE_BUILD")
    if override:
        return Path(override)
    src = Path(src) if src is not None else sources()
    if _in_checkout(src):
        return src / "build"
    return cache_root() / f"{__version__}-{source_digest(src)[:16]}"


def build(src: Path | str | None = None, out: Path | str | None = None, *,
          targets: tuple[str, ...] = ("all", "harness")) -> Path:
    """Build the firmware with ``make`` (incremental): both images (``all``: ``uno_taxel.{elf,hex}``,
    ``mega_drum.{elf,hex}``) and the simavr harness (``harness``: ``rigctl_simavr``) by default.

    Parameters
    ----------
    src : path, optional
        The source folder (default :func:`sources`, the installed package's); only read.
    out : path, optional
        The build folder (default :func:`build_dir` of ``src``). Concurrent builds into one folder wait for each
        other (a lock file in it).
    targets : tuple of str
        Makefile targets.

    Returns
    -------
    Path of the build folder.

    Raises
    ------
    FirmwareBuildError
        ``make`` failed; the message holds its output.
    """
    src = Path(src) if src is not None else sources()
    out = Path(out) if out is not None else build_dir(src)
    proc = make(targets, src, out)
    if proc.returncode != 0:
        raise FirmwareBuildError(f"firmware build failed ({' '.join(map(str, proc.args))}):\n{proc.stdout}\n"
                                 f"{proc.stderr}")
    return out


def missing_build_tools() -> list[str]:
    """The programs of :data:`BUILD_TOOLS` not on the PATH ([] when a build can start)."""
    return [tool for tool in BUILD_TOOLS if shutil.which(tool) is None]


def make(targets: tuple[str, ...], src: Path | str | None = None,
         out: Path | str | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``make`` on ``targets`` in the build folder ``out`` (default :func:`build_dir` of ``src``) as
    :func:`build` does: with the sources' BUILD_ID and under the folder's lock. Every make into one folder must go
    through here: a make without the BUILD_ID (or with another) rewrites the build-id stamp, and the next build
    relinks the images while others may be reading them. Returns the finished process (output captured); raises
    FirmwareBuildError when there is no ``make`` at all."""
    src = Path(src) if src is not None else sources()
    out = Path(out) if out is not None else build_dir(src)
    out.mkdir(parents=True, exist_ok=True)
    # BUILD_ID: the Uno reports it in its banner (build=), the Mega in its input registers (BUILD_ID_0 .. _2), so the
    # doctor can tell a board flashed from other sources
    cmd = ["make", "-s", "-C", str(src), f"BUILD={out.resolve()}", f"BUILD_ID={build_id(src)}", *targets]
    with open(out / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return subprocess.run(cmd, capture_output=True, text=True)
        except FileNotFoundError as exc:  # no make at all
            raise FirmwareBuildError(f"firmware build failed: {exc} (install make and the AVR toolchain)") from None
