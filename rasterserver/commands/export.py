"""``rasterserver export``: write a processed acquisition's mesh or points for other programs."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive
from rasterserver.errors import InputError
from rasterserver.export import write_mesh, write_points
from rasterserver.pipeline import Pipeline
from rasterserver.records_surface import MeshRecord, Points, Surface


class ExportFormat(StrEnum):
    """File format."""

    ply = "ply"
    obj = "obj"
    stl = "stl"
    csv = "csv"


class ExportWhat(StrEnum):
    """Which result to export."""

    mesh = "mesh"
    points = "points"
    smoothed = "smoothed"


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
    row and peak area per point) or CSV. Run `rasterserver process UID` first.
    """
    what = what or (ExportWhat.points if fmt is ExportFormat.csv else ExportWhat.mesh)
    if what is ExportWhat.mesh and fmt is ExportFormat.csv:
        raise InputError("csv holds points: use --what points or smoothed, or a mesh format")
    if what is not ExportWhat.mesh and fmt in (ExportFormat.obj, ExportFormat.stl):
        raise InputError(f"{fmt.value} holds meshes: use ply or csv for points")
    stage = {"mesh": "mesh", "points": "points", "smoothed": "surface"}[what.value]
    with open_archive(ctx) as archive:
        _row, record = Pipeline(archive).result(uid, stage, plugin=plugin)
    if isinstance(record, MeshRecord):
        write_mesh(record, out, fmt=fmt.value)  # type: ignore[arg-type]
        typer.echo(f"mesh of {len(record.vertices)} vertices, {len(record.triangles)} "
                   f"triangles written to {out}")
        return
    if isinstance(record, Surface):
        samples = record.sample_points()
        if samples is None:
            raise InputError(f"the stored surface of {uid} keeps no smoothed points")
        record = samples
    if not isinstance(record, Points):
        raise InputError(f"the stored {stage} result is a {record.kind} record, not points")
    write_points(record, out, fmt=fmt.value)  # type: ignore[arg-type]
    typer.echo(f"{len(record)} points written to {out}")


def register(app: typer.Typer) -> None:
    """Add the ``export`` command to ``app``."""
    app.command("export")(export)
