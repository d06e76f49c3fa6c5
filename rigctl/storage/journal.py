"""Crash-safe in-place updates of an HDF5 file: a copy-on-write page overlay, a redo journal, a detached applier.

HDF5 updates its metadata (superblock, group B-trees and heaps, object headers) in place and in no particular
order, so a writer killed while a file is open for writing can leave it unreadable ("addr overflow", h5py #1807,
#370), and SWMR, which orders the writes, flags the file "already open" after a crash. This module avoids both:

1. :class:`OverlayFile` is the file object HDF5 writes through (h5py's ``driver="fileobj"``). Every write lands in
   in-memory 4 KiB pages; the file on disk is not touched while HDF5 works.
2. :meth:`OverlayFile.commit` (after HDF5 has closed the file, so the overlay holds a complete, consistent file):
   pages past the old end of file are written first (nothing on disk refers to them yet); the pages that replace
   existing bytes go to a journal file ``<name>.journal`` (with a checksum and a commit mark; fsynced when durable).
3. :func:`apply_journal` writes those pages onto the file from a helper process started in its own session (one
   per writing process, kept from its first commit: :mod:`rigctl.storage.commit_helper`), which is handed the
   locked file descriptor; the writer waits for it. The helper deletes the journal.

What a plain HDF5 reader (h5py, HDFView, h5dump) sees after a ``kill -9`` of the writing process at any moment:

- before the journal's commit mark: the old file (plus unreferenced bytes past its end, which HDF5 ignores);
- after it, before the helper started: the old file, and a committed journal that the next rigctl opening
  (:func:`recover`, run by every rigctl reader and writer) replays;
- after the helper started: the helper is not killed with the writer (another session; a Ctrl-C does not reach it
  either), so it finishes within milliseconds and the file is the new version.

The file is therefore never half old, half new after a kill of the writer. Only killing the helper itself during
its few milliseconds (or a power cut during the in-place writes) leaves a torn file; the committed journal is then
still next to it, and :func:`recover` replays it (with ``durable`` commits, fsync orders the writes so the journal
is complete on disk before the first in-place write).
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import stat
import struct
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

try:  # POSIX; elsewhere (Windows) rigctl writers do not lock out HDF5 readers
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

from rigctl.storage import journal_replay, sidecars
from rigctl.storage.journal_replay import (
    COMMIT as _COMMIT,
    MAGIC as _MAGIC,
    pwrite as _pwrite,
    read_journal as _read_journal,
    replay as _replay,
)

PAGE = 4096
_O_BINARY = getattr(os, "O_BINARY", 0)


def _pread(fd: int, n: int, offset: int) -> bytes:
    if hasattr(os, "pread"):
        return os.pread(fd, n, offset)
    os.lseek(fd, offset, os.SEEK_SET)  # pragma: no cover
    return os.read(fd, n)  # pragma: no cover


def journal_path(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    return p.with_name(p.name + ".journal")


class CommittedInterrupt(KeyboardInterrupt):
    """A Ctrl-C (SIGINT) arrived during a commit's in-place writes: the commit was finished first, then this is
    raised (a KeyboardInterrupt, so callers that stop on Ctrl-C do; the data written is on disk)."""


class FileBusy(OSError):
    """Another process holds the file (a writer, or a reader with the HDF5 file lock) for longer than the wait."""


def lock_path(path: str | os.PathLike[str]) -> Path:
    """``<name>.lock``: the file a session writer holds locked for its whole life (:class:`WriterLock`)."""
    p = Path(path)
    return p.with_name(p.name + ".lock")


class WriterLockHeld(FileBusy):
    """Another writer (another process, or another writer object in this process) holds the writer lock of the
    file. ``pid`` is the holder's process id as it wrote it into the lock file (None if unknown)."""

    def __init__(self, message: str, pid: int | None = None) -> None:
        super().__init__(message)
        self.pid = pid


def _read_pid(fd: int) -> int | None:
    try:
        text = _pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None


