"""No import cycle between the modules of ``rasterserver`` and the built-in plugins.

The graph is read from the source with :mod:`ast`, not by importing: an edge is an import
that runs when the module is loaded (module level, also inside ``try`` or ``if``), not one
inside a function (deferred on purpose) or under ``if TYPE_CHECKING:`` (never run). ``import
a.b`` and ``from a import b`` (``b`` a module) point at ``a.b`` itself: the implicit load of a
package's ``__init__`` on the way is left out, as a package re-exporting its own submodules
is no cycle of design.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: Source folder -> the package name it installs as (pyproject.toml's package-dir).
PACKAGES = {"rasterserver": "rasterserver", "plugins": "rasterserver_plugins"}

#: Cycles that only the restructuring of issue 17 (catalogue, services) can break, each as
#: the sorted tuple of its modules. Empty: keep it so.
KNOWN_CYCLES: set[tuple[str, ...]] = set()


def module_files() -> dict[str, Path]:
    """Every module of the packages by dotted name (a package by its own name)."""
    found: dict[str, Path] = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join((package, *parts))] = path
    return found


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _load_time_imports(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """The import statements of ``body`` that run on import: not in def, class bodies are."""
    for node in body:
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _load_time_imports(node.body)
            yield from _load_time_imports(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, *(h.body for h in node.handlers), node.orelse,
                          node.finalbody):
                yield from _load_time_imports(block)
        elif isinstance(node, ast.With | ast.ClassDef):
            yield from _load_time_imports(node.body)
        # FunctionDef, AsyncFunctionDef: run when called, not when loaded


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that loading module ``name`` (file ``path``) imports."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in _load_time_imports(tree.body):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
            continue
        base = node.module or ""
        if node.level:
            anchor = name.split(".")
            anchor = anchor if is_package else anchor[:-1]
            anchor = anchor[: len(anchor) - (node.level - 1)]
            base = ".".join([*anchor, *([base] if base else [])])
        for alias in node.names:
            sub = f"{base}.{alias.name}"
            targets.add(sub if sub in modules else base)
    return {t for t in targets if t in modules and t != name}


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports when loaded."""
    files = module_files()
    names = set(files)
    return {name: imports_of(name, path, names) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[tuple[str, ...]] = []

    def visit(node: str) -> None:
        # recursive: the graph is a few hundred modules deep at most
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(graph.get(node, ())):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(tuple(sorted(component)))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def test_the_graph_is_read() -> None:
    """Guard against a walker that sees nothing: known edges and non-edges are found."""
    graph = import_graph()
    assert "rasterserver.archive" in graph["rasterserver.pipeline"]
    assert "rasterserver_plugins.symmetry_line" in graph["rasterserver_plugins.spinal_midline"]
    # under TYPE_CHECKING only: no edge
    assert "rasterserver.optics" not in graph["rasterserver.commands.reconstruct"]


def test_the_cycle_finder_finds_cycles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert cycles(graph) == [("a", "b", "c")]


def test_relative_imports_are_resolved(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    init = tmp_path / "pkg" / "__init__.py"
    init.write_text("from . import a\nfrom .b import thing\n")
    mod = tmp_path / "pkg" / "a.py"
    mod.write_text(
        "from typing import TYPE_CHECKING\nfrom . import b\nif TYPE_CHECKING:\n"
        "    from .c import x\ndef f():\n    from .c import y\n"
    )
    modules = {"pkg", "pkg.a", "pkg.b", "pkg.c"}
    assert imports_of("pkg", init, modules) == {"pkg.a", "pkg.b"}
    assert imports_of("pkg.a", mod, modules) == {"pkg.b"}


def test_no_import_cycle() -> None:
    found = set(cycles(import_graph()))
    new = sorted(found - KNOWN_CYCLES)
    assert not new, "import cycles (break them; see the module docstring):\n" + "\n".join(
        " <-> ".join(c) for c in new
    )


def test_known_cycles_still_exist() -> None:
    """A known cycle that is gone must leave the list, so that it cannot come back unseen."""
    gone = KNOWN_CYCLES - set(cycles(import_graph()))
    assert not gone, f"no longer cycles, remove them from KNOWN_CYCLES: {sorted(gone)}"
