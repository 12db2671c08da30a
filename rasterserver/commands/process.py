"""``rasterserver process``: run the stage chain over archived acquisitions."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, parse_datetime
from rasterserver.commands.failures import raise_for_failures
from rasterserver.errors import InputError

# The pipeline and the jobs (NumPy, the plugins, Dask) are imported when the command runs:
# `--help` and the other commands start without them. The failures' error is in
# commands.failures, shared with jobs, diff and demo.


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
    every: Annotated[
        bool,
        typer.Option("--all", help="Every acquisition with a raster frame (narrowed by the "
                     "options below)."),
    ] = False,
    patient: Annotated[str | None, typer.Option(help="All acquisitions of this patient.")] = None,
    all_unprocessed: Annotated[
        bool,
        typer.Option(
            "--all-unprocessed",
            help="Every acquisition (of --patient, if given) without a successful run.",
        ),
    ] = False,
    since: Annotated[
        str | None,
        typer.Option(metavar="TIME", help="Acquired at or after this time (ISO 8601 with "
                     "zone, or a date: 00:00 UTC).", show_default=False),
    ] = None,
    before: Annotated[
        str | None,
        typer.Option(metavar="TIME", help="Acquired before this time.", show_default=False),
    ] = None,
    station: Annotated[
        str | None, typer.Option(help="Taken at this station.", show_default=False)
    ] = None,
    from_plugin: Annotated[
        str | None,
        typer.Option(metavar="PLUGIN[@VERSION]", help="Whose stored results came from this "
                     "plugin (of this algorithm version): reprocess what a fixed plugin "
                     "made, e.g. peaks.first-moment@1.", show_default=False),
    ] = None,
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
        bool | None,
        typer.Option(
            "--dask/--no-dask",
            help="Compute on Dask (RASTERSERVER_DASK_SCHEDULER if set, else a local cluster), "
            "or here. Default: here for one acquisition; for more, on "
            "RASTERSERVER_DASK_SCHEDULER if set, else here below 200 acquisitions and on a "
            "local cluster from 200 (see docs/jobs.md).",
            show_default=False,
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(metavar="ADDRESS", help="Dask scheduler to compute on, e.g. "
                     "tcp://10.0.0.5:8786 (overrides RASTERSERVER_DASK_SCHEDULER).",
                     show_default=False),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress display.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """Process acquisitions: every stage's result is stored with its provenance.

    The request is stored as a job (its id is printed on stderr first): if this command is
    stopped (Ctrl-C pauses the job; kill -9, a reboot) `rasterserver jobs resume ID` finishes
    it, and `rasterserver jobs pause|cancel ID` stops it from another terminal. Selection
    options combine: uids named, plus those matching every filter given.

    Stored results of the same computation (same frame, plugins, versions, parameters and
    calibration) are reused, not recomputed; other plugins, parameters or calibrations add
    results beside the old ones. An unknown plugin, stage, patient, station or calibration is
    refused before any work. If an acquisition fails, the others are still processed and
    each failure is listed; the exit code is the failures' (3 for an unknown acquisition, 2
    for a frame that does not fit its calibration, ...) when they agree, else 1; 4 when the
    job was paused or cancelled by another command.

    Runs that a killed process left "running" are marked interrupted when their acquisition
    is processed again (and see `rasterserver runs reap`).
    """
    from rasterserver.commands.jobs import job_progress
    from rasterserver.errors import ConflictError
    from rasterserver.pipeline import DEFAULT_TARGETS, parse_stage_options, resolve_chain
    from rasterserver.processing_jobs import Selection, create_job, job_outcomes, run_job

    chain = parse_stage_options(stage or [])
    wanted = parse_calibration(calibration)
    targets = list(until or DEFAULT_TARGETS)
    plugin, _, version = (from_plugin or "").partition("@")
    if from_plugin is not None and (not plugin.strip() or (version == "" and "@" in from_plugin)):
        raise InputError(f"--from-plugin {from_plugin!r}: expected PLUGIN or PLUGIN@VERSION")
    selection = Selection(
        uids=tuple(uids or ()),
        all=every,
        unprocessed=all_unprocessed,
        patient=patient,
        since=parse_datetime(since, "--since"),
        before=parse_datetime(before, "--before"),
        station=station,
        plugin=plugin.strip() or None,
        plugin_version=version.strip() or None,
    )
    if not selection.uids and not selection.filtered:
        raise InputError(
            "name acquisitions, or use --all, --all-unprocessed, --patient, --since/--before, "
            "--station or --from-plugin"
        )
    for target in targets:
        # a misspelt plugin or stage is the request's fault, not each acquisition's: refuse
        # it once (exit 3 or 2) before any work
        resolve_chain(chain, until=target)
    with open_archive(ctx) as archive:
        job, count = create_job(
            archive, selection, chain=chain, calibration=wanted, targets=targets
        )
        if not count:
            typer.echo("nothing to process", err=True)
            return
        typer.echo(
            f"job {job.id}: {count} acquisition(s); if stopped, `rasterserver jobs resume "
            f"{job.id}` finishes it",
            err=True,
        )
        with job_progress(enabled=not quiet) as progress:
            status = run_job(archive, job.id, dask=dask, scheduler=scheduler, progress=progress)
        outcomes = job_outcomes(archive, job.id)
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
    if status.job.state in ("paused", "cancelled"):
        raise ConflictError(
            f"job {job.id} was {status.job.state} by another command: {status.left} of "
            f"{count} acquisition(s) not processed"
            + (f"; `rasterserver jobs resume {job.id}` continues it"
               if status.job.state == "paused" else "")
        )
    failed = [o for o in outcomes if o.status == "failed"]
    raise_for_failures(failed, len(outcomes))


def register(app: typer.Typer) -> None:
    """Add the ``process`` command to ``app``."""
    app.command("process")(process)