class WriterLock:
    """An exclusive ``flock`` on ``<name>.lock`` next to ``path``, held until :meth:`release` (or the process ends).

    One writer per file: a second :class:`WriterLock` of the same file, in another process or in this one (flock
    locks belong to an open file, not to a process), raises :class:`WriterLockHeld` at once, naming the holder's
    pid. The lock file is a sidecar, not the data file, because HDF5 readers take their own (shared) flock on the
    data file and must keep opening it between the writer's commits. The kernel drops the lock when the holder
    dies (``kill -9`` included). The lock file is a sidecar (:mod:`rigctl.storage.sidecars`): created with
    ``O_EXCL | O_NOFOLLOW`` in the folder's descriptor; one a killed writer left (a regular file of one link holding
    a pid, nobody holding it) is removed and made again; a link or any other file at its name is refused
    (:class:`rigctl.storage.sidecars.SidecarExists`) and left as it is. :meth:`release` deletes the file only if its
    name still holds the one this lock made (while still holding the lock; a writer that locked the deleted file
    meanwhile notices and locks the new one).

    Raises
    ------
    WriterLockHeld (a :class:`FileBusy`, an OSError) if another writer holds it; SidecarExists (a usage error) for a
    link or a foreign file at ``<name>.lock``; OSError if the lock file cannot be created (a read-only folder, ...).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.lock_path = lock_path(self.path)
        self._fd: int | None = None
        self._dir_fd = -1
        self._stat: os.stat_result | None = None
        if fcntl is None:  # pragma: no cover - no flock here: no lock
            return
        self._dir_fd = sidecars.folder_fd(self.lock_path.parent)
        try:
            for _ in range(100):  # retried when the lock file is deleted under us (released, or stale and removed)
                if self._try_lock():
                    return
            raise FileBusy(f"{self.lock_path} keeps being replaced; cannot lock {self.path}")  # pragma: no cover
        except BaseException:
            os.close(self._dir_fd)
            self._dir_fd = -1
            raise

    def _open(self) -> tuple[int, bool] | None:
        """The lock file's descriptor and whether this call created it (``O_EXCL | O_NOFOLLOW`` in the folder's
        descriptor); an existing one is opened without following, creating or truncating it. None: it vanished
        between the two (retry). :class:`rigctl.storage.sidecars.SidecarExists` for a link or a non-file."""
        name, flags = self.lock_path.name, os.O_RDWR | _O_BINARY | sidecars.CLOEXEC | sidecars.NOFOLLOW
        try:
            return os.open(name, flags | os.O_CREAT | os.O_EXCL, 0o644, dir_fd=self._dir_fd), True
        except FileExistsError:
            pass
        try:
            fd = os.open(name, flags | os.O_NONBLOCK, dir_fd=self._dir_fd)
        except FileNotFoundError:
            return None
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                raise
            raise self._not_ours("a symlink") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise self._not_ours("not a regular file")
        return fd, False

    def _not_ours(self, what: str) -> sidecars.SidecarExists:
        return sidecars.SidecarExists(f"{self.lock_path} is {what}, not a lock file of rigctl's: it was left as it "
                                      f"is; move it away to write {self.path.name}")

    def _try_lock(self) -> bool:
        opened = self._open()
        if opened is None:
            return False
        fd, created = opened
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _read_pid(fd)
            os.close(fd)
            who = ("another writer in this process" if pid == os.getpid() else
                   f"another process (pid {pid})" if pid else "another process")
            raise WriterLockHeld(f"{self.path} is being written by {who}: one writer per session file; "
                                 "wait for it to finish (or stop it) and try again", pid) from None
        except BaseException:
            os.close(fd)
            raise
        name = self.lock_path.name
        if not created:  # an existing lock file nobody holds: a killed writer's is made again, anything else kept
            stale = sidecars.stale_lock(name, self._dir_fd, fd)
            if stale:
                with contextlib.suppress(OSError):
                    os.unlink(name, dir_fd=self._dir_fd)
            os.close(fd)
            if not stale:
                raise self._not_ours("a file of another program (not a pid)")
            return False
        try:
            st = os.fstat(fd)
            same = os.path.samestat(st, os.stat(name, dir_fd=self._dir_fd, follow_symlinks=False))
        except FileNotFoundError:
            same = False
        if not same:  # another writer took ours for stale before we locked it: lock the current one
            os.close(fd)
            return False
        self._fd, self._stat = fd, st
        try:  # the holder's pid, for the message a second writer gets (best effort: the disk may be full)
            _pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass
        return True

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Delete the lock file (only if its name still holds the file this lock created) and drop the lock
        (idempotent)."""
        fd, self._fd = self._fd, None
        dfd, self._dir_fd = self._dir_fd, -1
        if fd is None:
            if dfd >= 0:
                os.close(dfd)
            return
        try:
            with contextlib.suppress(OSError):
                here = os.stat(self.lock_path.name, dir_fd=dfd, follow_symlinks=False)
                if self._stat is not None and os.path.samestat(here, self._stat):
                    os.unlink(self.lock_path.name, dir_fd=dfd)
            fcntl.flock(fd, fcntl.LOCK_UN)  # also drops it for a forked child that shares the descriptor
        finally:
            os.close(fd)
            os.close(dfd)

    def __del__(self) -> None:  # pragma: no cover - best effort when the owner was not closed
        try:
            self.release()
        except Exception:
            pass


