"""The files a writer makes beside its output (issue 77 item 3): ``<out>.part``, ``<out>.lock``, ``<out>.creating``,
``<out>.journal``, a small file's temporary twin. The one home of how they are made, used and removed.

Rules, for every writer (sessions, encoded files, NWB exports, CSV, figures, models, the rig config, serve's queue
and token files):

- a sidecar is **created, never opened**: ``O_CREAT | O_EXCL | O_NOFOLLOW`` relative to a descriptor of the output's
  folder (``openat``), so a symlink, a hard link or any file already at its name is never followed, truncated or
  written. Whatever is there is refused with one line (:class:`SidecarExists`, an
  :class:`OutputError`: a usage error, exit 2) that names it and says it was left as it is;
- a sidecar is **removed or renamed only if it is still the file this process created** (the same inode at the same
  name in the same folder descriptor, :meth:`Sidecar.is_ours`): a file someone put in its place is left;
- the rename onto the output (:meth:`Sidecar.commit_to`) is made within the folder descriptor too
  (``renameat``), so a folder swapped for a link between the start and the end of a write moves nothing elsewhere;
- small files rewritten whole (:func:`write_small_file`) go through a sidecar of a random name (``mkstemp``'s rule),
  so no name can be planted ahead of them and a killed writer's leftover never blocks the next one.

The writer lock (:class:`rigctl.storage.journal.WriterLock`) follows the same rule for ``<out>.lock``, with one
allowance: a lock file left by a killed rigctl writer (a regular file of one link holding a pid, or empty, not held)
is removed and created again (:func:`stale_lock`); anything else at that name is refused.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from pathlib import Path

__all__ = ["OutputError", "Sidecar", "SidecarExists", "folder_fd", "stale_lock", "write_small_file",
           "NOFOLLOW", "CLOEXEC"]

NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_DIRECTORY = getattr(os, "O_DIRECTORY", 0)
_BINARY = getattr(os, "O_BINARY", 0)
#: the largest lock file :func:`stale_lock` takes for rigctl's own (a pid and a newline), bytes
_LOCK_MAX_BYTES = 32


class OutputError(ValueError):
    """An output refused before any work (exists, is an input, unknown format, no folder, no space, a sidecar in
    the way): a usage error, shown as one line. ``option`` is the option that named the output."""

    def __init__(self, message: str, option: str = "--out") -> None:
        super().__init__(message)
        self.option = option


class SidecarExists(OutputError):
    """Something is already at a sidecar's name (a file of the user's, a link, a leftover of a killed run): it was
    not touched and the write did not start."""


def folder_fd(folder: str | os.PathLike[str]) -> int:
    """A descriptor of ``folder`` (``""`` is the working folder), opened as a folder (``O_DIRECTORY``). OSError."""
    return os.open(os.fspath(folder) or ".", os.O_RDONLY | _DIRECTORY | CLOEXEC)


def _describe(name: str, dir_fd: int) -> str:
    try:
        st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except OSError:
        return "something"
    if stat.S_ISLNK(st.st_mode):
        return "a symlink"
    if stat.S_ISDIR(st.st_mode):
        return "a folder"
    return "a file" if stat.S_ISREG(st.st_mode) else "a special file"


class Sidecar:
    """A file created new beside an output: ``path`` (its folder opened once, its name created with ``O_EXCL |
    O_NOFOLLOW`` relative to that descriptor). ``fd`` is open read-write (``O_RDWR``) until :meth:`close`.

    ``what`` names the sidecar's role in a refusal (``"part file"``, ``"lock file"``, ...); ``option`` the option
    that named the output. Raises :class:`SidecarExists` when anything is at the name (left as it is), OSError when
    the folder refuses a new file (read-only, full)."""

    def __init__(self, path: str | os.PathLike[str], *, what: str = "part file", option: str = "--out",
                 mode: int = 0o666, dir_fd: int | None = None) -> None:
        self.path = Path(path)
        self.name = self.path.name
        self.fd: int | None = None
        self._own_dir = dir_fd is None
        self.dir_fd = folder_fd(self.path.parent) if dir_fd is None else dir_fd
        try:
            self.fd = os.open(self.name, os.O_RDWR | os.O_CREAT | os.O_EXCL | NOFOLLOW | CLOEXEC | _BINARY, mode,
                              dir_fd=self.dir_fd)
        except FileExistsError:
            found = _describe(self.name, self.dir_fd)
            self._close_dir()
            raise SidecarExists(f"{self.path} exists ({found}): rigctl did not make this {what} in this run (a "
                                "file of yours, or one an interrupted run left); it was left as it is: move it "
                                f"away or choose another {option}", option) from None
        except BaseException:
            self._close_dir()
            raise
        self._stat = os.fstat(self.fd)
        self.committed = False

    def _close_dir(self) -> None:
        if self._own_dir and self.dir_fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.dir_fd)
        self.dir_fd = -1

    def is_ours(self) -> bool:
        """True while the name still holds the file this object created (same device and inode, not a link)."""
        if self.dir_fd < 0:
            return False
        try:
            st = os.stat(self.name, dir_fd=self.dir_fd, follow_symlinks=False)
        except OSError:
            return False
        return os.path.samestat(st, self._stat)

    def holds(self, fd: int) -> bool:
        """True if ``fd`` is open on the file this object created and its name still holds it."""
        try:
            return os.path.samestat(os.fstat(fd), self._stat) and self.is_ours()
        except OSError:
            return False

    def adopt(self, name: str) -> None:
        """Rename ``name`` (a file this process made in the same folder, e.g. by ``mkstemp``) over the sidecar,
        which must still be ours: the sidecar is that file from now on. OSError; :class:`SidecarExists` if the
        sidecar's name was taken by something else meanwhile."""
        self.require_ours()
        st = os.stat(name, dir_fd=self.dir_fd, follow_symlinks=False)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, f"{name} is not a regular file")
        os.replace(name, self.name, src_dir_fd=self.dir_fd, dst_dir_fd=self.dir_fd)
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        self._stat = st

    def require_ours(self) -> None:
        """:class:`SidecarExists` unless the name still holds the file this object created."""
        if not self.is_ours():
            raise SidecarExists(f"{self.path} was replaced while rigctl wrote it: nothing was renamed or removed; "
                                "check who else writes in this folder")

    def commit_to(self, target_name: str) -> None:
        """Rename the sidecar onto ``target_name`` in the same folder (atomic, ``renameat``), once it is complete;
        the object names the output from then on. :class:`SidecarExists` if the name no longer holds our file
        (nothing is renamed)."""
        self.require_ours()
        os.replace(self.name, target_name, src_dir_fd=self.dir_fd, dst_dir_fd=self.dir_fd)
        self.committed = True
        self.name, self.path = target_name, self.path.with_name(target_name)

    def remove(self, *, committed_too: bool = False) -> bool:
        """Delete the sidecar if it is still ours and was not committed (``committed_too``: also the output it
        became, e.g. an import that failed after); True if deleted. Never raises."""
        if (self.committed and not committed_too) or not self.is_ours():
            return False
        try:
            os.unlink(self.name, dir_fd=self.dir_fd)
        except OSError:
            return False
        return True

    def close_file(self) -> None:
        """Close the file's descriptor; the folder's stays open (to rename or remove the sidecar later)."""
        fd, self.fd = self.fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def close(self) -> None:
        """Close the file and the folder descriptors (idempotent; the sidecar itself stays)."""
        self.close_file()
        self._close_dir()

    def discard(self) -> None:
        """:meth:`remove` then :meth:`close`."""
        self.remove()
        self.close()


