"""The one output policy: how every command, the GUI and the operations layer write a file of the user's.

Rules (``docs/architecture.md``, "Outputs"), for sessions, encoded files, NWB exports, CSV, figures and models alike:

- **checked before any work** (:func:`check_output`): an existing file is replaced only when ``overwrite`` is asked;
  an output that is also an input is refused even then; the extension must be one the writer knows; the folder must
  exist and take a new file; a file another writer holds (a session being recorded: the one-writer lock of
  :class:`rigctl.storage.journal.WriterLock`) is refused; the free space is compared with an estimate of the output
  (:func:`check_space`);
- **written aside and renamed** (:func:`output_file`): the writer holds the target's writer lock for the whole
  write, writes ``<name>.part`` and renames it over the target only when complete; on any failure the part file is
  removed and the target (and every input) is left as it was;
- **a full disk is one line** (:class:`OutputWriteError`, an OSError): HDF5 files are written through
  :class:`GuardedFile`, so HDF5 itself never sees a failed write. (With h5py 3.16 / HDF5 2.0, a failed flush in
  HDF5's sec2 driver leaves the file's open-object list freed while datasets still refer to it; closing one of them
  later, even at interpreter exit, crashes in ``H5FO_top_decr`` -> ``H5SL_search``: the segfault users saw.) The
  guard stops sending bytes to the disk at the first refused write, keeps later writes in memory until the writer
  notices (:meth:`GuardedFile.check`, after each batch), so HDF5 closes cleanly and the part file is deleted;
- **only rigctl's own files are replaced** (:func:`check_replaceable`): ``overwrite`` replaces a regular file that is
  a rigctl output of the same kind (:func:`existing_kind`: a session, an encoded file, an NWB export, a model file,
  ``rigctl analyze``'s curves CSV, a figure rigctl marked as its own: :func:`figure_metadata`) and nothing else:
  never a device, a FIFO, a folder, a symlink whose target lies outside the output's folder, an empty file or another
  program's file (a writer without a kind still never replaces a session, an encoded file, an NWB export or a
  model). Client-given names (``rigctl serve``) are names inside a folder (:func:`name_in_folder`);
- **modes honour the umask** (0644 under umask 022, like any file the user makes), including files first made by
  :func:`tempfile.mkstemp` (0600).
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rigctl.storage import journal
from rigctl.storage.sidecars import OutputError, Sidecar

__all__ = ["HDF5_SUFFIXES", "OutputError", "OutputLocked", "OutputWriteError", "GuardedFile", "OutputTarget", "check_output",
           "check_replaceable", "check_space", "check_writable_folder", "current_umask", "apply_umask",
           "existing_kind", "figure_metadata", "free_bytes", "name_in_folder", "opened_in_folder", "output_file", "place_in_folder",
           "replacing", "same_file",
           "size_text", "CURVES_CSV_HEADER", "FIGURE_MARK", "MODEL_META_NAME", "OUTPUT_KINDS"]

#: the kinds of rigctl output :func:`existing_kind` recognises (``check_output(kind=)``), with their names in messages
OUTPUT_KINDS = {"session": "rigctl session file", "encoded": "rigctl encoded file", "nwb": "NWB file",
                "model": "rigctl model file", "nir": "NIR graph (rigctl export nir)", "curves": "rigctl analyze CSV (--csv)",
                "figure": "figure rigctl made (--plot, --confusion, --screenshot)"}
#: kinds that hold data (a recording, its spike trains, a fitted model): never replaced by a writer of another kind,
#: nor by a writer that names no kind
_DATA_KINDS = ("session", "encoded", "nwb", "model")
#: the header row of ``rigctl analyze --csv`` (:func:`rigctl.analysis.report.to_csv`): how an existing CSV is known
#: as rigctl's own
CURVES_CSV_HEADER = ("task", "variant", "n_pcs", "mean", "sd", "n_repeats", "n_tested")
#: the mark rigctl writes into its figures' metadata (:func:`figure_metadata`; PNG ``Software``, PDF/SVG/PS
#: ``Creator``): how an existing figure is known as rigctl's own
FIGURE_MARK = "rigctl figure"
#: the metadata entry of a model file (:mod:`rigctl.storage.model_file`): how an existing zip is known as a model
MODEL_META_NAME = "rigctl_model.json"
#: bytes read from each end of a file to find :data:`FIGURE_MARK` (PNG/SVG/PS carry it at the start, PDF at the end)
_MARK_SPAN = 1 << 16
#: the first bytes of an HDF5 file (at offset 0: rigctl writes no user block)
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: the longest client-given name :func:`name_in_folder` takes, bytes (a path component: 255, the file system's)
MAX_NAME_BYTES = 1024

#: the extensions of an HDF5 output (sessions, encoded files): ``check_output(..., suffixes=HDF5_SUFFIXES)`` refuses
#: ``--out x.csv`` for a writer of HDF5 (issue 38: it wrote HDF5 into x.csv without a word)
HDF5_SUFFIXES = (".h5", ".hdf5")

#: overlay page of :class:`GuardedFile` once the disk has refused a write, bytes
_PAGE = 1 << 16


class OutputLocked(OutputError):
    """Another writer holds the output (e.g. a session being recorded): refused even with ``overwrite``."""


class OutputWriteError(OSError):
    """The disk refused the output while it was written (no space, quota, read-only): the part file was removed,
    nothing else changed. ``str()`` is one line."""

    def __str__(self) -> str:
        return str(self.strerror)


def size_text(n_bytes: float) -> str:
    """``n_bytes`` as a short human figure (``"12.3 MB"``, ``"640 KiB"`` below 1 MB)."""
    if n_bytes < 1e6:
        return f"{n_bytes / 1024:.0f} KiB"
    return f"{n_bytes / 1e6:.1f} MB" if n_bytes < 1e9 else f"{n_bytes / 1e9:.2f} GB" if n_bytes < 1e12 \
        else f"{n_bytes / 1e12:.3g} TB"


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """True if ``a`` and ``b`` name the same file: :func:`os.path.samefile` when both exist (hard links, symlinks),
    else the same resolved path."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
    except OSError:
        pass
    return pa.resolve() == pb.resolve()


