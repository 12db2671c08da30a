"""``rasterserver station``: stations, their raster diapositives and calibrations."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from rasterserver.commands.common import open_archive, parse_datetime

station_app = typer.Typer(
    help="Register stations (camera + projector set-ups), rasters and calibrations.",
    no_args_is_help=True,
)


def _read(path: Path, what: str) -> Any:
    """The parsed JSON of ``path``; what it must be is checked when it is stored."""
    from rasterserver.documents import read_document

    return read_document(path, what=what)


@station_app.command("add")
def add(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Unique station name.")],
    description: Annotated[str, typer.Option(help="Free text.")] = "",
) -> None:
    """Register a station."""
    with open_archive(ctx) as archive:
        archive.add_station(name, description=description)
    typer.echo(f"station {name} registered")


@station_app.command("list")
def list_stations(ctx: typer.Context) -> None:
    """List stations with their newest calibration version."""
    with open_archive(ctx) as archive:
        for st in archive.stations():
            versions = [c.version for c in archive.calibrations(st.name)]
            newest = max(versions) if versions else "-"
            typer.echo(f"{st.name}\tcalibration {newest}\t{st.description}")


@station_app.command("add-raster")
def add_raster(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Raster name.")],
    definition: Annotated[Path, typer.Argument(help="Raster definition JSON file.")],
) -> None:
    """Store a raster diapositive definition (rasterserver.raster/1 JSON).

    The definition is checked first (docs/formats.md); a refused one stores nothing (exit 2).
    """
    document = _read(definition, "raster definition")
    with open_archive(ctx) as archive:
        archive.add_raster(name, document, source=definition.name)
    typer.echo(f"raster {name} stored")


@station_app.command("add-calibration")
def add_calibration(
    ctx: typer.Context,
    station: Annotated[str, typer.Argument(help="Station name.")],
    calibration: Annotated[Path, typer.Argument(help="Calibration JSON file.")],
    raster: Annotated[
        str | None, typer.Option(help="Name of the stored raster it was made with.")
    ] = None,
    valid_from: Annotated[
        str | None,
        typer.Option(
            help="From when it applies, ISO 8601 (default: now). Acquisitions are given the "
            "calibration valid when they were taken.",
        ),
    ] = None,
    notes: Annotated[str, typer.Option(help="Free text.")] = "",
) -> None:
    """Import a calibration as the station's next version (calibrations are immutable).

    The calibration is checked first (docs/formats.md); a refused one stores nothing (exit 2).
    """
    document = _read(calibration, "calibration")
    with open_archive(ctx) as archive:
        row = archive.add_calibration(
            station, document, raster=raster, notes=notes,
            valid_from=parse_datetime(valid_from, "--valid-from"), source=calibration.name,
        )
    typer.echo(f"station {station}: calibration version {row.version} stored")


def register(app: typer.Typer) -> None:
    """Add the ``station`` command group to ``app``."""
    app.add_typer(station_app, name="station")
