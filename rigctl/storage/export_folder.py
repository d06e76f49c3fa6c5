"""A folder of files as one rigctl output (``rigctl export events|trials --out DIR``), under the one output rule.

A folder output is written aside (``DIR.part-XXXX`` beside it) and renamed into place only when complete; a failure
removes the part folder and leaves ``DIR`` as it was. Its manifest (``rigctl_export.json``: ``kind``, the files it
wrote, what made it) says what it is, so that ``overwrite`` replaces only a folder rigctl wrote of the same kind and
holding nothing but what that manifest lists: never a folder of the user's, never one with files added since.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from rigctl.storage.outputs import OutputError, apply_umask, check_writable_folder

__all__ = ["MANIFEST_NAME", "FolderOutput", "check_folder_output", "folder_output", "read_manifest"]

#: the manifest's file name inside every folder output
MANIFEST_NAME = "rigctl_export.json"


def read_manifest(folder: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The manifest of a folder rigctl wrote (a dict with ``kind`` and ``files``), or None when it has none (or one
    that does not parse as rigctl's)."""
    path = Path(folder) / MANIFEST_NAME
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("kind"), str) or not isinstance(doc.get("files"), list):
        return None
    return doc


def _check_replaceable_folder(out: Path, kind: str, option: str) -> None:
    if out.is_symlink() or not out.is_dir():
        raise OutputError(f"{option} {out} exists and is not a folder rigctl wrote; choose another {option}")
    doc = read_manifest(out)
    if doc is None:
        raise OutputError(f"{option} {out} is not a folder rigctl wrote (no {MANIFEST_NAME}); --overwrite replaces "
                          "only rigctl's own output: choose another folder")
    if doc["kind"] != kind:
        raise OutputError(f"{option} {out} holds a rigctl export of another kind ({doc['kind']}); --overwrite "
                          f"replaces only a {kind} export")
    listed = {str(f) for f in doc["files"]} | {MANIFEST_NAME}
    foreign = sorted(p.name for p in out.iterdir() if p.name not in listed)
    if foreign:
        raise OutputError(f"{option} {out} holds files rigctl did not write ({', '.join(foreign[:3])}"
                          f"{', ...' if len(foreign) > 3 else ''}); --overwrite never removes them: choose another "
                          "folder")


class FolderOutput:
    """The folder being written: :attr:`path` (the part folder), :meth:`file` names a file in it and lists it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.files: list[str] = []

    def file(self, name: str) -> Path:
        """The path of a new file ``name`` (a plain name, no folder) in the output; listed in the manifest."""
        if Path(name).name != name or name in (MANIFEST_NAME, "", ".", ".."):
            raise ValueError(f"not a plain file name for a folder output: {name!r}")
        self.files.append(name)
        return self.path / name


def check_folder_output(out: str | os.PathLike[str], *, kind: str, overwrite: bool, option: str = "--out") -> Path:
    """Check a folder output before any work: a new folder in a writable parent, or (``overwrite``) a rigctl folder
    output of ``kind``. Returns the path; raises :class:`rigctl.storage.outputs.OutputError` (one line)."""
    p = Path(out)
    if p.exists() or p.is_symlink():
        if not overwrite:
            raise OutputError(f"{option} {p} exists; choose another {option} or pass --overwrite")
        _check_replaceable_folder(p, kind, option)
    check_writable_folder(p.parent if str(p.parent) else Path("."), option=option, target=p)
    return p


@contextlib.contextmanager
def folder_output(out: str | os.PathLike[str], *, kind: str, overwrite: bool = False, option: str = "--out",
                  manifest: Mapping[str, Any] | None = None) -> Iterator[FolderOutput]:
    """Write a folder output: yields a :class:`FolderOutput` on a part folder beside ``out``; on success its
    manifest (``kind``, ``files`` and ``manifest``'s entries) is written and the folder renamed to ``out`` (an old
    folder output of the same kind replaced when ``overwrite``); on any error the part folder is removed.

    Raises :class:`rigctl.storage.outputs.OutputError` as :func:`check_folder_output`."""
    target = check_folder_output(out, kind=kind, overwrite=overwrite, option=option)
    part = Path(tempfile.mkdtemp(prefix=f"{target.name}.part-", dir=target.parent))
    apply_umask(part, 0o777)
    try:
        fo = FolderOutput(part)
        yield fo
        doc = {"kind": kind, **dict(manifest or {}), "files": sorted(fo.files)}
        with open(part / MANIFEST_NAME, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=1)
            fh.write("\n")
        for name in (*fo.files, MANIFEST_NAME):
            if (part / name).exists():
                apply_umask(part / name)
        if target.exists():
            _check_replaceable_folder(target, kind, option)  # again: it may have changed during the work
            old = Path(tempfile.mkdtemp(prefix=f"{target.name}.old-", dir=target.parent))
            os.rename(target, old / "x")
            os.rename(part, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(part, target)
    except BaseException:
        shutil.rmtree(part, ignore_errors=True)
        raise