def current_umask() -> int:
    """The process's umask (read from /proc where it is, else set and restored at once)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def apply_umask(path: str | os.PathLike[str], mode: int = 0o666) -> None:
    """Give ``path`` ``mode`` minus the umask (what ``open()`` would have made; mkstemp makes 0600)."""
    os.chmod(path, mode & ~current_umask())


def free_bytes(folder: str | os.PathLike[str]) -> int | None:
    """Bytes an unprivileged user may still write in ``folder``'s file system (None if unknown)."""
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):
        return None
    return int(st.f_bavail * st.f_frsize)


def check_space(path: str | os.PathLike[str], need_bytes: float | None, *, option: str = "--out",
                replaces: bool = True) -> None:
    """Refuse (:class:`OutputError`) an output of about ``need_bytes`` that the folder's free space cannot hold
    (the size of the file it replaces counts as free when ``replaces``). None or 0 passes."""
    if not need_bytes:
        return
    p = Path(path)
    free = free_bytes(p.parent if str(p.parent) else ".")
    if free is None:
        return
    if replaces and p.is_file():
        free += p.stat().st_size
    if need_bytes > free:
        raise OutputError(f"{option} {p}: needs about {size_text(need_bytes)}, {size_text(free)} free in "
                          f"{p.parent}: free space or choose another folder", option)


