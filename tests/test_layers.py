"""The package's layers, read from its source with ``ast``: imports point only down, and no module cycles.

Layers, bottom to top: ``bayesmag._src.core`` <- ``bayesmag._src.pipeline`` <- ``bayesmag._src.app``.
A module may import its own layer and the layers below it, never above (function-level imports
count too: a lazy import is still an arrow). The public top-level modules ``bayesmag/*.py`` sit
above all three and may import anything. Cycles are looked for among all ``bayesmag._src``
modules, counting every import of a module (a package's ``__init__`` included).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "bayesmag"
LAYERS = ("core", "pipeline", "app")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, name: str) -> set[str]:
    """Every ``bayesmag...`` module ``path`` imports (absolute or relative), at any depth of the file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "bayesmag"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "bayesmag":
                continue
            out.add(mod)
            out |= {f"{mod}.{a.name}" for a in node.names}      # `from pkg import submodule`
    return out


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in ROOT.rglob("*.py") if ".venv" not in p.parts}
    graph = {}
    for name, path in files.items():
        graph[name] = {m for m in _imports(path, name) if m in files and m != name}
    return graph


GRAPH = _graph()


def _layer(module: str) -> int | None:
    parts = module.split(".")
    if len(parts) >= 3 and parts[1] == "_src" and parts[2] in LAYERS:
        return LAYERS.index(parts[2])
    return None


def test_graph_is_read():
    """The walker sees the package (a broken walker would pass every other test)."""
    assert "bayesmag._src.core.physics" in GRAPH
    assert "bayesmag._src.core.data" in GRAPH["bayesmag._src.app.job"]
    assert sum(map(len, GRAPH.values())) > 100


@pytest.mark.parametrize("layer", LAYERS)
def test_imports_point_down(layer):
    up = sorted(f"{m} -> {i}" for m, deps in GRAPH.items() if _layer(m) == LAYERS.index(layer)
                for i in deps if _layer(i) is not None and _layer(i) > _layer(m))
    assert not up, "upward imports:\n" + "\n".join(up)


def test_library_does_not_import_top_level_modules():
    """``bayesmag._src`` never imports the public ``bayesmag`` namespace (it sits on top)."""
    bad = sorted(f"{m} -> {i}" for m, deps in GRAPH.items() if _layer(m) is not None
                 for i in deps if not i.startswith("bayesmag._src"))
    assert not bad, "\n".join(bad)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
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
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _without_package_inits(graph):
    """Drop the edges of a package ``__init__`` to its own submodules (re-exports, not a cycle)."""
    return {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}


def test_no_import_cycles():
    src = {m: {d for d in deps if d.startswith("bayesmag._src")} for m, deps in GRAPH.items()
           if m.startswith("bayesmag._src")}
    cycles = _cycles(_without_package_inits(src))
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
