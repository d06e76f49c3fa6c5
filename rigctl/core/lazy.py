"""Public names of a package, re-exported from its private modules on first use (PEP 562).

A package ``__init__`` lists its public API once, as ``{name: module}``; :func:`lazy_exports` gives the module its
``__all__``, ``__getattr__`` and ``__dir__``, so ``from rigctl.storage import open_session`` works without importing
every module of the package (and its heavy dependencies: h5py, pynwb, numba, scikit-learn) when only one is used.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[list[str], Callable[[str], Any],
                                                                     Callable[[], list[str]]]:
    """``(__all__, __getattr__, __dir__)`` for ``package`` whose public names live in the modules ``exports`` maps
    them to (``{"open_session": "rigctl.storage.session"}``). ``__getattr__`` imports the module on first use and
    raises AttributeError for any other name."""
    names = sorted(exports)

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    def __dir__() -> list[str]:
        return names

    return list(names), __getattr__, __dir__