def check_writable_folder(folder: Path, *, option: str, target: Path | None = None) -> None:
    """Refuse a folder that does not exist or does not take a new file (tried with a temporary file, removed)."""
    what = f"{option} {target}" if target is not None else f"{option} {folder}"
    if not folder.is_dir():
        raise OutputError(f"{what}: the folder {folder} does not exist: create it or choose another", option)
    try:
        fd, probe = tempfile.mkstemp(prefix=".rigctl-write-check-", dir=folder)
    except OSError as exc:
        raise OutputError(f"{what}: cannot write in {folder} ({exc.strerror or exc}): choose another folder",
                          option) from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def figure_metadata(path: str | os.PathLike[str]) -> dict[str, str] | None:
    """The metadata that marks a figure at ``path`` as rigctl's (``savefig(..., metadata=)``; :data:`FIGURE_MARK`),
    by its extension: ``{"Software": ...}`` for PNG, ``{"Creator": ...}`` for PDF, SVG, EPS and PS; None for formats
    that carry none (JPEG, TIFF, raw, ...): such a file is never known as rigctl's, so ``--overwrite`` cannot replace
    it (the refusal says so)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".png":
        return {"Software": FIGURE_MARK}
    if suffix in (".pdf", ".svg", ".eps", ".ps"):
        return {"Creator": FIGURE_MARK}
    return None


def _non_hdf5_kind(path: str | os.PathLike[str], head: bytes) -> str:
    """``"model"``, ``"curves"``, ``"figure"`` or ``"other"`` for a file that is not HDF5 (bounded reads)."""
    if head.startswith(b"PK\x03\x04"):
        import zipfile

        with contextlib.suppress(Exception):
            with zipfile.ZipFile(path) as z:
                if MODEL_META_NAME in z.namelist():
                    return "model"
        return "other"
    first = head.split(b"\n", 1)[0].strip().decode("utf-8", "replace")
    if first == ",".join(CURVES_CSV_HEADER):
        return "curves"
    mark = FIGURE_MARK.encode()
    if mark in head:
        return "figure"
    try:
        with open(path, "rb") as fh:
            size = fh.seek(0, os.SEEK_END)
            if size > len(head):
                fh.seek(max(len(head), size - _MARK_SPAN))
                if mark in fh.read(_MARK_SPAN):
                    return "figure"
    except OSError:
        pass
    return "other"


def existing_kind(path: str | os.PathLike[str]) -> str:
    """What an existing regular file is: ``"session"`` (a rigctl session: ``/plan`` and ``/protocol``, no
    ``/features``), ``"encoded"`` (``/features``), ``"nwb"`` (an ``nwb_version`` root attribute), ``"hdf5"``
    (another HDF5 file), ``"model"`` (a zip holding :data:`MODEL_META_NAME`), ``"curves"`` (a CSV whose header is
    :data:`CURVES_CSV_HEADER`), ``"figure"`` (:data:`FIGURE_MARK` in its first or last 64 KiB), ``"empty"``, or
    ``"other"`` (another program's file, or unreadable). Reads the signature, then the HDF5 top level read-only
    (file locking off: a probe never waits for a writer); never more than 128 KiB of any other file."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(_MARK_SPAN)
    except OSError:
        return "other"
    if not head:
        return "empty"
    if not head.startswith(_HDF5_SIGNATURE):
        return _non_hdf5_kind(path, head)
    import h5py

    try:
        with h5py.File(path, "r", locking=False) as f:
            if "features" in f:
                return "encoded"
            if "nwb_version" in f.attrs:
                return "nwb"
            if "plan" in f and "protocol" in f:
                return "session"
            if "version" in f and isinstance(f.get("node"), h5py.Group) and "type" in f["node"]:
                return "nir"
            return "hdf5"
    except Exception:  # noqa: BLE001 - h5py raises OSError, ValueError, RuntimeError, KeyError on damaged files
        return "other"


_KIND_TEXT = {"hdf5": "an HDF5 file of another program", "empty": "an empty file",
              "other": "a file of another program (not a rigctl output)", "session": "a rigctl session file",
              "encoded": "a rigctl encoded file", "nwb": "an NWB file", "model": "a rigctl model file",
              "curves": "a rigctl analyze CSV", "figure": "a figure rigctl made"}


def check_replaceable(path: str | os.PathLike[str], *, kind: str | None = None, option: str = "--out") -> None:
    """Refuse (:class:`OutputError`, one line) replacing the existing ``path`` with ``overwrite``: anything but a
    regular file (a device such as /dev/null, a FIFO, a socket, a folder), a symlink whose target is outside
    ``path``'s folder, and, when ``kind`` (a key of :data:`OUTPUT_KINDS`) is given, any file that is not a rigctl
    output of that kind (:func:`existing_kind`; a figure in a format that carries no mark, :func:`figure_metadata`,
    is never known as rigctl's). Without ``kind``, a rigctl session, encoded file, NWB export or model is refused
    (data is never replaced by a writer of another kind). A path that does not exist passes."""
    p = Path(path)
    try:
        st = os.lstat(p)
    except (OSError, ValueError):
        return
    if stat.S_ISLNK(st.st_mode):
        target = p.resolve()
        if not target.is_relative_to(p.parent.resolve()):
            raise OutputError(f"{option} {p} is a symlink to {target}, outside its folder: rigctl never replaces "
                              "a file through a link leading out; choose another output", option)
        try:
            st = os.stat(p)
        except OSError:
            return  # a dangling link: the new file replaces the link itself
    if stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{option} {p} is a folder: give a file name", option)
    if not stat.S_ISREG(st.st_mode):
        what = "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else \
            "a FIFO" if stat.S_ISFIFO(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a file"
        raise OutputError(f"{option} {p} is {what}, not a regular file: --overwrite never replaces it; choose "
                          "another output", option)
    found = existing_kind(p)
    if kind is None:
        if found in _DATA_KINDS:
            raise OutputError(f"{option} {p} is {_KIND_TEXT[found]}: --overwrite never replaces it with another "
                              "kind of file; choose another output", option)
        return
    if found != kind:
        unmarked = (" (rigctl cannot mark a " + (p.suffix or "file without extension") + " as its own: use .png, "
                    ".pdf or .svg to be able to replace it)") if kind == "figure" and figure_metadata(p) is None \
            else ""
        raise OutputError(f"{option} {p} is {_KIND_TEXT.get(found, found)}, not a {OUTPUT_KINDS[kind]}{unmarked}: "
                          f"--overwrite replaces only a {OUTPUT_KINDS[kind]}; choose another output or move it "
                          "away yourself", option)


def name_in_folder(folder: str | os.PathLike[str], name: str, *, option: str = "out") -> Path:
    """The file ``name`` (a client's relative name, e.g. ``"mouse1/s1.h5"``) inside ``folder``, resolved.

    Raises OutputError naming the rule broken: an empty name, a NUL or another control character, an absolute
    path, a ``..`` component, a name longer than :data:`MAX_NAME_BYTES` bytes (or a component over 255) or not
    encodable for the file system, or a name that resolves outside ``folder`` (a symlink leading out)."""
    if not isinstance(name, str) or not name.strip():
        raise OutputError(f"{option}: give a file name inside the data folder", option)
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise OutputError(f"{option}: control characters (NUL, newline, ...) are refused in a file name", option)
    try:
        raw = os.fsencode(name)
    except UnicodeError:
        raise OutputError(f"{option}: the name cannot be encoded for the file system", option) from None
    if len(raw) > MAX_NAME_BYTES or any(len(part) > 255 for part in raw.split(b"/")):
        raise OutputError(f"{option}: the name is too long (at most {MAX_NAME_BYTES} bytes, 255 a component)",
                          option)
    rel = Path(name)
    if rel.is_absolute() or name.startswith(("/", "\\", "~")):
        raise OutputError(f"{option} {name}: absolute paths are refused: give a name relative to the data folder",
                          option)
    if ".." in rel.parts or ".." in name.split("\\"):
        raise OutputError(f"{option} {name}: '..' is refused: give a name inside the data folder", option)
    base = Path(folder).resolve()
    try:
        full = (base / rel).resolve()
    except (OSError, RuntimeError, ValueError):
        raise OutputError(f"{option} {name}: the name does not resolve (a symlink loop?)", option) from None
    if full == base or not full.is_relative_to(base):
        raise OutputError(f"{option} {name}: the name resolves outside the data folder (a symlink leading out?)",
                          option)
    return full


def _walk_subfolders(folder: str | os.PathLike[str], name: str, *, option: str,
                     create: bool) -> tuple[int | None, list[str], list[str]]:
    """Open each subfolder of ``name`` inside ``folder`` with ``O_NOFOLLOW`` from the one before it (``openat``; made
    when missing and ``create``): ``(descriptor of the last one, or None when one is missing and not made, the
    subfolders walked, every part of name)``. OutputError naming a link, a file or an unreadable subfolder."""
    parts = [part for part in Path(name).parts if part not in ("", ".")]
    nofollow = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(Path(folder).resolve(), os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0))
    walked: list[str] = []
    try:
        for part in parts[:-1]:
            here = "/".join([*walked, part])
            try:
                try:
                    sub = os.open(part, nofollow, dir_fd=fd)
                except FileNotFoundError:
                    if not create:
                        os.close(fd)
                        return None, walked, parts  # nothing further exists: no link to follow
                    with contextlib.suppress(FileExistsError):
                        os.mkdir(part, 0o777, dir_fd=fd)
                    sub = os.open(part, nofollow, dir_fd=fd)
            except OSError as exc:  # ELOOP: a symlink; ENOTDIR: a file; EACCES, ...
                why = ("is a symlink: subfolders are opened without following links" if exc.errno == errno.ELOOP
                       else "is not a folder" if exc.errno == errno.ENOTDIR else exc.strerror or str(exc))
                raise OutputError(f"{option} {name}: {here} in the data folder {why}", option) from None
            os.close(fd)
            fd, walked = sub, [*walked, part]
        if stat.S_ISLNK(_lstat_at(parts[-1], fd)):
            raise OutputError(f"{option} {name}: it is a symlink: a session is written only as a file of its own",
                              option)
    except BaseException:
        os.close(fd)
        raise
    return fd, walked, parts


