"""``rasterserver runs``: the pipeline runs of an acquisition, and runs of killed processes."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive
from rasterserver.runner import local_host

# The pipeline (NumPy, SQLAlchemy, the registry) is imported when a command runs, not at start.

runs_app = typer.Typer(
    help=(
        "Pipeline runs: list an acquisition's runs; mark runs whose process was killed "
        "(out of memory, kill -9, power cut) as interrupted instead of running for ever."
    ),
    no_args_is_help=True,
)


def _time(value: object) -> str:
    return value.isoformat() if value is not None else ""  # type: ignore[attr-defined]


@runs_app.command("list")
def list_runs(
    ctx: typer.Context,
    uid: Annotated[str, typer.Argument(help="Acquisition uid (see `rasterserver list`).")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """List the pipeline runs of an acquisition, oldest first.

    A run that a killed process of this host left "running" is shown, and stored, as failed
    with an error beginning "interrupted:". Runs of other hosts are shown as stored.
    """
    from rasterserver.pipeline import Pipeline

    with open_archive(ctx) as archive:
        rows = Pipeline(archive).runs(uid)
    for run in rows:
        record = {
            "id": run.id,
            "status": run.status,
            "started_at": _time(run.started_at),
            "finished_at": _time(run.finished_at),
            "host": run.host,
            "computed": run.computed,
            "reused": run.reused,
            "error": run.error,
        }
        if as_json:
            typer.echo(json.dumps(record))
        else:
            typer.echo(
                f"{run.id}\t{run.status}\t{record['started_at']}\t{run.host}\t"
                f"{run.computed} computed, {run.reused} reused\t{run.error}"
            )


@runs_app.command("reap")
def reap(
    ctx: typer.Context,
    host: Annotated[
        list[str] | None,
        typer.Option(
            help="Also mark every running run of this host: only when nothing processes "
            "there any more (it crashed or was switched off). Repeatable. Naming this host "
            "marks its runs recorded by older versions, which name no process; live "
            "processes are never touched.",
            show_default=False,
        ),
    ] = None,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Only count the runs that would be marked.")
    ] = False,
) -> None:
    """Mark pipeline runs left "running" by a killed process as interrupted.

    A run is marked "running" when processing starts. If the process is killed (out of
    memory, kill -9, power cut) the run stays so. This command checks every running run of
    this host: when its process is gone (or its process id now belongs to another process)
    the run is stored as failed, with an error beginning "interrupted:" that names the
    process. Runs of live processes are left alone. Runs of other hosts cannot be checked
    from here; they are counted, and marked only with --host.

    Listing runs and processing an acquisition do the same for its runs automatically;
    reprocessing an interrupted acquisition reuses every result it had stored.
    Prints how many runs were marked; exits 0 whether or not there were any.
    """
    from rasterserver.pipeline import INTERRUPTED, Pipeline

    with open_archive(ctx) as archive:
        report = Pipeline(archive).reap(hosts=host or [], dry_run=dry_run)
    verb = "would be marked" if dry_run else "marked"
    typer.echo(f"{report.marked} interrupted run(s) {verb} failed "
               f"(error \"{INTERRUPTED.strip()} ...\")")
    if report.alive:
        typer.echo(f"{report.alive} run(s) of live processes on {local_host()} left running")
    if report.unchecked:
        hosts = ", ".join(f"{name or '?'} ({n})" for name, n in sorted(report.unchecked.items()))
        typer.echo(
            f"still running, not checkable from here: {hosts}; if nothing processes there "
            "any more, run again with --host NAME",
            err=True,
        )


def register(app: typer.Typer) -> None:
    """Add the ``runs`` command group to ``app``."""
    app.add_typer(runs_app, name="runs")
