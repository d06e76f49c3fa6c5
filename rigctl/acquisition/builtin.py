"""The protocols that ship inside the package (``rigctl/protocols/``; the repo's ``protocols/`` links to them), found
by name: ``rigctl acquire quick_check`` runs ``quick_check.toml`` from wherever rigctl is installed.

:func:`find_protocol` takes what a user typed (a path, or a built-in name with or without its extension);
:func:`builtin_protocols` lists the built-in ones and :func:`summary` gives each one's first comment line.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

__all__ = ["builtin_folder", "builtin_protocols", "find_protocol", "summary"]

_SUFFIXES = (".toml", ".py")


def builtin_folder() -> Path:
    """The folder of the built-in protocols inside the installed package."""
    return Path(str(resources.files("rigctl") / "protocols"))


def builtin_protocols() -> dict[str, Path]:
    """Built-in protocol name (file stem) -> file, sorted by name (TOML protocols and Python-script protocols)."""
    folder = builtin_folder()
    files = [p for p in folder.iterdir() if p.suffix in _SUFFIXES and not p.name.startswith(("_", "."))] \
        if folder.is_dir() else []
    return {p.stem: p for p in sorted(files)}


def find_protocol(name_or_path: str | os.PathLike) -> Path:
    """The protocol file a user means: an existing path as given, else a built-in protocol of that name
    (``quick_check`` or ``quick_check.toml``).

    Raises
    ------
    FileNotFoundError
        Neither a file nor a built-in name; the message lists the built-in names.
    """
    p = Path(name_or_path)
    if p.is_file():
        return p
    builtin = builtin_protocols()
    key = p.stem if p.suffix in _SUFFIXES and p.parent == Path(".") else (p.name if p.parent == Path(".") else None)
    if key in builtin:
        return builtin[key]
    raise FileNotFoundError(f"no protocol file {name_or_path} and no built-in protocol of that name (built-in: "
                            f"{', '.join(builtin) or 'none'}; `rigctl protocols` lists them)")


def summary(path: Path) -> str:
    """The first line of a protocol's leading comment (TOML ``#`` lines) or docstring (script), "" if none."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError:
        return ""
    for line in lines:
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            return s.lstrip("#").strip()
        if s.startswith(('"""', "'''")):
            return s.strip("\"' ").strip()
        return ""
    return ""