def _lstat_at(name: str, dir_fd: int) -> int:
    """``name``'s mode in ``dir_fd`` (not following a link), 0 when there is nothing."""
    try:
        return os.stat(name, dir_fd=dir_fd, follow_symlinks=False).st_mode
    except FileNotFoundError:
        return 0


def place_in_folder(folder: str | os.PathLike[str], name: str, *, option: str = "out", create: bool = False) -> Path:
    """The file ``name`` inside ``folder`` as :func:`name_in_folder` gives it, checked again on the disk as it is now,
    without following a link: each subfolder of ``name`` is opened with ``O_NOFOLLOW`` from the one before it
    (``openat``), so a subfolder that is a symlink, even one leading back inside, is refused, as is a ``name`` that
    is itself a symlink; ``create``: missing subfolders are made (``mkdir`` in the folder opened, mode 0777 less the
    umask). The path returned holds no link and reaches the folders that were opened (compared by inode).

    For a name given earlier and checked (``rigctl serve``'s queued runs, at submit); a run writes through
    :func:`opened_in_folder`. Raises OutputError naming the rule broken or the subfolder at fault."""
    full = name_in_folder(folder, name, option=option)
    base = Path(folder).resolve()
    fd, walked, parts = _walk_subfolders(folder, name, option=option, create=create)
    if fd is None:
        return full
    try:
        parent = base.joinpath(*walked)
        try:
            same = os.path.samestat(os.stat(parent), os.fstat(fd))
        except OSError:
            same = False
        if not same:
            raise OutputError(f"{option} {name}: the folder {parent} changed while it was checked", option)
    finally:
        os.close(fd)
    return base.joinpath(*parts)