def _lock(fd: int, path: object, wait_s: float) -> None:
    if fcntl is None:  # pragma: no cover
        return
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise FileBusy(f"{path} is held by another process (a reader or writer) for more than {wait_s:g} s"
                               ) from None
            time.sleep(0.02)


def open_in_place(path: str | os.PathLike[str]) -> int:
    """A descriptor of the session file ``path`` open read-write, the file itself: a symbolic link at its name is
    never followed (``O_NOFOLLOW``: a session swapped for a link, e.g. inside a served data folder, would send the
    writes to the file it points to, anywhere). OSError (ELOOP) in one line for a link."""
    try:
        return os.open(path, os.O_RDWR | _O_BINARY | sidecars.NOFOLLOW)
    except OSError as exc:
        if exc.errno == errno.ELOOP or (exc.errno == errno.EMLINK and os.path.islink(path)):
            raise OSError(errno.ELOOP, f"{path} is a symbolic link: a session is written where it is, never through "
                                       "a link (refused; nothing written)") from None
        raise


def recover(path: str | os.PathLike[str], *, wait_s: float = 10.0) -> bool:
    """Finish or discard an interrupted commit of ``path``. Returns True if a committed journal was replayed.

    A journal without its commit mark (the writer died before committing) is discarded: the file was not touched
    in place. A committed one is replayed by a detached helper process (:func:`apply_journal`), like a commit.
    Raises :class:`FileBusy` if another process holds the file.
    """
    jpath = journal_path(path)
    try:
        if not stat.S_ISREG(os.lstat(jpath).st_mode):
            return False  # a link or a non-file at the journal's name is never read (nor replayed, nor removed)
    except FileNotFoundError:
        return False
    fd = open_in_place(path)
    try:
        _lock(fd, path, wait_s)
        if not jpath.exists():  # another process recovered it meanwhile
            return False
        if _read_journal(jpath)[0] is None:
            jpath.unlink()
            return False
        apply_journal(fd, jpath, durable=True)
        return True
    finally:
        os.close(fd)


#: test hooks: seconds the helper waits before each in-place write, and a gate (a path): the helper makes the first
#: in-place write, creates ``<gate>.reached`` and waits until the file ``<gate>`` exists (at most
#: :data:`rigctl.storage.journal_replay.GATE_MAX_S`) before the others, so a test acts in the middle of the in-place
#: writes, however loaded the machine
_TEST_WRITE_DELAY_S = 0.0
_TEST_WRITE_GATE = ""


