"""No import cycle between the modules of the installed packages: ``rasterserver``, the
built-in plugins and the migrations.

The graph is read from the source with :mod:`ast`, not by importing: an edge is an import
that runs when the module is loaded (module level, also inside ``try`` or ``if``), not one
under ``if TYPE_CHECKING:`` (never run). ``import a.b`` and ``from a import b`` (``b`` a
module) point at ``a.b`` itself: the implicit load of a package's ``__init__`` on the way is
left out, as a package re-exporting its own submodules is no cycle of design.

Two graphs: the load-time one (imports inside functions left out) must have no cycle at all.
The full one (imports inside functions too: deferred to start faster, but still a dependency
of design, as ``archive`` and ``repair`` importing each other was) must have none either.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: Source folder -> the package name it installs as (pyproject.toml's package-dir).
PACKAGES = {"rasterserver": "rasterserver", "plugins": "rasterserver_plugins",
            "migrations": "rasterserver_migrations"}

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


def _load_time_imports(body: list[ast.stmt], *, deferred: bool = False,
                       ) -> Iterator[ast.Import | ast.ImportFrom]:
    """The import statements of ``body`` that run on import: not in def (unless
    ``deferred``), class bodies are; never those under ``if TYPE_CHECKING:``."""
    for node in body:
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _load_time_imports(node.body, deferred=deferred)
            yield from _load_time_imports(node.orelse, deferred=deferred)
        elif isinstance(node, ast.Try):
            for block in (node.body, *(h.body for h in node.handlers), node.orelse,
                          node.finalbody):
                yield from _load_time_imports(block, deferred=deferred)
        elif isinstance(node, ast.With | ast.AsyncWith | ast.ClassDef | ast.For | ast.AsyncFor
                        | ast.While):
            yield from _load_time_imports([*node.body, *getattr(node, "orelse", [])],
                                          deferred=deferred)
        elif deferred and isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield from _load_time_imports(node.body, deferred=deferred)
        # otherwise FunctionDef, AsyncFunctionDef: run when called, not when loaded


def imports_of(name: str, path: Path, modules: set[str], *, deferred: bool = False,
               ) -> set[str]:
    """The modules of ``modules`` that loading module ``name`` (file ``path``) imports (with
    ``deferred``: or that its functions import)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in _load_time_imports(tree.body, deferred=deferred):
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


def import_graph(*, deferred: bool = False) -> dict[str, set[str]]:
    """Module -> the package modules it imports when loaded (``deferred``: or ever)."""
    files = module_files()
    names = set(files)
    return {name: imports_of(name, path, names, deferred=deferred)
            for name, path in files.items()}


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
    found = cycles(import_graph())
    assert not found, "import cycles (break them; see the module docstring):\n" + "\n".join(
        " <-> ".join(c) for c in found
    )


def test_no_cycle_through_deferred_imports() -> None:
    found = cycles(import_graph(deferred=True))
    assert not found, "cycles through imports in functions (break them):\n" + "\n".join(
        " <-> ".join(c) for c in found
    )


def test_the_catalogue_ingest_and_integrity_layers_are_acyclic_even_deferred() -> None:
    """The modules issue 17 took out of the archive hub depend on each other one way."""
    graph = import_graph(deferred=True)
    assert "rasterserver.archive" not in graph["rasterserver.repair"]
    assert "rasterserver.archive" not in graph["rasterserver.integrity"]
    assert "rasterserver.archive" not in graph["rasterserver.ingest"]
    layer = {m for m in graph if m.startswith(("rasterserver.catalog", "rasterserver.store"))}
    assert not {m for c in cycles(graph) for m in c} & layer
    hashing = graph["rasterserver.hashing"]
    assert not hashing, f"the ground floor imports {sorted(hashing)}"


def test_deferred_imports_are_read(tmp_path: Path) -> None:
    mod = tmp_path / "a.py"
    mod.write_text("for _ in ():\n    import d\n"
                   "def f():\n    import b\n    for _ in ():\n        import c\n")
    assert imports_of("a", mod, {"a", "b", "c", "d"}) == {"d"}
    assert imports_of("a", mod, {"a", "b", "c", "d"}, deferred=True) == {"b", "c", "d"}