@contextlib.contextmanager
def opened_in_folder(folder: str | os.PathLike[str], name: str, *, option: str = "out") -> Iterator[Path]:
    """The file ``name`` inside ``folder`` (the rules of :func:`place_in_folder`, subfolders made), as a path that
    reaches it through a descriptor of its subfolder opened now and held for the block: ``/proc/<pid>/fd/<n>/<leaf>``
    (Linux). Whatever is renamed or linked by name meanwhile (a subfolder flipped to a symlink), every open, create
    and rename through it lands in the folder that was checked: nothing is checked by name and then opened by name.
    Where /proc is missing, the checked path by name. OutputError as :func:`place_in_folder`."""
    name_in_folder(folder, name, option=option)
    fd, walked, parts = _walk_subfolders(folder, name, option=option, create=True)
    assert fd is not None
    try:
        via = Path(f"/proc/{os.getpid()}/fd/{fd}")
        try:
            reached = os.path.samestat(os.stat(via), os.fstat(fd))
        except OSError:
            reached = False
        yield (via if reached else Path(folder).resolve().joinpath(*walked)) / parts[-1]
    finally:
        os.close(fd)


def _check_unlocked(p: Path, option: str) -> None:
    """Refuse ``p`` while another writer holds its writer lock (probed: taken and released at once)."""
    if not journal.lock_path(p).exists():
        return
    try:
        lock = journal.WriterLock(p)
    except journal.WriterLockHeld as exc:
        raise OutputLocked(f"{option} {p}: {exc}", option) from None
    except OSError:
        return  # a lock file we cannot open: the folder check says what is wrong
    lock.release()


