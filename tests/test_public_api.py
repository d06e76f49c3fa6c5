"""The public API: every package re-exports its public names with ``__all__`` (docs/architecture.md), each name
resolves to the object of the module it lives in, an unknown name is an AttributeError, and the re-exports are
lazy (importing a package does not import every module of it and their heavy dependencies)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGES = ["rigctl", "rigctl.core", "rigctl.devices", "rigctl.simulation", "rigctl.acquisition", "rigctl.storage",
            "rigctl.encoding", "rigctl.analysis", "rigctl.operations"]


@pytest.mark.parametrize("name", PACKAGES)
def test_every_public_name_resolves(name):
    pkg = importlib.import_module(name)
    assert pkg.__all__ and len(set(pkg.__all__)) == len(pkg.__all__)
    for public in pkg.__all__:
        obj = getattr(pkg, public)
        home = getattr(obj, "__module__", None)
        if home and home.startswith("rigctl.") and not isinstance(obj, (int, float, str, tuple, dict)):
            # the object is the one of the module it lives in, not a copy
            assert getattr(importlib.import_module(home), getattr(obj, "__name__", public), obj) is obj
        assert public in dir(pkg)
    with pytest.raises(AttributeError):
        pkg.no_such_public_name  # noqa: B018 - the access is the test


def test_re_exports_are_lazy():
    """Importing rigctl.storage for session files does not load the NWB export (pynwb) or the analyses."""
    code = ("import sys, rigctl.storage as s; s.open_session; "
            "print(sorted(m for m in ('pynwb', 'sklearn', 'rigctl.storage.nwb') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


LAZY_PACKAGES = ["rigctl", "rigctl.acquisition", "rigctl.storage", "rigctl.encoding", "rigctl.analysis",
                 "rigctl.simulation", "rigctl.devices", "rigctl.server"]


def _type_checking_view(package: str) -> tuple[dict[str, str], dict[str, str], set[str]]:
    """``(_EXPORTS, {name: module} imported under ``if TYPE_CHECKING:``, names bound outside that block)`` of a
    lazy package's ``__init__``, read from its source."""
    spec = importlib.util.find_spec(package)
    assert spec is not None and spec.origin is not None
    tree = ast.parse(Path(spec.origin).read_text())
    exports: dict[str, str] = {}
    typed: dict[str, str] = {}
    visible: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "_EXPORTS" for t in node.targets):
            exports = ast.literal_eval(node.value)
        elif isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom) and imp.module, ast.dump(imp)
                for alias in imp.names:
                    # `import X as X`: an explicit re-export, which mypy's no_implicit_reexport accepts
                    assert alias.asname == alias.name, f"{package}: {alias.name} re-exported without `as`"
                    typed[alias.name] = imp.module
        else:
            visible |= {t.id for n in ast.walk(node) if isinstance(n, ast.Assign) for t in n.targets
                        if isinstance(t, ast.Name)}
            visible |= {e.id for n in ast.walk(node) if isinstance(n, ast.Assign) for t in n.targets
                        if isinstance(t, ast.Tuple) for e in t.elts if isinstance(e, ast.Name)}
    return exports, typed, visible


@pytest.mark.parametrize("package", LAZY_PACKAGES)
def test_lazy_names_are_typed_for_checkers(package):
    """Every lazily re-exported name is imported under ``if TYPE_CHECKING:`` from the module _EXPORTS names, so
    mypy sees its real type, and the lazy ``__getattr__`` is hidden from checkers (it would make any unknown name
    ``Any``). tests/typing/public_api.py, checked by the project's mypy run, asserts the types themselves."""
    exports, typed, visible = _type_checking_view(package)
    assert exports, f"{package} has no _EXPORTS"
    assert typed == exports
    assert "__getattr__" not in visible, f"{package}'s lazy __getattr__ is visible to type checkers"


def test_version_has_one_value():
    """``rigctl.__version__`` is ``rigctl.core.version``'s (what rigctl's modules import) and pyproject.toml's."""
    import tomllib

    import rigctl
    from rigctl.core import version

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    assert rigctl.__version__ == version.__version__ == project["version"]
