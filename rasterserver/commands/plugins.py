"""``rasterserver plugins``: list the installed stage plugins, broken ones included."""

from __future__ import annotations

import dataclasses
import json
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from rasterserver.registry import GraphEdge, PluginInfo

#: :data:`rasterserver.registry.STAGE_GROUP`, written out: the registry loads NumPy and
#: pydantic, which every command's `--help` would pay for (tests/commands/test_cli_imports.py
#: checks that the two agree).
STAGE_GROUP = "rasterserver.stages"

_HELP = (
    "List every installed stage plugin: name, stage kind, algorithm version, input and output "
    "record kinds, the package (name and version) that provides it, and its status.\n\n"
    f"Stage plugins are found through the '{STAGE_GROUP}' entry-point group, built-in ones "
    "included. A plugin that fails to import or is not a valid stage is shown as 'broken' "
    "with the reason; it cannot be used but does not affect the others, and the command still "
    "exits with 0.\n\n"
    "With --graph, the stage graph instead: which record kinds each stage kind takes and "
    "gives, as the pipeline resolves chains by record types (* marks the default plugin of a "
    "kind). A package that adds a stage kind appears in the graph where its records fit."
)

_COLUMNS = ("NAME", "STAGE", "VERSION", "INPUT", "OUTPUT", "PACKAGE", "STATUS")


def _row(info: PluginInfo) -> tuple[str, ...]:
    package = " ".join(p for p in (info.package, info.package_version) if p) or "?"
    return (
        info.name,
        info.stage or "?",
        info.version or "?",
        info.input_kind or "?",
        info.output_kind or "?",
        package,
        info.status,
    )


def _table(infos: list[PluginInfo]) -> str:
    # Plain aligned text rather than a rich table: rich wraps and truncates cells to the
    # terminal width, which breaks long reasons and grep.
    rows = [_COLUMNS, *(_row(info) for info in infos)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_COLUMNS))]
    lines = []
    for info, row in zip([None, *infos], rows, strict=True):
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
        if info is not None and not info.ok:
            lines.append(f"    reason: {info.error}")
    return "\n".join(lines)


def _assembled(kind: str) -> str:
    """How the service assembles records of ``kind`` that no stage makes (e.g. the comparison's
    input from two acquisitions), as the record class declares it in ``assembled_from``."""
    from rasterserver.records import record_types

    cls = record_types().get(kind)
    what = getattr(cls, "assembled_from", "") if cls is not None else ""
    return f"  (assembled from {what})" if what else ""


def _graph(edges: list[GraphEdge]) -> str:
    """Draw the graph as a tree from the record kinds nothing makes (the camera image)."""
    by_input: dict[str, list[GraphEdge]] = {}
    for edge in edges:
        by_input.setdefault(edge.input_kind, []).append(edge)
    made = {edge.output_kind for edge in edges}
    roots = [kind for kind in by_input if kind not in made] or sorted(by_input)[:1]
    lines: list[str] = []

    def walk(kind: str, indent: str, seen: frozenset[str]) -> None:
        children = by_input.get(kind, [])
        for i, edge in enumerate(children):
            last = i == len(children) - 1
            mark = "*" if edge.default else " "
            lines.append(
                f"{indent}{'└─' if last else '├─'} {edge.stage}: {edge.plugin} "
                f"{edge.version}{mark} → {edge.output_kind}"
            )
            if edge.output_kind not in seen:
                walk(edge.output_kind, indent + ("   " if last else "│  "), seen | {kind})

    for root in roots:
        lines.append(root + _assembled(root))
        walk(root, "", frozenset({root}))
    return "\n".join(lines)


def plugins(
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a JSON list of objects instead of a table.")
    ] = False,
    stage: Annotated[
        str | None,
        typer.Option(
            "--stage",
            metavar="KIND",
            help="Only plugins of this stage kind (peaks, lines, order, numbers, points, "
            "surface, mesh, or any other).",
            show_default=False,
        ),
    ] = None,
    graph: Annotated[
        bool, typer.Option("--graph", help="Show the stage graph by record kinds.")
    ] = False,
) -> None:
    from rasterserver.registry import Registry

    registry = Registry(warn_broken=False).discover()  # listed below instead
    if graph:
        edges = registry.graph()
        if as_json:
            typer.echo(json.dumps([dataclasses.asdict(e) for e in edges], indent=2))
        else:
            typer.echo(_graph(edges) if edges else "no working stage plugins installed")
        return
    infos = registry.infos(stage)
    if as_json:
        typer.echo(json.dumps([info.to_dict() for info in infos], indent=2))
    elif infos:
        typer.echo(_table(infos))
    elif stage is None:
        typer.echo(f"no stage plugins installed (entry-point group {STAGE_GROUP})")
    else:
        kinds = ", ".join(registry.stage_kinds()) or "none"
        typer.echo(f"no stage plugins of kind {stage!r} (installed kinds: {kinds})")
    if stage is not None:
        unknown = [info for info in registry.infos() if info.stage is None]
        if unknown:
            # Their kind is unknown because they did not load: say so rather than hide them.
            typer.echo(
                f"note: {len(unknown)} broken plugin(s) of unknown stage kind not shown "
                f"({', '.join(info.name for info in unknown)}); run without --stage",
                err=True,
            )


def register(app: typer.Typer) -> None:
    """Add the ``plugins`` command to ``app``."""
    app.command("plugins", help=_HELP)(plugins)
