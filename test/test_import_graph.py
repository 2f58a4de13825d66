"""The package's import graph: no circles (also none through imports inside functions), and the
layers point one way (evaluation and the engine never import the console tools)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("cegc_ros", "msg_adapters")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _graph() -> dict[str, set[str]]:
    modules = {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            for t in targets:
                while t and t not in modules:           # a name inside a module: the module
                    t = t.rpartition(".")[0]
                if t and t != name and not name.startswith(t + ".") and not t == package:
                    graph[name].add(t)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:                    # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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


def test_no_import_circles_even_through_imports_inside_functions():
    assert _cycles(_graph()) == []


def test_the_graph_sees_imports_inside_functions():
    g = _graph()
    assert "cegc_ros.replay" in g["cegc_ros.evaluation.through_node"]     # imported in a function
    assert "cegc_ros.data.codec" in g["cegc_ros.data.views"]


def test_layers_point_one_way():
    g = _graph()
    for name, deps in g.items():
        if not name.startswith("cegc_ros.tools"):
            assert not any(d.startswith("cegc_ros.tools") for d in deps), (name, deps)
        if name.startswith("msg_adapters"):
            assert not any(d.startswith("cegc_ros") for d in deps), (name, deps)
    assert "cegc_ros.baselines" not in g["cegc_ros.engine"]