def apply_journal(fd: int, jpath: str | os.PathLike[str], *, durable: bool = True) -> None:
    """Apply a committed journal to the open, locked file ``fd``, in a detached helper process.

    The in-place writes of a commit are the only moment at which the file on disk is neither the old nor the new
    version. They are made by this process's commit helper (:mod:`rigctl.storage.commit_helper`: ``python -I -S
    journal_replay.py --serve``, started at the first commit and kept), which is handed the locked descriptor for
    the commit and runs in its own session: a ``kill -9`` of the writing process (or of its process group, or a
    Ctrl-C) cannot stop it half way, so plain HDF5 readers never see a torn file after such a kill. This process
    waits for its answer. Where that helper cannot serve (no descriptor passing, it cannot be started or died), a
    helper for this commit alone inherits the descriptor (``journal_replay.py --apply FD JOURNAL``); if that cannot
    be started or fails too, the journal is applied here. A Ctrl-C while waiting is held until the journal is
    applied, then raised as :class:`CommittedInterrupt`. Killing the helper itself (or a power cut) leaves the
    committed journal, which :func:`recover` replays.
    """
    import subprocess  # (here: the helper, which imports none of this module, is the only other user of it)

    from rigctl.storage.commit_helper import serve_commit

    jpath = Path(jpath)
    served, interrupted = serve_commit(fd, jpath, durable, _TEST_WRITE_DELAY_S, _TEST_WRITE_GATE)
    cmd = [sys.executable, "-I", "-S", os.path.abspath(journal_replay.__file__), "--apply", str(fd), str(jpath),
           "1" if durable else "0", repr(float(_TEST_WRITE_DELAY_S)), _TEST_WRITE_GATE]
    proc = None
    if not served and jpath.exists() and sys.executable and not getattr(sys, "frozen", False):  # (a frozen
        try:  # app's executable is not Python)
            proc = subprocess.Popen(cmd, pass_fds=(fd,), start_new_session=True, stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL, close_fds=True)
        except (OSError, ValueError):  # pragma: no cover - cannot start processes (or pass fds) here
            proc = None
    if proc is not None:
        while True:  # a Ctrl-C must not abandon the commit: wait for the helper, then re-raise
            try:
                proc.wait()
                break
            except KeyboardInterrupt as exc:
                interrupted = exc
    if jpath.exists():  # no helper could start or finish: apply it here
        _replay(fd, jpath, durable, _TEST_WRITE_DELAY_S, _TEST_WRITE_GATE)
    if interrupted is not None:
        raise CommittedInterrupt("interrupted while committing; the commit was completed first") from interrupted


#: the largest buffer of new bytes an :class:`OverlayFile` hands on to the next one (:data:`_SPARE_TAILS`)
SPARE_TAIL_MAX_BYTES = 128 << 20
#: buffers of new bytes kept from a closed :class:`OverlayFile` for the next: a fresh buffer grown to a dataset
#: generator's batch (~55 MB) by HDF5's chunk-sized writes cost ~0.2 ms a trial in new pages and regrowth copies
_SPARE_TAILS: list[bytearray] = []


class RandomAccessFile(io.RawIOBase):
    """The base of the file objects rigctl hands h5py (:class:`OverlayFile`,
    :class:`rigctl.storage.outputs.GuardedFile`): readable, writable and seekable, its position ``_pos`` and size
    ``_size`` in bytes kept by the subclass, which gives ``readinto``, ``write`` and ``truncate``."""

    _pos: int
    _size: int

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = 0) -> int:
        """Moves to ``offset`` bytes from the start (``whence`` 0), the position (1) or the end (2)."""
        self._pos = offset if whence == 0 else self._pos + offset if whence == 1 else self._size + offset
        return self._pos


