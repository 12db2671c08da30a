"""``rasterserver export``: write a processed acquisition's mesh or points for other programs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive
from rasterserver.export_choices import ExportFormat, ExportFrame, ExportWhat

# The writers (OpenCV, NumPy, open3d) and the pipeline are imported when the command runs.


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
    frame: Annotated[
        ExportFrame,
        typer.Option(
            help="station: the calibration's world frame (X right, Y down, Z anterior); "
            "patient: the body-fixed frame of the back-shape analysis (origin DM, X right, Y up, "
            "Z posterior), the frame visits are compared in.",
        ),
    ] = ExportFrame.station,
) -> None:
    """Export the newest stored mesh or point cloud of an acquisition.

    Meshes go to PLY, OBJ or STL (open3d); point clouds to PLY (with line number, column,
    row and peak area per point) or CSV. Run `rasterserver process UID` first. A sidecar
    FILE.json names the acquisition, the stored result, the coordinate frame (origin and
    axes) and the units. Files are replaced whole or not at all; a path that cannot be written
    exits 2 before any work.
    """
    from rasterserver.export import select_export, sidecar_path
    from rasterserver.output_files import check_output
    from rasterserver.pipeline import Pipeline
    from rasterserver.records_surface import MeshRecord

    check_output(out, what="--out")  # before the archive is opened
    check_output(sidecar_path(out), what="the sidecar of --out")
    with open_archive(ctx) as archive:
        chosen = select_export(
            Pipeline(archive), uid, fmt=fmt, what=what, plugin=plugin, frame=frame
        )
        chosen.write(out, sidecar=True)
    record = chosen.record
    if isinstance(record, MeshRecord):
        typer.echo(
            f"mesh of {len(record.vertices)} vertices, {len(record.triangles)} "
            f"triangles written to {out} ({chosen.frame.value} frame, mm)"
        )
    else:
        typer.echo(f"{len(record)} points written to {out} ({chosen.frame.value} frame, mm)")


def register(app: typer.Typer) -> None:
    """Add the ``export`` command to ``app``."""
    app.command("export")(export)
