"""The code's shape: no import cycles (imports inside functions included), small modules.

The import graph is read from the source (every ``import`` / ``from … import`` anywhere
in a module, including inside functions, where a cycle hides at import time but is a
cycle of dependencies all the same). Two graphs are checked: modules, and the
subpackages of ``eventrecon`` (``eventrecon.data`` → ``eventrecon.events`` is fine,
``events`` → ``data`` as well would be a cycle).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"eventrecon": ROOT / "src" / "eventrecon", "baselines": ROOT / "baselines"}
MAX_LINES = 800


def _modules() -> dict[str, Path]:
    mods = {}
    for root in PACKAGES.values():
        for path in root.rglob("*.py"):
            parts = path.relative_to(root.parent).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            mods[name] = path
    return mods


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_pkg: bool) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        parts = module.split(".") if is_pkg else module.split(".")[:-1]
        parts = parts[: len(parts) - node.level + 1]
        base = ".".join([*parts, base] if base else parts)
    return [f"{base}.{a.name}" for a in node.names] + [base]


def import_graph() -> dict[str, set[str]]:
    """``module -> modules of this project it imports`` (anywhere in its source)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            for target in _targets(node, name, is_pkg):
                while target and target not in mods:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on_stack.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def _subpackage(module: str) -> str:
    """``eventrecon.data.layout`` → ``eventrecon.data``; top-level modules are their own."""
    parts = module.split(".")
    return ".".join(parts[:2])


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_import_cycle():
    assert cycles(import_graph()) == []


def test_no_subpackage_import_cycle():
    graph: dict[str, set[str]] = {}
    for mod, deps in import_graph().items():
        src = _subpackage(mod)
        graph.setdefault(src, set()).update(_subpackage(d) for d in deps if _subpackage(d) != src)
    for deps in list(graph.values()):
        for d in deps:
            graph.setdefault(d, set())
    # the package's own __init__ (resolvers, constants) is imported by everything
    graph.pop("eventrecon", None)
    for deps in graph.values():
        deps.discard("eventrecon")
    assert cycles(graph) == []


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_modules_are_at_most_400_lines(package: str):
    long = {str(p.relative_to(ROOT)): n for p in PACKAGES[package].rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_docstrings_cite_only_files_in_the_repository():
    cited = re.compile(r"(?<![\w/])(method|design)\.md|\.\./shared")
    outside = [str(p.relative_to(ROOT)) for pkg in PACKAGES.values() for p in pkg.rglob("*.py")
               if cited.search(p.read_text())]
    assert outside == []
    assert (ROOT / "docs" / "method.md").is_file() and (ROOT / "docs" / "architecture.md").is_file()
