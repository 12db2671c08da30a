"""``rasterserver ingest``: store camera frames as one acquisition."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, parse_date, parse_datetime
from rasterserver.times import TIME_RULE

# The archive (SQLAlchemy, HDF5, NumPy) is imported when a command runs, not at start.


def ingest(
    ctx: typer.Context,
    files: Annotated[
        list[Path],
        typer.Argument(
            help="Frame files: PNG, TIFF (8/16 bit), NPY, or raw bytes with --shape/--dtype.",
            show_default=False,
        ),
    ],
    patient: Annotated[
        str | None, typer.Option(help="Patient identifier (registered with `patient add`).")
    ] = None,
    role: Annotated[
        list[str] | None,
        typer.Option(
            help="Role of each frame, in order (raster, projector-off, projector-on, dark, "
            "other); one value applies to all. Default: raster.",
        ),
    ] = None,
    kind: Annotated[str, typer.Option(help="patient, calibration or test.")] = "patient",
    station: Annotated[str | None, typer.Option(help="Station that took the frames.")] = None,
    calibration: Annotated[
        int | None,
        typer.Option(help="Calibration version of the station (default: the newest)."),
    ] = None,
    visit_date: Annotated[
        str | None, typer.Option(help="Visit date YYYY-MM-DD (default: acquisition date).")
    ] = None,
    acquired_at: Annotated[
        str | None, typer.Option(help=f"When the frames were taken: {TIME_RULE}. A time "
                                 "without zone is refused. Default: now.")
    ] = None,
    operator: Annotated[str, typer.Option(help="Who took the frames.")] = "",
    notes: Annotated[str, typer.Option(help="Free text.")] = "",
    shape: Annotated[
        str | None, typer.Option(help="ROWSxCOLUMNS of raw frames, e.g. 604x576.")
    ] = None,
    dtype: Annotated[str | None, typer.Option(help="uint8 or uint16, for raw frames.")] = None,
    convert_color: Annotated[
        bool, typer.Option(help="Convert colour images to grey instead of refusing them.")
    ] = False,
    idempotency_key: Annotated[str | None, typer.Option(
        help="A key for this upload: run again with the same key and frames (a retry), it "
             "reports the acquisition stored the first time instead of storing it twice; "
             "with other frames or metadata it is refused (exit 4).")] = None,
) -> None:
    """Validate frames and store them as one acquisition (write-once HDF5 + catalogue row).

    Every frame is checked before anything is written: a colour, empty, truncated, oversized
    or non-image file, an unknown patient or an unknown calibration stores nothing.

    A frame whose size differs from the camera of the calibration that applies is refused
    (exit 2); when no calibration applies yet it is stored with a warning saying why.
    """
    from rasterserver.frame_fit import calibration_notice
    from rasterserver.ingest_request import ingest_request

    request = ingest_request(
        [(path, path.name) for path in files], roles=role, patient=patient, kind=kind,
        station=station, calibration_version=calibration,
        visit_date=parse_date(visit_date, "--visit-date"),
        acquired_at=parse_datetime(acquired_at, "--acquired-at"), operator=operator,
        notes=notes, shape=shape, dtype=dtype, convert_color=convert_color,
        idempotency_key=idempotency_key, source="cli",
        spelling={"shape": "--shape", "roles": "--role values"})
    with open_archive(ctx) as archive:
        acq, replayed = request.store(archive)
        notice = calibration_notice(archive, acq)
    done = "already stored under this key" if replayed else "stored"
    typer.echo(f"acquisition {acq.uid}: {len(acq.frames)} frame(s) {done}")
    if notice:
        typer.echo(f"warning: {notice}", err=True)


def register(app: typer.Typer) -> None:
    """Add the ``ingest`` command to ``app``."""
    app.command("ingest")(ingest)