def check_output(path: str | os.PathLike[str], *, option: str = "--out", overwrite: bool = False,
                 inputs: Iterable[str | os.PathLike[str] | None] = (), suffixes: Iterable[str] | None = None,
                 overwrite_hint: str = "pass --overwrite to replace it", need_bytes: float | None = None,
                 kind: str | None = None) -> Path:
    """Refuse an output path before any work starts; returns it as a Path.

    Parameters
    ----------
    path : the output file. option : the option that named it (for the message).
    overwrite : an existing file may be replaced.
    inputs : the command's input files (None entries are ignored): the output must be none of them.
    suffixes : allowed extensions (lower case, with the dot), or None for any.
    overwrite_hint : what to do about an existing file (e.g. "continue it with --resume, or pass --overwrite").
    need_bytes : an estimate of the output's size: refused when the folder has less free space.
    kind : the output's kind (a key of :data:`OUTPUT_KINDS`): an existing file is replaced only when it is a rigctl
        output of that kind (:func:`check_replaceable`; never a device, a FIFO or a symlink leading out, whatever
        the kind).

    Raises
    ------
    OutputError (a ValueError; the CLI shows it as a usage error, exit 2), one line: the path is a folder, is one
    of the inputs, has an unsupported extension, exists without ``overwrite``, its folder is missing or does not
    take a new file, it does not fit the free space; :class:`OutputLocked` when another writer holds it (a session
    being recorded), even with ``overwrite``.
    """
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{option} {p} is a folder: give a file name", option)
    for inp in inputs:
        if inp is not None and same_file(p, inp):
            alias = f" ({inp})" if str(inp) != str(p) else ""
            raise OutputError(f"{option} {p} is one of the input files{alias}: choose another output file", option)
    if suffixes is not None:
        allowed = tuple(suffixes)
        if p.suffix.lower() not in allowed:
            raise OutputError(f"{option} {p}: unsupported format {p.suffix or '(no extension)'}; use one of "
                              f"{', '.join(allowed)}", option)
    _check_unlocked(p, option)
    if p.exists() and not overwrite:
        raise OutputError(f"{option} {p} exists: {overwrite_hint}", option)
    check_replaceable(p, kind=kind, option=option)
    check_writable_folder(p.parent if str(p.parent) else Path("."), option=option, target=p)
    check_space(p, need_bytes, option=option)
    return p


