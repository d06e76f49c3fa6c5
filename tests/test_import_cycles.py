"""No import cycle inside rigctl or the GUI: every module's imports, inside functions and under ``TYPE_CHECKING``
included, form a graph without cycles, so each package's modules stack in layers (the intra-package ``layers``
contracts in pyproject.toml hold the order; import-linter cannot find cycles in general, so this test does). The
graph is grimp's, the one import-linter checks."""

from __future__ import annotations

import grimp


def strongly_connected(graph: grimp.ImportGraph) -> list[list[str]]:
    """The graph's import cycles: its strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_the_cycle_finder_finds_cycles():
    graph = grimp.ImportGraph()
    for module in ("p", "p.a", "p.b", "p.c", "p.d"):
        graph.add_module(module)
    for importer, imported in (("p.a", "p.b"), ("p.b", "p.c"), ("p.c", "p.a"), ("p.d", "p.a"), ("p", "p.d")):
        graph.add_import(importer=importer, imported=imported)
    assert strongly_connected(graph) == [["p.a", "p.b", "p.c"]]
    graph.remove_import(importer="p.c", imported="p.a")
    assert strongly_connected(graph) == []


def test_no_import_cycle_inside_rigctl():
    graph = grimp.build_graph("rigctl", "rigctl_gui", cache_dir=None)
    assert len(graph.modules) > 100
    assert strongly_connected(graph) == []


def test_every_private_module_is_closed_to_the_faces():
    """pyproject.toml's ``faces-public-api`` contract names every private (``_x``) module outside the faces, so a
    new one cannot be imported by the CLI, the GUI or the server by being left off the list."""
    import fnmatch
    import tomllib
    from pathlib import Path

    config = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    contract = next(c for c in config["tool"]["importlinter"]["contracts"] if c["id"] == "faces-public-api")
    faces = tuple(contract["source_modules"])
    graph = grimp.build_graph("rigctl", "rigctl_gui", cache_dir=None)
    private = [m for m in graph.modules if m.rsplit(".", 1)[-1].startswith("_") and not m.endswith("__")
               and not m.startswith(faces)]
    assert private, "no private module found: the scan is broken"

    def covered(module: str) -> bool:
        # import-linter's wildcards stand for whole segments: `*` one, `**` any number
        return any(fnmatch.fnmatchcase(module, pattern.replace("**", "*")) and
                   ("**" in pattern or module.count(".") == pattern.count("."))
                   for pattern in contract["forbidden_modules"])

    assert [m for m in sorted(private) if not covered(m)] == []
