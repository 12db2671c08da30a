"""``rasterserver export``: write a processed acquisition's mesh or points for other programs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive
from rasterserver.export import ExportFormat, ExportWhat, select_export
from rasterserver.output_files import check_output
from rasterserver.pipeline import Pipeline
from rasterserver.records_surface import MeshRecord


def export(
    ctx: typer.Context,
    uid: Annotated[str, typer.Argument(help="Acquisition uid.", show_default=False)],
    fmt: Annotated[
        ExportFormat, typer.Option("--format", "-f", help="ply, obj, stl (meshes) or csv.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="File to write.")],
    what: Annotated[
        ExportWhat | None,
        typer.Option(
            help="mesh, points (one per peak) or smoothed (points); default: mesh, or points "
            "for csv.",
        ),
    ] = None,
    plugin: Annotated[
        str | None, typer.Option(help="Use the newest result of this plugin (default: any).")
    ] = None,
) -> None:
    """Export the newest stored mesh or point cloud of an acquisition.

    Meshes go to PLY, OBJ or STL (open3d); point clouds to PLY (with line number, column,
    row and peak area per point) or CSV. Run `rasterserver process UID` first. The file is
    replaced whole or not at all; a path that cannot be written exits 2 before any work.
    """
    check_output(out, what="--out")  # before the archive is opened
    with open_archive(ctx) as archive:
        chosen = select_export(Pipeline(archive), uid, fmt=fmt, what=what, plugin=plugin)
        chosen.write(out)
    record = chosen.record
    if isinstance(record, MeshRecord):
        typer.echo(
            f"mesh of {len(record.vertices)} vertices, {len(record.triangles)} "
            f"triangles written to {out}"
        )
    else:
        typer.echo(f"{len(record)} points written to {out}")


def register(app: typer.Typer) -> None:
    """Add the ``export`` command to ``app``."""
    app.command("export")(export)
