"""Replaying a committed redo journal onto its HDF5 file: the whole program of the detached commit helper.

:func:`rigctl.storage.journal.apply_journal` starts ``python -I -S journal_replay.py --apply FD JOURNAL DURABLE DELAY_S
[GATE]`` for every commit (a recorded trial, an encoded table): a script run this way is compiled from source each
time and imports what it names, so this file holds only the replay and imports only ``os``, ``struct``, ``sys``,
``time`` and ``zlib`` (measured: 56 ms of CPU a helper start against 75 ms when the helper was journal.py itself, with
``subprocess``, ``pathlib`` and ``typing``; a session of 100 trials starts 100 helpers). The journal's format
(:data:`MAGIC`, the page records, the CRC and :data:`COMMIT` mark) is written by
:meth:`rigctl.storage.journal.OverlayFile.commit`; docs/session-format.md describes it.
"""

from __future__ import annotations

import os
import struct
import sys
import time
import zlib

#: a journal starts with this and ends with :data:`COMMIT` once it is complete (its commit mark)
MAGIC = b"RIGCTLJ1"
COMMIT = b"COMMITOK"

#: the longest a test gate holds the in-place writes, s (see :func:`replay`)
GATE_MAX_S = 300.0


def pwrite(fd: int, data: bytes | memoryview, offset: int) -> None:
    """Write all of ``data`` at byte ``offset`` of ``fd`` (``os.pwrite`` may write less than asked). OSError."""
    view = memoryview(data)
    while view:
        if hasattr(os, "pwrite"):
            n = os.pwrite(fd, view, offset)
        else:  # pragma: no cover
            os.lseek(fd, offset, os.SEEK_SET)
            n = os.write(fd, view)
        view = view[n:]
        offset += n


def read_journal(jpath: str | os.PathLike[str]) -> tuple[list[tuple[int, bytes]] | None, int]:
    """The journal's ``([(offset, page bytes), ...], new file size in bytes)``, or ``(None, 0)`` when it is not
    committed (no commit mark, a bad CRC-32, too short). OSError when it cannot be read."""
    with open(jpath, "rb") as fh:
        raw = fh.read()
    if len(raw) < 28 or raw[:8] != MAGIC or raw[-8:] != COMMIT:
        return None, 0
    body, crc = raw[:-12], struct.unpack("<I", raw[-12:-8])[0]
    if zlib.crc32(body) != crc:
        return None, 0
    new_size, count = struct.unpack_from("<QI", body, 8)
    pos = 20
    entries = []
    for _ in range(count):
        offset, length = struct.unpack_from("<QI", body, pos)
        pos += 12
        entries.append((offset, body[pos:pos + length]))
        pos += length
    return entries, new_size


def _wait_at_gate(gate: str) -> None:
    with open(gate + ".reached", "ab"):
        pass
    deadline = time.monotonic() + GATE_MAX_S
    while not os.path.exists(gate) and time.monotonic() < deadline:
        time.sleep(0.005)


def replay(fd: int, jpath: str | os.PathLike[str], durable: bool, delay_s: float = 0.0, gate: str = "") -> None:
    """Write a committed journal's pages onto ``fd``, truncate the file to the journal's size, fsync it when
    ``durable``, then delete the journal; a journal that is not committed (or already replayed and removed by another
    process) is left as it is. Test hooks: ``delay_s`` seconds before each in-place write; ``gate`` (a path): after
    the first write, create ``<gate>.reached`` and wait until ``<gate>`` exists (at most :data:`GATE_MAX_S`).
    OSError."""
    entries, new_size = read_journal(jpath)
    if entries is None:
        return
    for i, (offset, data) in enumerate(entries):
        if delay_s:
            time.sleep(delay_s)
        if gate and i == 1:
            _wait_at_gate(gate)
        pwrite(fd, data, offset)
    if os.fstat(fd).st_size != new_size:
        os.ftruncate(fd, new_size)
    if durable:
        os.fsync(fd)
    os.unlink(jpath)


def serve(sock_fd: int) -> None:
    """The commit helper of a writing process (:mod:`rigctl.storage.commit_helper`): on the inherited socket
    ``sock_fd`` (AF_UNIX, SOCK_SEQPACKET), each message ``SEQ\0JOURNAL\0DURABLE(0|1)\0DELAY_S\0GATE`` with the
    locked file's descriptor is one commit: :func:`replay` onto it, the descriptor closed, then ``SEQ`` sent back
    (also when the replay failed: the writer then finds the journal and applies it itself). Returns when the
    writer's end is closed (its exit or kill)."""
    import socket  # (only here: a helper per commit, ``--apply``, does not pay for it)

    sock = socket.socket(fileno=sock_fd)
    while True:
        try:
            msg, fds, _, _ = socket.recv_fds(sock, 1 << 16, 1)
        except OSError:  # pragma: no cover
            return
        if not msg:
            return
        try:
            seq, jpath, durable, delay_s, gate = msg.split(b"\0")
            if fds:
                replay(fds[0], os.fsdecode(jpath), durable == b"1", float(delay_s), os.fsdecode(gate))
        except (OSError, ValueError):  # a journal already replayed, a bad message: the writer looks for itself
            pass
        finally:
            for fd in fds:
                os.close(fd)
        try:
            sock.send(seq)
        except OSError:  # the writer is gone (killed during the commit): the commit is done all the same
            return


def main(argv: list[str]) -> int:
    """``journal_replay.py --apply FD JOURNAL DURABLE(0|1) DELAY_S [GATE]``: :func:`replay` on the inherited, locked
    descriptor FD; ``journal_replay.py --serve SOCKET_FD``: :func:`serve`. Exit 2 with a usage line for other
    arguments."""
    if len(argv) == 2 and argv[0] == "--serve":
        serve(int(argv[1]))
        return 0
    if len(argv) not in (5, 6) or argv[0] != "--apply":
        print("usage: journal_replay.py --apply FD JOURNAL DURABLE(0|1) DELAY_S [GATE] | --serve SOCKET_FD",
              file=sys.stderr)
        return 2
    replay(int(argv[1]), argv[2], argv[3] == "1", float(argv[4]), argv[5] if len(argv) == 6 else "")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
