"""The public API: every package re-exports its public names with ``__all__`` (docs/architecture.md), each name
resolves to the object of the module it lives in, an unknown name is an AttributeError, and the re-exports are
lazy (importing a package does not import every module of it and their heavy dependencies)."""

from __future__ import annotations

import importlib
import subprocess
import sys

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
