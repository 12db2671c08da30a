"""``rasterserver process``: run the stage chain over archived acquisitions."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, progress_bar
from rasterserver.errors import InputError, RasterServerError
from rasterserver.jobs import process_many
from rasterserver.pipeline import DEFAULT_TARGETS, Pipeline, parse_stage_options


def parse_calibration(text: str | None) -> tuple[str, int | None] | None:
    """Parse ``STATION:VERSION`` (or ``STATION`` for its newest calibration)."""
    if text is None:
        return None
    usage = f"--calibration {text!r}: expected STATION:VERSION, e.g. clinic-1:3"
    station, sep, version = text.rpartition(":")
    if not sep:
        return text.strip(), None
    try:
        number = int(version)
    except ValueError:
        raise InputError(usage) from None
    if not station.strip() or number < 1:
        raise InputError(usage)
    return station.strip(), number


def process(
    ctx: typer.Context,
    uids: Annotated[
        list[str] | None,
        typer.Argument(help="Acquisition uids (see `rasterserver list`).", show_default=False),
    ] = None,
    patient: Annotated[str | None, typer.Option(help="All acquisitions of this patient.")] = None,
    all_unprocessed: Annotated[
        bool,
        typer.Option(
            "--all-unprocessed",
            help="Every acquisition (of --patient, if given) without a successful run.",
        ),
    ] = False,
    stage: Annotated[
        list[str] | None,
        typer.Option(help="KIND=PLUGIN: use another plugin for a stage; repeatable."),
    ] = None,
    calibration: Annotated[
        str | None,
        typer.Option(
            help="STATION:VERSION (or STATION for its newest): use this calibration instead of "
            "the one attached at ingest; it must be of the acquisition's station.",
        ),
    ] = None,
    until: Annotated[
        list[str] | None,
        typer.Option(
            metavar="KIND",
            help="Last stage kind to run; repeatable (default: mesh and analysis). Any kind of "
            "the stage graph: see `rasterserver plugins --graph`.",
            show_default=False,
        ),
    ] = None,
    dask: Annotated[
        bool,
        typer.Option(
            "--dask/--no-dask",
            help="Compute on Dask: RASTERSERVER_DASK_SCHEDULER if set, else a local cluster.",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """Process acquisitions: every stage's result is stored with its provenance.

    Stored results of the same computation (same frame, plugins, versions, parameters and
    calibration) are reused, not recomputed; other plugins, parameters or calibrations add
    results beside the old ones. Exits 1 if any acquisition failed (each is listed).

    Runs that a killed process left "running" are marked interrupted when their acquisition
    is processed again (and see `rasterserver runs reap`).
    """
    chain = parse_stage_options(stage or [])
    wanted = parse_calibration(calibration)
    with open_archive(ctx) as archive:
        pipeline = Pipeline(archive)
        selected = list(uids or [])
        if all_unprocessed:
            selected += pipeline.unprocessed(patient=patient)
        elif patient is not None:
            selected += [
                a.uid for a in reversed(archive.acquisitions(patient=patient, limit=1_000_000))
            ]
        if not selected:
            if uids or patient or all_unprocessed:
                typer.echo("nothing to process", err=True)
                return
            raise InputError("name acquisitions, or use --patient or --all-unprocessed")
        selected = list(dict.fromkeys(selected))  # each once, in the order given
        with progress_bar("processing") as progress:
            outcomes = process_many(
                archive,
                selected,
                chain=chain,
                calibration=wanted,
                until=until or DEFAULT_TARGETS,
                dask=dask,
                progress=progress,
            )
    for outcome in outcomes:
        if as_json:
            typer.echo(json.dumps(outcome.to_dict()))
        elif outcome.status == "done":
            note = f"; {outcome.reason}" if outcome.reason else ""
            typer.echo(
                f"{outcome.uid}\tdone\t{outcome.computed} computed, {outcome.reused} reused{note}"
            )
        else:
            typer.echo(f"{outcome.uid}\tfailed\t{outcome.error}")
    failed = sum(o.status == "failed" for o in outcomes)
    if failed:
        raise RasterServerError(f"{failed} of {len(outcomes)} acquisition(s) failed, see above")


def register(app: typer.Typer) -> None:
    """Add the ``process`` command to ``app``."""
    app.command("process")(process)
