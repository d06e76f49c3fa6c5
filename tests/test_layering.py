"""The layering rules (docs/architecture.md), enforced in two ways that do not overlap:

- between rigctl's own packages, from the source: the import-linter contracts in pyproject.toml (``lint-imports``,
  run by scripts/test.sh), which read every import statement, those inside functions too;
  :func:`test_the_contracts_catch_an_import_inside_a_function` is their negative control;
- what static analysis cannot see, at run time: which third-party modules importing a layer actually loads (a
  dependency that pulls in Qt, a plugin loaded by name). The layers are imported, every module of each
  (pkgutil.walk_packages), one after another in one fresh interpreter, each after those it may use, and a layer's
  test fails if a module it must not use shows up in ``sys.modules`` while its modules are imported (or was there
  before it); the message names the forbidden module and the first module of the layer whose import brought it
  in. Rules: nothing in rigctl but ``rigctl.cli.gui`` loads Qt, pyqtgraph or the GUI package; the core, the file
  formats, the encoder and the analyses never load serial or Modbus.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

_PROBE = textwrap.dedent("""
    import importlib, json, pkgutil, sys, traceback
    layers = json.loads(sys.argv[1])  # [[package, skip], ...] in order: each after those before it

    out = {}
    for package, skip in layers:
        before = sorted(sys.modules)  # loaded before the layer (by a layer before it, or by Python)
        seen, culprit, errors = set(before), {}, {}
        pkg = importlib.import_module(package)
        names = [package] + [m.name for m in pkgutil.walk_packages(pkg.__path__, package + ".")
                             if not any(m.name == s or m.name.startswith(s + ".") for s in skip)]
        for name in names:
            try:
                importlib.import_module(name)
            except Exception as exc:  # a module of the layer that cannot be imported at all
                errors[name] = f"{type(exc).__name__}: {exc}"
            for m in sorted(set(sys.modules) - seen):  # in the order the layer's modules brought them in
                culprit[m] = name
                seen.add(m)
        out[package] = {"modules": names, "culprit": culprit, "errors": errors, "before": before}
    print(json.dumps(out))
""")

#: layer -> (modules of it not checked, third-party modules it must not load), in the order the probe imports them:
#: each layer only after the layers it may use, so that whatever shows up while a layer's modules are imported was
#: loaded by them (a module loaded by an earlier layer is that layer's failure, and is named as such)
_NO_WIRE = ["serial", "pymodbus"]
RULES: dict[str, tuple[list[str], list[str]]] = {
    "rigctl.core": ([], _NO_WIRE),
    "rigctl.storage": ([], _NO_WIRE),
    "rigctl.encoding": ([], _NO_WIRE),
    "rigctl.analysis": ([], _NO_WIRE),
    "rigctl": (["rigctl.cli.gui"], ["PySide6", "pyqtgraph", "rigctl_gui"]),
}


def probe(layers: dict[str, list[str]]) -> dict:
    """Import every module of each layer (package -> the modules of it not checked), in the given order, in one
    fresh interpreter (one interpreter start and one import of numpy, h5py, scikit-learn... instead of one per layer):
    per layer, every module that came in while its modules were imported (and the first of them whose import brought
    it in), and every module that had come in before it."""
    arg = json.dumps([[package, skip] for package, skip in layers.items()])
    proc = subprocess.run([sys.executable, "-c", _PROBE, arg], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"importing {list(layers)} failed:\n{proc.stderr[-3000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


def judge(out: dict, forbidden: list[str]) -> tuple[dict[str, str], list[str]]:
    """A layer's probe record against its ``forbidden`` modules (each with its submodules): {forbidden module: the
    first module of the layer whose import brought it in}, and the forbidden modules already loaded before it."""

    def hits(modules) -> set[str]:
        return {f for f in forbidden for m in modules if m == f or m.startswith(f + ".")}

    before = hits(out["before"])
    culprit: dict[str, str] = {}
    for module, name in out["culprit"].items():  # in import order: the first culprit of each is kept
        for f in hits([module]) - before:
            culprit.setdefault(f, name)
    return culprit, sorted(before)


@pytest.fixture(scope="module")
def probed() -> dict:
    """The probe of every layer of :data:`RULES`, in that order (one interpreter for the rules and their negative
    control)."""
    return probe({package: skip for package, (skip, _) in RULES.items()})


@pytest.mark.parametrize("layer", list(RULES))
def test_layer_imports_nothing_forbidden(layer, probed):
    out = probed[layer]
    assert len(out["modules"]) >= 1
    assert not out["errors"], f"modules of {layer} that cannot be imported: {out['errors']}"
    culprit, before = judge(out, RULES[layer][1])
    bad = [f"{f} (first pulled in by importing {m})" for f, m in sorted(culprit.items())]
    bad += [f"{f} (already loaded by a layer imported before it)" for f in before]
    assert not bad, f"{layer} must not import: " + "; ".join(bad)


def test_the_probe_sees_a_forbidden_import(probed):
    """Negative control: the probe reports what a layer does import (numpy is everywhere in storage), and a forbidden
    module an earlier layer loaded against the later layer too, never lost (one probe: one interpreter; the layers
    core, storage, encoding in that order, as :data:`RULES` imports them)."""
    assert list(RULES)[:3] == ["rigctl.core", "rigctl.storage", "rigctl.encoding"]
    assert judge(probed["rigctl.core"], ["h5py"]) == ({}, [])
    culprit, before = judge(probed["rigctl.storage"], ["h5py", "serial"])
    assert "h5py" in culprit and not before
    assert culprit["h5py"].startswith("rigctl.storage")
    culprit, before = judge(probed["rigctl.encoding"], ["h5py"])
    assert before == ["h5py"] and not culprit


def test_the_contracts_catch_an_import_inside_a_function(tmp_path):
    """Negative control of the import contracts: ``lint-imports`` on a copy of the package whose dataset generator
    imports the acquisition layer inside a function (as simulation/dataset.py once did) names that import."""
    shutil.copytree(REPO / "rigctl", tmp_path / "rigctl", ignore=shutil.ignore_patterns("__pycache__", "arduino"))
    (tmp_path / "rigctl_gui").symlink_to(REPO / "gui")
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    module = tmp_path / "rigctl" / "simulation" / "dataset.py"
    module.write_text(module.read_text() + "\n\ndef _plan(path):\n    from rigctl.acquisition.protocol import "
                      "load_protocol\n\n    return load_protocol(path).plan()\n")
    lint = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    run = subprocess.run([sys.executable, "-c", lint, "--no-cache"], cwd=tmp_path, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(tmp_path)}, timeout=300)
    assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-3000:]
    assert "rigctl.simulation is not allowed to import rigctl.acquisition" in run.stdout
    assert "rigctl.simulation.dataset -> rigctl.acquisition.protocol" in run.stdout
