"""``rasterserver station``: stations, their raster diapositives and calibrations."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from rasterserver.commands.common import open_archive, parse_datetime
from rasterserver.errors import InputError

station_app = typer.Typer(
    help="Register stations (camera + projector set-ups), rasters and calibrations.",
    no_args_is_help=True,
)


def _load_json(path: Path, what: str) -> dict[str, Any]:
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path.name}: no such {what} file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path.name}: not a JSON {what} ({exc})") from None
    if not isinstance(document, dict):
        raise InputError(f"{path.name}: a {what} must be a JSON object")
    return document


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
    """Store a raster diapositive definition (rasterserver.raster/1 JSON)."""
    document = _load_json(definition, "raster definition")
    with open_archive(ctx) as archive:
        archive.add_raster(name, document)
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
    """Import a calibration as the station's next version (calibrations are immutable)."""
    document = _load_json(calibration, "calibration")
    with open_archive(ctx) as archive:
        row = archive.add_calibration(
            station, document, raster=raster, notes=notes,
            valid_from=parse_datetime(valid_from, "--valid-from"),
        )
    typer.echo(f"station {station}: calibration version {row.version} stored")


def register(app: typer.Typer) -> None:
    """Add the ``station`` command group to ``app``."""
    app.add_typer(station_app, name="station")
