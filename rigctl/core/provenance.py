"""Provenance: what made a file (software, host, command line), stored in every file rigctl writes.

:func:`software_provenance` collects what the host knows without a rig: a fresh UUID, rigctl's version and, when the
package runs from a git clone, the commit and whether the tree was dirty (ScopeFoundry stores the same), Python and
the key packages' versions, the host and the command line. The acquisition layer adds the boards' firmware identity,
the protocol, the rig config and calibration (:func:`rigctl.acquisition.provenance.session_provenance`); the encoder
adds its parameters. Files keep it as one JSON root attribute, :data:`PROVENANCE_ATTR`; ``rigctl info --provenance``
prints it, the NWB export carries it. Imports nothing else of rigctl's but its version.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import platform
import shlex
import subprocess
import sys
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rigctl.core.version import __version__

__all__ = ["KEY_PACKAGES", "PROVENANCE_ATTR", "RESUMED_ATTR", "git_state", "package_versions", "provenance_json",
           "software_provenance"]

#: the root attribute (JSON text) every rigctl file keeps its provenance in
PROVENANCE_ATTR = "provenance"

#: the root attribute (JSON list) a resumed session keeps each resuming run's provenance in, oldest first: the
#: trials recorded after ``complete_trials_before`` were recorded by that run (its software, firmware and rig), not
#: by the one :data:`PROVENANCE_ATTR` names
RESUMED_ATTR = "provenance_resumed"

#: the packages whose versions decide what a file holds (distribution names)
KEY_PACKAGES = ("numpy", "scipy", "h5py", "numba", "scikit-learn", "pyserial", "pymodbus", "pynwb", "hdmf", "pylsl",
                "click")


def package_versions(names: Sequence[str] = KEY_PACKAGES) -> dict[str, str | None]:
    """``{distribution: version}`` of ``names`` as installed (None: not installed); looked up once per process."""
    return dict(_versions(tuple(names)))


@functools.lru_cache(maxsize=8)
def _versions(names: tuple[str, ...]) -> dict[str, str | None]:
    from importlib import metadata  # here: its imports cost ~0.1 s, which reading a session (rigctl info) never needs

    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


@functools.lru_cache(maxsize=4)
def git_state(where: str | None = None) -> dict[str, Any] | None:
    """The git commit and dirty flag of the clone ``where`` (default: the one holding the rigctl package), or None
    when it is not in a clone or git is missing. ``{"commit": 40 hex, "dirty": bool, "describe": str}``; cached per
    process (a file written later in the same process records the state at the first call)."""
    root = Path(where) if where else Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
        describe = git("describe", "--always", "--dirty")
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": commit, "dirty": dirty, "describe": describe}


def software_provenance(command_line: Sequence[str] | None = None, **extra: Any) -> dict[str, Any]:
    """What made a file, as a JSON-able dict.

    Keys: ``provenance_id`` (a fresh UUID4), ``created_utc``, ``rigctl_version``, ``git`` (:func:`git_state`, None
    outside a clone), ``python`` (version, implementation), ``packages`` (:func:`package_versions`), ``host``
    (node name, platform, machine), ``command_line`` (``sys.orig_argv``, else ``sys.argv``, unless given, joined as a shell would read it),
    then ``extra`` (firmware, protocol, rig config, parameters: what the writer knows).
    """
    # the interpreter's own command line where there is one (``python -m rigctl ...``, ``python -c ...``: sys.argv
    # alone is ['-m'...] or ['-c']); the installed ``rigctl`` script gives both the same way
    argv = list((getattr(sys, "orig_argv", None) or sys.argv) if command_line is None else command_line)
    out: dict[str, Any] = {
        "provenance_id": str(uuid.uuid4()),
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "rigctl_version": __version__,
        "git": git_state(),
        "python": {"version": platform.python_version(), "implementation": platform.python_implementation()},
        "packages": package_versions(),
        "host": {"node": platform.node(), "platform": platform.platform(), "machine": platform.machine()},
        "command_line": shlex.join(str(a) for a in argv),
    }
    out.update(extra)
    return out


def provenance_json(prov: Mapping[str, Any]) -> str:
    """``prov`` as the JSON text files store (:data:`PROVENANCE_ATTR`)."""
    return json.dumps(dict(prov), default=str, sort_keys=True)