def stale_lock(name: str, dir_fd: int, fd: int) -> bool:
    """True if the file open as ``fd`` (locked by the caller, found at ``name`` in ``dir_fd``) is a lock file a
    killed rigctl writer left: a regular file of one link, at most :data:`_LOCK_MAX_BYTES` bytes holding a pid (or
    nothing), the same file the name holds now. Anything else (a user's file, a hard link to one) is not ours."""
    try:
        st = os.fstat(fd)
        here = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1 or not os.path.samestat(st, here) \
            or st.st_size > _LOCK_MAX_BYTES:
        return False
    text = os.pread(fd, _LOCK_MAX_BYTES, 0).decode("ascii", "replace").strip()
    return text == "" or text.isdigit()


def write_small_file(path: str | os.PathLike[str], data: bytes, *, mode: int = 0o666,
                     exact_mode: bool = False) -> Path:
    """Replace ``path`` by ``data`` whole (a rig config, a queue or token file): written to a sidecar of a random
    name in the same folder (created ``O_EXCL | O_NOFOLLOW``), fsynced, renamed over ``path`` within the folder's
    descriptor. ``mode`` less the umask, or exactly ``mode`` when ``exact_mode`` (a 0600 token file). On any error
    the sidecar is removed and ``path`` is as it was. OSError."""
    p = Path(path)
    dfd = folder_fd(p.parent)
    try:
        for _ in range(100):
            try:
                side = Sidecar(p.with_name(f".{p.name}.{secrets.token_hex(4)}.tmp"), what="temporary file",
                               mode=mode, dir_fd=dfd)
                break
            except SidecarExists:
                continue
        else:  # pragma: no cover - 100 random names all taken
            raise OSError(errno.EEXIST, f"no free temporary name beside {p}")
        try:
            assert side.fd is not None
            if exact_mode:
                os.fchmod(side.fd, mode)
            view = memoryview(data)
            while view:
                view = view[os.write(side.fd, view):]
            os.fsync(side.fd)
            side.commit_to(p.name)
        finally:
            side.discard()
    finally:
        os.close(dfd)
    return p
