"""The control channel of a running ``rigctl sim`` (issue 51): the Unix socket ``control`` in its port folder, through
which ``rigctl sim inject`` arms faults on the simulated rig while faces drive it as hardware.

The socket is the owner's only: made with mode 0600 in a private folder (0700) and moved into the port folder (so
no other user could connect between its creation and its chmod), and every connection's peer is checked to be this
user (or root) by its credentials (``SO_PEERCRED``). One JSON request line, one JSON answer line, per connection:

- ``{"inject": ["estop@3+2", ...]}``: each spec parsed (:func:`rigctl.core.faults.parse_fault`) and checked against
  the rig (``fault_refusal``), then all armed at once on the physics clock from now, beside what was armed before
  (:meth:`rigctl.simulation.rig.SimulatedRig.add_faults`). Answer ``{"ok": true, "armed": [spec, ...], "time_s": T,
  "wall_time_s": W}`` (T: the clock of the truth log, ``time_s``, when they were armed: a fault ``F@A+D`` starts at
  T + A), or ``{"ok": false, "usage": true, "error": "one line"}`` for a spec that is malformed or the rig cannot model.
- ``{"status": true}``: ``{"ok": true, "time_s": T, "wall_time_s": W, "pid": P, "active": [fault names]}``.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

from rigctl.core.faults import FaultSchedule, FaultSpec, FaultSpecError, parse_fault

__all__ = ["CONTROL_NAME", "ControlServer", "NoSimRunning", "SimControlError", "request"]

#: the socket's name in the port folder
CONTROL_NAME = "control"
#: the longest request or answer, bytes
MAX_LINE = 64 * 1024
#: a client's (and the server's per-connection) time limit, s: bounds a hang only
TIMEOUT_S = 10.0


class NoSimRunning(RuntimeError):
    """No simulated rig answers in that folder (no control socket, or a dead one's)."""


class SimControlError(RuntimeError):
    """The running simulated rig refused the request (``usage``: a malformed spec or one it cannot model)."""

    def __init__(self, message: str, *, usage: bool):
        super().__init__(message)
        self.usage = usage


class FaultRig(Protocol):
    """What the server needs of the rig (:class:`rigctl.simulation.rig.SimulatedRig`)."""

    def fault_refusal(self, spec: FaultSpec) -> str | None: ...

    def add_faults(self, specs: list[FaultSpec]) -> FaultSchedule: ...


@contextlib.contextmanager
def _short_path(folder: Path, name: str) -> Iterator[str]:
    """A path to ``folder/name`` that fits a Unix socket address (108 bytes): the path itself when short, else
    through an ``O_PATH`` descriptor of the folder (``/proc/self/fd/N/name``). OSError if the folder is missing."""
    full = str(folder / name)
    if len(os.fsencode(full)) < 100:
        yield full
        return
    fd = os.open(folder, os.O_PATH | os.O_DIRECTORY)
    try:
        yield f"/proc/self/fd/{fd}/{name}"
    finally:
        os.close(fd)


def _peer_uid(conn: socket.socket) -> int:
    _pid, uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    return int(uid)


def _read_line(conn: socket.socket) -> bytes:
    data = b""
    while b"\n" not in data and len(data) < MAX_LINE:
        chunk = conn.recv(4096)
        if not chunk:
            break
        data += chunk
    return data.split(b"\n", 1)[0]


class ControlServer:
    """The control socket of one simulated rig, served by a daemon thread until :meth:`close`.

    Parameters
    ----------
    rig : the simulated rig (``fault_refusal``, ``add_faults``).
    folder : its port folder (the socket is ``folder/control``; one that is there, a killed rig's, is replaced).
    now_s : the truth log's clock (``time_s``), s.
    active : the names of the faults active now.
    """

    def __init__(self, rig: FaultRig, folder: str | os.PathLike[str], *, now_s: Callable[[], float],
                 active: Callable[[], list[str]]):
        self.rig, self.folder, self.now_s, self.active = rig, Path(folder), now_s, active
        self.path = self.folder / CONTROL_NAME
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        private = Path(tempfile.mkdtemp(prefix=".control-", dir=self.folder))  # 0700: nobody else reaches in
        try:
            with _short_path(private, CONTROL_NAME) as addr:
                self._sock.bind(addr)
            os.chmod(private / CONTROL_NAME, 0o600)
            os.replace(private / CONTROL_NAME, self.path)
        except BaseException:
            self._sock.close()
            raise
        finally:
            with contextlib.suppress(OSError):
                (private / CONTROL_NAME).unlink()
            with contextlib.suppress(OSError):
                private.rmdir()
        self._ino = os.stat(self.path).st_ino
        self._sock.listen(8)
        self._sock.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="sim-control", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            with conn:
                try:
                    conn.settimeout(TIMEOUT_S)
                    if _peer_uid(conn) not in (os.getuid(), 0):
                        continue  # another user's (the socket's mode already keeps them out)
                    answer = self.handle(_read_line(conn))
                    conn.sendall(json.dumps(answer).encode() + b"\n")
                except OSError:
                    pass  # the client went away

    def handle(self, line: bytes) -> dict[str, object]:
        """The answer to one request line (see the module's doc)."""
        try:
            req = json.loads(line)
        except ValueError:
            return {"ok": False, "usage": True, "error": "not a JSON request"}
        if not isinstance(req, dict):
            return {"ok": False, "usage": True, "error": "not a JSON object"}
        if "inject" in req:
            texts = req["inject"]
            if not isinstance(texts, list) or not texts or not all(isinstance(t, str) for t in texts):
                return {"ok": False, "usage": True, "error": "inject takes a list of FAULT@T[+D] specs"}
            specs = []
            try:
                for text in texts:
                    spec = parse_fault(text)
                    why = self.rig.fault_refusal(spec)
                    if why:
                        raise FaultSpecError(f"{spec}: not on the simulated rig: {why}")
                    specs.append(spec)
            except FaultSpecError as exc:
                return {"ok": False, "usage": True, "error": str(exc)}
            t, wall = self.now_s(), time.time()
            self.rig.add_faults(specs)
            return {"ok": True, "armed": [str(s) for s in specs], "time_s": t, "wall_time_s": wall}
        if req.get("status"):
            return {"ok": True, "time_s": self.now_s(), "wall_time_s": time.time(), "pid": os.getpid(),
                    "active": sorted(self.active())}
        return {"ok": False, "usage": True, "error": f"unknown request {sorted(req)}"}

    def close(self) -> None:
        """Stop serving and remove the socket (if it is still this server's)."""
        self._stop.set()
        self._sock.close()
        self._thread.join(timeout=2)
        with contextlib.suppress(OSError):
            if os.stat(self.path).st_ino == self._ino:
                self.path.unlink()


def request(folder: str | os.PathLike[str], req: dict[str, object], *,
            timeout_s: float = TIMEOUT_S) -> dict[str, object]:
    """Send ``req`` to the simulated rig running in ``folder``; its answer (``ok`` true).

    Raises NoSimRunning when no simulated rig answers there, SimControlError when it refuses the request."""
    folder = Path(folder)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    with sock:
        try:
            with _short_path(folder, CONTROL_NAME) as addr:
                sock.connect(addr)
        except (FileNotFoundError, NotADirectoryError, ConnectionRefusedError) as exc:
            raise NoSimRunning(f"no simulated rig running in {folder} (start one: rigctl sim --port-dir {folder})") \
                from exc
        except PermissionError as exc:
            raise NoSimRunning(f"the simulated rig in {folder} is another user's (its control socket: {exc.strerror})")\
                from exc
        sock.sendall(json.dumps(req).encode() + b"\n")
        line = _read_line(sock)
    if not line:
        raise NoSimRunning(f"the simulated rig in {folder} did not answer (stopping?)")
    answer = json.loads(line)
    if not answer.get("ok"):
        raise SimControlError(str(answer.get("error")), usage=bool(answer.get("usage")))
    return dict(answer)
