"""``rasterserver list``: acquisitions in the catalogue."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_catalog, parse_datetime
from rasterserver.errors import InputError
from rasterserver.times import TIME_RULE


def list_acquisitions(
    ctx: typer.Context,
    patient: Annotated[str | None, typer.Option(help="Only this patient's.")] = None,
    since: Annotated[
        str | None, typer.Option(help=f"Taken at or after this time: {TIME_RULE}.")
    ] = None,
    until: Annotated[str | None, typer.Option(help="Taken before this time (as --since).")] = None,
    kind: Annotated[str | None, typer.Option(help="patient, calibration or test.")] = None,
    limit: Annotated[int, typer.Option(min=1, help="Rows per page.")] = 100,
    offset: Annotated[int, typer.Option(min=0, help="Rows to skip.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """List acquisitions, newest first."""
    # imported here, not at start: SQLAlchemy, which `--help` does not need
    from rasterserver.catalog import listing
    from rasterserver.catalog.vocabulary import ACQUISITION_KINDS

    if kind is not None and kind not in ACQUISITION_KINDS:
        # an unknown kind would list nothing, as if the archive were empty
        raise InputError(f"--kind must be one of {', '.join(ACQUISITION_KINDS)}, got {kind!r}")
    # the catalogue alone: listing needs neither the file stores nor their NumPy and HDF5
    with open_catalog(ctx) as catalog:
        rows = listing.find(
            catalog,
            patient=patient,
            since=parse_datetime(since, "--since"),
            until=parse_datetime(until, "--until"),
            kind=kind,
            limit=limit,
            offset=offset,
        )
    for acq in rows:
        record = {
            "uid": acq.uid,
            "patient": acq.patient,
            "kind": acq.kind,
            "acquired_at": acq.acquired_at.isoformat(),
            "frames": [
                {"index": f.index, "role": f.role, "shape": [f.height, f.width], "dtype": f.dtype}
                for f in acq.frames
            ],
        }
        if as_json:
            typer.echo(json.dumps(record))
        else:
            frames = ", ".join(f"{f.role} {f.height}x{f.width} {f.dtype}" for f in acq.frames)
            typer.echo(
                f"{acq.uid}\t{record['patient'] or '-'}\t{acq.kind}\t"
                f"{acq.acquired_at:%Y-%m-%d %H:%M}\t{frames}"
            )


def register(app: typer.Typer) -> None:
    """Add the ``list`` command to ``app``."""
    app.command("list")(list_acquisitions)
