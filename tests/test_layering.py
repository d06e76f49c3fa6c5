"""The layering rules, enforced: each layer of rigctl is imported, every module of it (pkgutil.walk_packages), in a
fresh interpreter, and the test fails if a module the layer must not use shows up in ``sys.modules``; the message
names the forbidden module and the first module of the layer whose import brought it in.

Rules (docs/architecture.md): ``rigctl.core`` imports nothing else of rigctl's; storage never touches the devices,
the simulator, the acquisition, the encoder, the analysis or Qt; encoding and analysis never touch serial ports,
Modbus, the devices, the simulator, the acquisition, Qt or the GUI; acquisition never imports the simulator (only
the composition root ``rigctl.rigs`` knows every backend); devices never import the simulator, the acquisition or
storage; nothing below the CLI imports the operator layer (``rigctl.operations``); and nothing in rigctl but
``rigctl.cli.gui`` pulls in Qt, pyqtgraph or the ``gui`` package.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

_PROBE = textwrap.dedent("""
    import importlib, json, pkgutil, sys, traceback
    package, skip, forbidden = sys.argv[1], set(json.loads(sys.argv[2])), json.loads(sys.argv[3])

    def hits():
        return {f for f in forbidden for m in list(sys.modules) if m == f or m.startswith(f + ".")}

    culprit, errors = {}, {}
    pkg = importlib.import_module(package)
    names = [package] + [m.name for m in pkgutil.walk_packages(pkg.__path__, package + ".")
                         if not any(m.name == s or m.name.startswith(s + ".") for s in skip)]
    for name in names:
        try:
            importlib.import_module(name)
        except Exception as exc:  # a module of the layer that cannot be imported at all
            errors[name] = f"{type(exc).__name__}: {exc}"
        for f in hits():
            culprit.setdefault(f, name)
    print(json.dumps({"modules": names, "culprit": culprit, "errors": errors}))
""")

#: layer -> (modules of it not checked, forbidden modules)
_ALL_RIGCTL = ["PySide6", "pyqtgraph", "rigctl_gui"]
#: the operator service layer sits above every library layer: only the CLI and the GUI import it
_ABOVE = ["rigctl.operations"]
RULES: dict[str, tuple[list[str], list[str]]] = {
    "rigctl.core": ([], ["rigctl.devices", "rigctl.simulation", "rigctl.acquisition", "rigctl.storage",
                         "rigctl.encoding", "rigctl.analysis", "rigctl.cli", "rigctl.rigs", "rigctl.texture_set"]
                    + _ALL_RIGCTL + _ABOVE),
    "rigctl.storage": ([], ["serial", "pymodbus", "rigctl.devices", "rigctl.simulation", "rigctl.acquisition",
                            "rigctl.encoding", "rigctl.analysis"] + _ALL_RIGCTL + _ABOVE),
    "rigctl.encoding": ([], ["serial", "pymodbus", "rigctl.devices", "rigctl.simulation", "rigctl.acquisition"]
                        + _ALL_RIGCTL + _ABOVE),
    "rigctl.analysis": ([], ["serial", "pymodbus", "rigctl.devices", "rigctl.simulation", "rigctl.acquisition"]
                        + _ALL_RIGCTL + _ABOVE),
    "rigctl.acquisition": ([], ["rigctl.simulation"] + _ALL_RIGCTL + _ABOVE),
    "rigctl.devices": ([], ["rigctl.simulation", "rigctl.acquisition", "rigctl.storage"] + _ALL_RIGCTL + _ABOVE),
    "rigctl.simulation": ([], _ALL_RIGCTL + _ABOVE),
    "rigctl": (["rigctl.cli.gui"], _ALL_RIGCTL),
}


def probe(package: str, skip: list[str], forbidden: list[str]) -> dict:
    """Import every module of ``package`` (but ``skip``) in a fresh interpreter; which ``forbidden`` modules came in."""
    proc = subprocess.run([sys.executable, "-c", _PROBE, package, json.dumps(skip), json.dumps(forbidden)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"importing {package} failed:\n{proc.stderr[-3000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("layer", list(RULES))
def test_layer_imports_nothing_forbidden(layer):
    skip, forbidden = RULES[layer]
    out = probe(layer, skip, forbidden)
    assert len(out["modules"]) >= 1
    assert not out["errors"], f"modules of {layer} that cannot be imported: {out['errors']}"
    bad = [f"{f} (first pulled in by importing {m})" for f, m in sorted(out["culprit"].items())]
    assert not bad, f"{layer} must not import: " + "; ".join(bad)


def test_the_probe_sees_a_forbidden_import():
    """Negative control: the probe reports what a layer does import (numpy is everywhere in storage)."""
    out = probe("rigctl.storage", [], ["numpy"])
    assert "numpy" in out["culprit"]