# ----------------------------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------------------------
class GuardedFile(journal.RandomAccessFile):
    """A file object for h5py (``h5py.File(GuardedFile(path), "w")``) whose writes never fail in HDF5's eyes.

    Bytes go straight to the file (``os.pwrite``) until the disk refuses one (ENOSPC, EDQUOT, EFBIG, EIO, ...);
    from then on nothing more is sent to the disk: writes land in an in-memory page overlay (reads see them), the
    error is kept, and :meth:`check` raises it as an :class:`OutputWriteError`. The owner calls :meth:`check` after
    each batch it writes, then closes HDF5 (which succeeds) and removes the file. The file is created with mode
    0666 minus the umask.
    """

    def __init__(self, path: str | os.PathLike[str], *, what: str | None = None, fd: int | None = None) -> None:
        super().__init__()
        self.path = Path(path)
        self.what = what or str(self.path)
        # ``fd``: the empty file a Sidecar created (never a file opened by name; the guard closes its own copy)
        self._fd = os.dup(fd) if fd is not None else os.open(
            self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
            | getattr(os, "O_CLOEXEC", 0), 0o666)
        self._pos = 0
        self._size = 0
        self._disk_size = 0  # bytes from 0 that are on disk (as written; beyond: zeros or the overlay)
        self.error: OSError | None = None
        self._pages: dict[int, bytearray] = {}

    # -- io.RawIOBase (readinto, write, truncate; the rest: journal.RandomAccessFile) ----------------------------
    def _pread(self, n: int, at: int) -> bytes:
        n = max(0, min(n, self._disk_size - at))
        return os.pread(self._fd, n, at) if n else b""

    def readinto(self, b: Any) -> int:
        n = max(0, min(len(b), self._size - self._pos))
        if n == 0:
            return 0
        out = memoryview(b).cast("B")
        start, end = self._pos, self._pos + n
        data = self._pread(n, start)
        out[:len(data)] = data
        out[len(data):n] = bytes(n - len(data))
        for i in range(start // _PAGE, (end - 1) // _PAGE + 1) if self._pages else ():
            page = self._pages.get(i)
            if page is not None:
                lo, up = max(start, i * _PAGE), min(end, (i + 1) * _PAGE)
                out[lo - start:up - start] = page[lo - i * _PAGE:up - i * _PAGE]
        self._pos = end
        return n

    def _overlay(self, data: memoryview, at: int) -> None:
        done = 0
        while done < len(data):
            i, off = divmod(at + done, _PAGE)
            page = self._pages.get(i)
            if page is None:
                page = bytearray(_PAGE)
                disk = self._pread(_PAGE, i * _PAGE)
                page[:len(disk)] = disk
                self._pages[i] = page
            k = min(_PAGE - off, len(data) - done)
            page[off:off + k] = data[done:done + k]
            done += k

    def write(self, b: Any) -> int:
        data = memoryview(b).cast("B")
        n, at, done = len(data), self._pos, 0
        while self.error is None and done < n:
            try:
                k = os.pwrite(self._fd, data[done:], at + done)
            except OSError as exc:
                self.error = exc
                break
            if k == 0:
                self.error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                break
            done += k
            self._disk_size = max(self._disk_size, at + done)
        if done < n:
            self._overlay(data[done:], at + done)
        self._pos = at + n
        self._size = max(self._size, self._pos)
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else int(size)
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as exc:
                self.error = exc
        self._disk_size = min(self._disk_size, size)
        for i in [i for i in self._pages if i * _PAGE >= size]:
            del self._pages[i]
        tail = self._pages.get(size // _PAGE)
        if tail is not None:  # bytes past the new end read as zeros if the file grows again
            tail[size % _PAGE:] = bytes(_PAGE - size % _PAGE)
        self._size = size
        return size

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if not self.closed:
            with contextlib.suppress(OSError):
                os.close(self._fd)
        super().close()

    # -- the owner's side ---------------------------------------------------------------------------------------
    @property
    def failed(self) -> bool:
        return self.error is not None

    def check(self) -> None:
        """Raise :class:`OutputWriteError` (one line) if the disk has refused a write."""
        if self.error is not None:
            raise _write_error(self.error, self.what)

    def sync(self) -> None:
        """fsync the bytes written (raises :class:`OutputWriteError` if the disk refused any)."""
        self.check()
        try:
            os.fsync(self._fd)
        except OSError as exc:
            self.error = exc
            self.check()


def _write_error(exc: OSError, what: str) -> OutputWriteError:
    reason = (exc.strerror or str(exc)).rstrip(".").lower() if isinstance(exc, OSError) else str(exc)
    hint = "free space or choose another folder" if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) \
        else "choose another folder"
    return OutputWriteError(exc.errno, f"{reason} writing {what}: the partial output was removed, the inputs "
                                       f"are unchanged; {hint}")


class OutputTarget:
    """What :func:`output_file` yields: ``part`` (the part file's name, created empty by this process:
    :class:`rigctl.storage.sidecars.Sidecar`), ``path`` (the final name); :meth:`h5_file` gives the part file to
    h5py through a :class:`GuardedFile`, :meth:`adopt` takes a file made beside it as the part file, :meth:`check`
    raises a refused write."""

    def __init__(self, path: Path, sidecar: Sidecar) -> None:
        self.path, self.sidecar = path, sidecar
        self.part = sidecar.path
        self.guard: GuardedFile | None = None

    def h5_file(self) -> GuardedFile:
        """The part file as a :class:`GuardedFile` (created, empty) for ``h5py.File(target.h5_file(), "w")``."""
        self.guard = GuardedFile(self.part, what=str(self.path), fd=self.sidecar.fd)
        return self.guard

    def adopt(self, made: str | os.PathLike[str]) -> None:
        """Take ``made`` (a file this process made in the output's folder) as the part file (renamed over it)."""
        self.sidecar.adopt(Path(made).name)

    def check(self) -> None:
        if self.guard is not None:
            self.guard.check()


def _finish(target: OutputTarget) -> None:
    """fsync and rename the part file over the target (within the folder's descriptor), mode per the umask."""
    side = target.sidecar
    if target.guard is not None:
        target.guard.sync()
        target.guard.close()
    try:
        fd = os.open(side.name, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0),
                     dir_fd=side.dir_fd)
    except OSError:
        fd = -1
    if fd < 0 or not side.holds(fd):
        if fd >= 0:
            os.close(fd)
        side.require_ours()  # SidecarExists: replaced by someone else; nothing renamed, nothing removed
        raise OutputWriteError(errno.EIO, f"{side.path} cannot be reopened to be made durable")
    try:
        try:
            os.fsync(fd)
            os.fchmod(fd, 0o666 & ~current_umask())
        finally:
            os.close(fd)
    except OSError as exc:
        raise _write_error(exc, str(target.path)) from None
    side.commit_to(target.path.name)


