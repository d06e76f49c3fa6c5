"""The size limits of docs/architecture.md ("Size limits and their named exceptions"): no module of rigctl/ or gui/
over 800 lines, no function over 100 lines, but the units named there with why."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100


def _named_exceptions() -> dict[str, str]:
    """``unit -> kind`` from the table of docs/architecture.md's size-limits section."""
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split("## Size limits and their named exceptions", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `([^`]+)` \| (module|function) \|", section, flags=re.M)
    assert rows, "the size-limits table of docs/architecture.md has no rows"
    return dict(rows)


def _long_functions(node: ast.AST, where: str, found: dict[str, str]) -> None:
    """Add ``where::Class.name`` of every function under ``node`` over the limit to ``found``."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.ClassDef):
            _long_functions(child, f"{where}{child.name}.", found)
        elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if child.end_lineno - child.lineno + 1 > MAX_FUNCTION_LINES:
                found[f"{where}{child.name}"] = "function"
            _long_functions(child, f"{where}{child.name}.", found)


def _oversized() -> dict[str, str]:
    """``unit -> kind`` of every module and function over its limit; functions as ``path::Class.name``."""
    found: dict[str, str] = {}
    for root in ("rigctl", "gui"):
        for path in sorted((REPO / root).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            source = path.read_text()
            if source.count("\n") > MAX_MODULE_LINES:
                found[rel] = "module"
            _long_functions(ast.parse(source), f"{rel}::", found)
    return found


def test_every_oversized_unit_is_named_with_why():
    over, named = _oversized(), _named_exceptions()
    unnamed = sorted(u for u in over if u not in named)
    assert not unnamed, (f"over {MAX_MODULE_LINES} lines (module) or {MAX_FUNCTION_LINES} lines (function) and not "
                         f"named in docs/architecture.md's size limits: {unnamed}; split it, or name it there with why")


def test_no_named_exception_is_stale():
    over, named = _oversized(), _named_exceptions()
    stale = sorted(u for u in named if u not in over)
    assert not stale, f"named as an exception in docs/architecture.md but within the limits now (delete the row): {stale}"
