"""The shape of the code: the import graph of hmflow's packages has no cycle, no import runs up
a layer, hmcore never imports Prefect, and no module outgrows one concept.

Read from the source with :mod:`ast` (nothing is imported), so the graph is the one a reader
sees: every ``import`` and ``from ... import`` of a project module, at module top or inside a
function alike.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hmcore", "tasks", "flows", "storage", "hmflow", "deployments")
LAYERS = (
    ("hmcore.errors", "hmcore.units", "hmcore.ordering", "storage"),
    ("hmcore.eclipse", "hmcore.simulation", "hmcore.fields"),
    ("hmcore.model",),
    ("hmcore.scoring",),
    ("hmcore.calibration",),
    ("hmcore.diagnosis",),
    ("hmcore.scenarios",),
    ("hmcore.reporting", "hmcore.cases"),
    ("tasks",),
    ("flows",),
    ("deployments",),
    ("hmflow",),
)
"""Lowest first: a module may import its own layer and those below it, never one above."""
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    mods = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


def _imports(name: str, path: Path, mods: dict[str, Path]) -> set[str]:
    """The project modules (and top-level third-party names) ``name`` imports."""
    found = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                       for a in node.names]
        else:
            continue
        for target in targets:
            found.add(target)
    return found


def _own(target: str, mods: dict[str, Path]) -> str | None:
    while target and target not in mods:
        target = target.rpartition(".")[0]
    return target or None


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        own = {_own(t, mods) for t in _imports(name, path, mods)}
        graph[name] = {m for m in own if m and m != name}
    return graph


def _layer(module: str) -> int | None:
    for k, layer in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in layer):
            return k
    return None


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_every_module_has_a_layer():
    assert [m for m in _graph() if _layer(m) is None and "." in m] == []


def test_the_import_graph_has_no_cycle():
    assert _cycles(_graph()) == []


def test_no_import_runs_up_a_layer():
    graph = _graph()
    upward = [f"{a} -> {b}" for a, targets in sorted(graph.items()) for b in sorted(targets)
              if _layer(a) is not None and _layer(b) is not None and _layer(b) > _layer(a)]
    assert upward == []


def test_hmcore_never_imports_prefect():
    mods = _modules()
    offenders = sorted(name for name, path in mods.items() if name.startswith("hmcore")
                       and any(t == "prefect" or t.startswith("prefect.")
                               or t.startswith("prefect_")
                               for t in _imports(name, path, mods)))
    assert offenders == []


def test_no_module_outgrows_one_concept():
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert long == {}


@pytest.mark.parametrize("graph, cycle", [
    ({"a": {"b"}, "b": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
])
def test_the_cycle_finder_finds_a_cycle(graph, cycle):
    assert _cycles(graph) == cycle
