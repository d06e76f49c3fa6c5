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


_QUOTES = ('"""', "'''")


def _leading_text(lines: list[str]) -> str:
    """The first paragraph of the leading ``#`` comment, or of the leading docstring, joined on one line."""
    out: list[str] = []
    doc = False
    for line in lines:
        s = line.strip()
        if not out and not doc:
            if not s:
                continue
            if s.startswith("#"):
                out.append(s.lstrip("#").strip())
                continue
            if s.startswith(_QUOTES):
                doc = True
                body = s[3:]
                closed = any(q in body for q in _QUOTES)
                for q in _QUOTES:
                    body = body.replace(q, "")
                if body.strip():
                    out.append(body.strip())
                if closed:
                    break
                continue
            break
        if doc:
            if not s or any(q in s for q in _QUOTES):
                for q in _QUOTES:
                    s = s.replace(q, "")
                if s.strip():
                    out.append(s.strip())
                break
            out.append(s)
        elif s.startswith("#") and s.lstrip("#").strip():
            out.append(s.lstrip("#").strip())
        else:
            break
    return " ".join(out)


def summary(path: Path) -> str:
    """The first sentence of a protocol's leading comment (TOML ``#`` lines) or docstring (script), whole even when
    it runs over several lines ("" if none): what ``rigctl protocols`` shows."""
    import re

    try:
        text = _leading_text(path.read_text(encoding="utf-8").splitlines())
    except OSError:
        return ""
    m = re.search(r"(?<!Fig)(?<!Figs)(?<!Eq)(?<!eq)(?<!Ref)(?<=[a-z0-9)\]])[.:](?=\s+[A-Z0-9]|$)", text)
    return text[:m.start()] + "." if m else text