class OverlayFile(RandomAccessFile):
    """A file object for h5py (``h5py.File(OverlayFile(path), "r+")``) that keeps every write in memory until
    :meth:`commit`. Takes an exclusive ``flock`` on the file for its lifetime (other rigctl writers wait, HDF5
    readers holding the file make it wait up to ``wait_s``)."""

    def __init__(self, path: str | os.PathLike[str], *, wait_s: float = 10.0, durable: bool = True) -> None:
        super().__init__()
        self.path = Path(path)
        self.durable = durable
        recover(self.path, wait_s=wait_s)
        self._fd = open_in_place(self.path)
        try:
            _lock(self._fd, self.path, wait_s)
        except BaseException:
            os.close(self._fd)
            raise
        self._base_size = os.fstat(self._fd).st_size
        self._size = self._base_size
        self._pages: dict[int, bytearray] = {}  # pages of the bytes below _base_size (what is on disk)
        # the bytes from _base_size on (all new): one buffer, no per-page work; its first _tail_len bytes are the
        # file's, the rest room to grow (a buffer an earlier overlay used: its old bytes are never read)
        try:
            self._tail = _SPARE_TAILS.pop()
        except IndexError:
            self._tail = bytearray()
        self._tail_len = 0
        self._zero_from = self._base_size  # after a truncation below _base_size: disk bytes from here read as 0
        self._pos = 0

    # -- io.RawIOBase (readinto, write, truncate; the rest: RandomAccessFile) ------------------------------------
    def readinto(self, b: Any) -> int:
        n = max(0, min(len(b), self._size - self._pos))
        if n == 0:
            return 0
        start, end, base = self._pos, self._pos + n, self._base_size
        out = memoryview(b).cast("B")
        if start < base:  # the part on disk, with the pages written over it
            hi = min(end, base)
            data = _pread(self._fd, max(0, min(hi, self._zero_from) - start), start)
            out[: len(data)] = data
            if len(data) < hi - start:
                out[len(data):hi - start] = bytes(hi - start - len(data))
            for i in range(start // PAGE, (hi - 1) // PAGE + 1):
                page = self._pages.get(i)
                if page is None:
                    continue
                lo, up = max(start, i * PAGE), min(hi, (i + 1) * PAGE)
                out[lo - start:up - start] = page[lo - i * PAGE:up - i * PAGE]
        if end > base:  # the new part
            lo = max(start, base)
            t0, t1 = lo - base, end - base
            have = max(0, min(t1, self._tail_len) - t0)
            out[lo - start:lo - start + have] = self._tail[t0:t0 + have]
            if have < t1 - t0:
                out[lo - start + have:n] = bytes(t1 - t0 - have)
        self._pos += n
        return n

    def _page(self, i: int) -> bytearray:
        page = self._pages.get(i)
        if page is None:
            page = bytearray(PAGE)
            data = _pread(self._fd, max(0, min(PAGE, self._zero_from - i * PAGE)), i * PAGE)
            page[: len(data)] = data
            self._pages[i] = page
        return page

    def write(self, b: Any) -> int:
        data = memoryview(b).cast("B")
        n = len(data)
        pos, base = self._pos, self._base_size
        done = 0
        while done < n and pos + done < base:  # over bytes on disk: into their pages
            i = (pos + done) // PAGE
            off = (pos + done) - i * PAGE
            k = min(PAGE - off, n - done, base - (pos + done))
            self._page(i)[off:off + k] = data[done:done + k]
            done += k
        if done < n:  # new bytes: into the tail buffer
            t0 = pos + done - base
            end = t0 + n - done
            if end > len(self._tail):  # room for twice the bytes (CPython grows a bytearray by an eighth)
                self._tail.extend(bytes(max(end, 2 * len(self._tail)) - len(self._tail)))
            if t0 > self._tail_len:  # a gap reads as zeros
                self._tail[self._tail_len:t0] = bytes(t0 - self._tail_len)
            self._tail[t0:end] = data[done:]
            self._tail_len = max(self._tail_len, end)
        self._pos += n
        self._size = max(self._size, self._pos)
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else int(size)
        base = self._base_size
        if size < base:
            self._tail_len = 0
            for i in [i for i in self._pages if i * PAGE >= size]:
                del self._pages[i]
            if size % PAGE:
                page = self._page(size // PAGE)
                page[size % PAGE:] = bytes(PAGE - size % PAGE)
            self._zero_from = min(self._zero_from, size)
        elif size - base < self._tail_len:
            self._tail_len = size - base
        self._size = size
        return size

    def flush(self) -> None:  # everything stays in memory until commit()
        pass

    # -- commit ---------------------------------------------------------------------------------------------------
    def commit(self) -> None:
        """Write the overlay to the file (new bytes, then the journal, then the in-place pages by a helper)."""
        size, base = self._size, self._base_size
        if self._zero_from < min(size, base):  # bytes cut off by a truncation, then regrown: zeros over the old
            for i in range(self._zero_from // PAGE, (min(size, base) - 1) // PAGE + 1):
                self._page(i)
        inplace = []
        for i in sorted(self._pages):
            start = i * PAGE
            stop = min(start + PAGE, size, base)
            if stop > start:
                inplace.append((start, memoryview(self._pages[i])[: stop - start]))
        jpath = journal_path(self.path)
        made_journal = False
        try:
            if size > base:  # new bytes first: nothing on disk refers to them yet
                with memoryview(self._tail) as tail:
                    have = min(self._tail_len, size - base)
                    _pwrite(self._fd, tail[:have], base)
                if have < size - base:
                    _pwrite(self._fd, bytes(size - base - have), base + have)
            if inplace or size < base:
                body = bytearray(_MAGIC + struct.pack("<QI", size, len(inplace)))
                for start, data in inplace:
                    body += struct.pack("<QI", start, len(data)) + data
                body += struct.pack("<I", zlib.crc32(body)) + _COMMIT
                if self.durable:
                    os.fsync(self._fd)  # the fresh pages are on disk before the journal can point at them
                try:  # a sidecar: created new, never a file or link already there (rigctl.storage.sidecars)
                    jfd = os.open(jpath, os.O_WRONLY | os.O_CREAT | os.O_EXCL | sidecars.NOFOLLOW | _O_BINARY
                                  | sidecars.CLOEXEC, 0o644)
                except FileExistsError:
                    raise OSError(errno.EEXIST, f"{jpath} exists and is not this commit's journal (left as it is: "
                                                "move it away)") from None
                made_journal = True
                try:
                    _pwrite(jfd, bytes(body), 0)
                    if self.durable:
                        os.fsync(jfd)
                finally:
                    os.close(jfd)
        except OSError:  # e.g. ENOSPC: nothing refers to the new bytes and the journal has no commit mark yet,
            self._undo_partial_commit(jpath if made_journal else None, base)  # so the file is the old one: give
            # the space back
            raise
        if inplace or size < base:
            # the in-place writes, by a detached helper (which truncates and, if durable, fsyncs)
            apply_journal(self._fd, jpath, durable=self.durable)
        else:
            if size != os.fstat(self._fd).st_size:
                os.ftruncate(self._fd, size)
            if self.durable:
                os.fsync(self._fd)
        self._pages.clear()
        self._tail_len = 0
        self._base_size = self._zero_from = size

    def _undo_partial_commit(self, jpath: Path | None, base: int) -> None:
        """After a failed write before the journal's commit mark: drop the uncommitted journal and the bytes written
        past the old end of the file (best effort; both are ignored by readers anyway)."""
        undos: tuple[Callable[[], None], ...] = ((lambda: jpath.unlink(missing_ok=True)) if jpath else lambda: None,
                                                 lambda: os.ftruncate(self._fd, base))
        for undo in undos:
            try:
                undo()
            except OSError:
                pass

    def close(self) -> None:
        if not self.closed:
            try:
                os.close(self._fd)  # releases the flock
            finally:
                super().close()
                tail, self._tail, self._tail_len = self._tail, bytearray(), 0
                if 0 < len(tail) <= SPARE_TAIL_MAX_BYTES and not _SPARE_TAILS:
                    _SPARE_TAILS.append(tail)  # (list.append and pop: atomic, overlays in several threads)
