"""No import circles: no module of the package imports one that imports it
back, directly or through others (issue 37).

The graph is read from the source with :mod:`ast`, nothing is imported:
every import of a package module, at module level, in a function or under
``if TYPE_CHECKING:``, is an edge. ``from pkg import name`` imports the
submodule ``pkg.name`` when there is one, else the module that ``pkg``'s
``__init__`` takes *name* from, else ``pkg``'s ``__init__``. A package's
``__init__`` re-exporting its own submodules is not an edge: it runs after
them, and they may import their siblings through it. (The layers, which
module may import which, are checked in ``tests/test_package.py``.)
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "kikuchipy_geomdic"


def _modules(package: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted name of every module under *package*: (its file, whether it
    is a package's ``__init__``)."""
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        is_init = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_init else parts)] = (path, is_init)
    return out


def _absolute(module: str | None, level: int, here: str, is_init: bool) -> str:
    """The absolute module of ``from <level dots><module> import ...`` in
    module *here*."""
    if not level:
        return module or ""
    base = here.split(".")
    base = base[: len(base) - level + 1] if is_init else base[: len(base) - level]
    return ".".join(base + ([module] if module else []))


def _reexports(modules) -> dict[str, dict[str, tuple[str, str]]]:
    """For each package, the module its ``__init__`` takes each name from,
    and the name there."""
    out = {}
    for name, (path, is_init) in modules.items():
        if not is_init:
            continue
        table = out.setdefault(name, {})
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ImportFrom):
                source = _absolute(node.module, node.level, name, True)
                for alias in node.names:
                    table[alias.asname or alias.name] = (source, alias.name)
    return out


def _target(package: str, name: str, modules, reexports, seen=()) -> str:
    """The module that ``from package import name`` imports."""
    if f"{package}.{name}" in modules:
        return f"{package}.{name}"
    source, original = reexports.get(package, {}).get(name, (None, name))
    if source in modules and source != package and source not in seen:
        if source in reexports:  # a package re-exporting a subpackage's name
            return _target(source, original, modules, reexports, (*seen, package))
        return source
    return package


def import_graph(package: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (see the module docstring)."""
    modules = _modules(package)
    reexports = _reexports(modules)
    graph = {}
    for here, (path, is_init) in modules.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom):
                source = _absolute(node.module, node.level, here, is_init)
                if source in modules:
                    edges |= {_target(source, a.name, modules, reexports) for a in node.names}
        edges.discard(here)
        if is_init:
            edges = {e for e in edges if not e.startswith(f"{here}.")}
        graph[here] = edges
    return graph


def _shortest_circle(graph, component: set[str], start: str) -> list[str] | None:
    """The shortest circle ``[start, ..., start]`` inside *component*."""
    previous, frontier = {}, [start]
    while frontier and start not in previous:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & component):
                if w not in previous:
                    previous[w] = v
                    nxt.append(w)
        frontier = nxt
    if start not in previous:
        return None
    path, v = [start], previous[start]
    while v != start:
        path.append(v)
        v = previous[v]
    return [start, *reversed(path[1:]), start]


def circles(graph: dict[str, set[str]]) -> list[tuple[list[str], set[str]]]:
    """Each strongly connected component of *graph* (Tarjan's algorithm)
    with more than one module, and its shortest circle ``[a, ..., a]``."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for component in components:
        found = [_shortest_circle(graph, component, v) for v in sorted(component)]
        out.append((min(found, key=len), component))
    return sorted(out, key=lambda c: c[0])


def _named(found) -> str:
    lines = []
    for circle, component in found:
        line = " -> ".join(circle)
        if len(component) > len(circle) - 1:
            line += f" (in a circle too: {', '.join(sorted(component - set(circle)))})"
        lines.append(line)
    return "\n".join(lines)


def test_no_import_circles():
    graph = import_graph(PACKAGE)
    assert len(graph) > 20
    found = circles(graph)
    if found:
        pytest.fail("Import circles:\n" + _named(found), pytrace=False)


def test_circles_are_found(tmp_path):
    """The check itself, on a small package: a circle of three through a
    function-level and a ``from . import`` import is found; a package
    ``__init__`` re-exporting its submodules, which import each other
    through it, is not a circle."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "from pkg.sub import f\nfrom pkg.sub import kk as k\n",
        "a.py": "from pkg import b\n",
        "b.py": "def g():\n    from .c import h\n",
        "c.py": "import pkg.a\n",
        "sub/__init__.py": "from pkg.sub.x import f\nfrom .y import k as kk\n",
        "sub/x.py": "from pkg.sub import kk\ndef f(): ...\n",
        "sub/y.py": "def k(): ...\n",
        "d.py": "from pkg.sub import f\nfrom pkg import k\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    graph = import_graph(pkg)
    assert graph["pkg"] == set()
    assert graph["pkg.sub"] == set()
    assert graph["pkg.sub.x"] == {"pkg.sub.y"}
    assert graph["pkg.d"] == {"pkg.sub.x", "pkg.sub.y"}
    assert [c for c, _ in circles(graph)] == [["pkg.a", "pkg.b", "pkg.c", "pkg.a"]]
    # A name re-exported from a sibling that imports the module back
    (pkg / "sub/y.py").write_text("from pkg.sub import f\ndef k(): ...\n")
    assert [c for c, _ in circles(import_graph(pkg))] == [
        ["pkg.a", "pkg.b", "pkg.c", "pkg.a"],
        ["pkg.sub.x", "pkg.sub.y", "pkg.sub.x"],
    ]
