"""The import graph of common, services and deploy has no cycle.

Every import counts, a function's deferred one too: a cycle broken only by deferring an
import is still two modules that cannot be understood one without the other."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "services", "deploy")


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, packages: tuple[str, ...]) -> dict[str, set[str]]:
    """Module -> the modules of `packages` it imports (a package's `__init__` only where it
    is imported by its own name, not for each of its submodules)."""
    paths = {module_name(root, p): p for pk in packages for p in (root / pk).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for mod, path in paths.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                # `from a import b`: module a.b if there is one, else the names of a
                names = [f"{base}.{a.name}" for a in node.names]
                names = [n if n in paths else base for n in names]
            else:
                continue
            deps |= {n for n in names if n in paths and n != mod}
        graph[mod] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_project_has_no_import_cycle():
    graph = import_graph(ROOT, PACKAGES)
    assert {"deploy.launch.cli", "services.planner.mppi", "common.bus"} <= set(graph)
    assert "deploy.sim.experiment" in graph["deploy.analysis.collisions"]    # edges are seen
    assert cycles(graph) == []


def test_a_cycle_is_found_even_through_a_deferred_import(tmp_path):
    pkg = tmp_path / "pk"
    (pkg / "sub").mkdir(parents=True)
    for f in ("__init__.py", "sub/__init__.py"):
        (pkg / f).write_text("")
    (pkg / "a.py").write_text("from pk.sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..c import g\n    return g\n")
    (pkg / "c.py").write_text("import pk.a\n")
    (pkg / "d.py").write_text("from pk import a\n")                # into the cycle, not of it
    graph = import_graph(tmp_path, ("pk",))
    assert graph["pk.sub.b"] == {"pk.c"} and graph["pk.d"] == {"pk.a"}
    assert cycles(graph) == [["pk.a", "pk.c", "pk.sub.b"]]
    (pkg / "c.py").write_text("import json\n")
    assert cycles(import_graph(tmp_path, ("pk",))) == []