@contextlib.contextmanager
def output_file(path: str | os.PathLike[str], *, overwrite: bool = False, part_suffix: str = ".part",
                option: str = "--out", kind: str | None = None) -> Iterator[OutputTarget]:
    """Write one output under the policy (module docstring): hold the target's writer lock, yield an
    :class:`OutputTarget` whose ``part`` file becomes ``path`` when the block completes; on an exception the part
    file is removed and ``path`` is left as it was. An OSError raised while writing becomes an
    :class:`OutputWriteError` (one line).

    Raises
    ------
    OutputLocked if another writer holds ``path``; FileExistsError if ``path`` exists and ``overwrite`` is False;
    OutputError if ``path`` is not a file rigctl replaces (:func:`check_replaceable` with ``kind``); OutputWriteError
    (the disk refused the output).
    """
    p = Path(path)
    try:
        lock = journal.WriterLock(p)
    except journal.WriterLockHeld as exc:
        raise OutputLocked(f"{option} {p}: {exc}", option) from None
    except OSError as exc:
        raise _write_error(exc, str(p)) from None
    target: OutputTarget | None = None
    try:
        if p.exists() and not overwrite:
            raise FileExistsError(f"{p} exists (pass overwrite=True / --overwrite to replace it)")
        check_replaceable(p, kind=kind, option=option)
        try:  # the part file: created new (O_EXCL | O_NOFOLLOW in the folder's descriptor), a user's never touched
            target = OutputTarget(p, Sidecar(p.with_name(p.name + part_suffix), what="part file", option=option))
        except OSError as exc:
            raise _write_error(exc, str(p)) from None
        try:
            yield target
            target.check()
            _finish(target)
        except OutputWriteError:
            raise
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS):
                raise _write_error(exc, str(p)) from None
            raise
    finally:
        if target is not None:
            if target.guard is not None:
                target.guard.close()
            target.sidecar.discard()  # removed only if it is still the file this process made
        lock.release()


@contextlib.contextmanager
def replacing(path: str | os.PathLike[str], *, overwrite: bool = True, kind: str | None = None,
              option: str = "--out") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same extension, for writers that choose the format by it: plots,
    CSV, models); renamed over ``path`` when the block completes, with the umask's mode, under ``path``'s writer
    lock (:func:`output_file`, which refuses what :func:`check_replaceable` refuses for ``kind``). An exception
    leaves ``path`` as it was and removes the temporary file."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}-", suffix=p.suffix, dir=p.parent if str(p.parent) else ".")
    os.close(fd)
    try:
        with output_file(p, overwrite=overwrite, kind=kind, option=option) as target:
            yield Path(tmp)
            target.adopt(tmp)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
