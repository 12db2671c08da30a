"""``rasterserver jobs``: processing jobs kept in the catalogue: list, show, pause, resume,
cancel; and the progress display that ``process`` and ``jobs resume`` share."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Annotated, Any

import typer

from rasterserver.commands.common import open_archive
from rasterserver.interrupts import raise_if_interrupted

if TYPE_CHECKING:
    from rasterserver.processing_jobs import JobStatus

# The pipeline and Dask are imported when a command runs, not at start.

jobs_app = typer.Typer(
    help=(
        "Processing jobs: every `rasterserver process` and every POST /jobs is a job kept in "
        "the catalogue, with its selection, chain, counts and times. A job can be paused, "
        "cancelled, and resumed by any process, also after the process running it was killed."
    ),
    no_args_is_help=True,
)

#: Seconds between two progress lines when stderr is not a terminal (a log, a pipe).
LINE_EVERY_S = 10.0


def _duration(seconds: float | None) -> str:
    from rasterserver.commands.progress import duration

    return duration(seconds)


def _progress_text(status: JobStatus) -> str:
    job = status.job
    rate = f"{status.rate:.1f}/s" if status.rate else "-/s"
    failed = f", {job.failed} failed" if job.failed else ""
    return (
        f"job {job.id[:8]}: {job.done + job.failed}/{job.total}{failed}, {rate}, "
        f"ETA {_duration(status.eta_s)}"
    )


@contextmanager
def job_progress(*, enabled: bool = True) -> Iterator[Callable[[JobStatus], None]]:
    """Yield a callback drawing a job's progress on stderr, with rate and ETA.

    On a terminal: the CLI's bar (:func:`rasterserver.commands.progress.rich_bar`) with the
    job's own counts, rate and ETA (from the catalogue, so a resumed job's bar starts where
    it stopped). Elsewhere: a line every :data:`LINE_EVERY_S` seconds, so a log shows the job
    moving without a line per acquisition.
    """
    if not enabled:
        yield lambda _status: raise_if_interrupted()
        return
    if not sys.stderr.isatty():
        last = [time.monotonic()]

        def line(status: JobStatus) -> None:
            raise_if_interrupted()  # a Ctrl-C swallowed in a finaliser stops the job here
            if time.monotonic() - last[0] >= LINE_EVERY_S:
                last[0] = time.monotonic()
                typer.echo(_progress_text(status), err=True)

        yield line
        return
    from rasterserver.commands.progress import rich_bar

    with rich_bar("processing") as (bar, task):

        def update(status: JobStatus) -> None:
            raise_if_interrupted()
            job = status.job
            bar.update(
                task, completed=job.done + job.failed, total=job.total,
                description=f"job {job.id[:8]}" + (f" ({job.failed} failed)" if job.failed
                                                   else ""),
                rate=f"{status.rate:.1f} acq/s" if status.rate else "",
                eta=_duration(status.eta_s),
            )

        yield update


def _when(value: Any) -> str:
    return value.strftime("%Y-%m-%d %H:%M:%S") if value is not None else "-"


@jobs_app.command("list")
def list_command(
    ctx: typer.Context,
    state: Annotated[
        str | None,
        typer.Option(help="Only jobs in this state: queued, running, paused, cancelled, done, "
                     "failed (stored state; an interrupted job is stored as running)."),
    ] = None,
    limit: Annotated[int, typer.Option(min=1, help="At most this many jobs.")] = 50,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line.")] = False,
) -> None:
    """List processing jobs, newest first: id, state, done/failed/total, owner, created.

    A job whose coordinator process is gone (killed, host rebooted) shows as "interrupted":
    `rasterserver jobs resume ID` finishes it.
    """
    from rasterserver.processing_jobs import job_status, list_jobs

    with open_archive(ctx) as archive:
        statuses = [job_status(archive, j) for j in list_jobs(archive, state=state, limit=limit)]
    if not statuses and not as_json:
        typer.echo("no processing jobs" + (f" in state {state}" if state else ""), err=True)
    for status in statuses:
        job = status.job
        if as_json:
            record = status.to_dict()
            record.pop("chain")
            typer.echo(json.dumps(record))
        else:
            typer.echo(
                f"{job.id}\t{status.state}\t{job.done} done, {job.failed} failed, "
                f"{status.left} left of {job.total}\t{job.owner} ({job.origin})\t"
                f"{_when(job.created_at)}"
            )


@jobs_app.command("show")
def show_command(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(metavar="ID", help="Job id (or its first 6+ "
                                          "characters), see `rasterserver jobs list`.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
) -> None:
    """Show a job: its state, selection, chain (plugins, versions, parameters), counts,
    times, rate and ETA, and its first failed acquisitions with their reasons."""
    from rasterserver.processing_jobs import find_job, job_status

    with open_archive(ctx) as archive:
        status = job_status(archive, find_job(archive, job_id), failures=20)
    if as_json:
        typer.echo(json.dumps(status.to_dict()))
        return
    record = status.to_dict()
    job = status.job
    lines = [
        f"job        {job.id}",
        f"state      {status.state}" + (
            "  (its process is gone: `rasterserver jobs resume` finishes it)"
            if status.interrupted else ""),
        f"started by {job.owner} ({job.origin})",
        f"selection  {json.dumps(job.selection)}",
        f"targets    {', '.join(job.targets)}",
    ]
    for target, steps in job.chain.get("resolved", {}).items():
        chain = " -> ".join(f"{s['plugin']} {s['version']}" for s in steps)
        lines.append(f"chain      {target}: {chain}")
    if job.chain.get("params"):
        lines.append(f"parameters {json.dumps(job.chain['params'])}")
    if job.chain.get("calibration"):
        lines.append("calibration " + ":".join(str(p) for p in job.chain["calibration"]))
    lines += [
        f"progress   {job.done} done, {job.failed} failed, {status.left} left of {job.total}",
        f"rate       {status.rate:.2f} acquisitions/s" if status.rate else "rate       -",
    ]
    if status.eta_s is not None:
        lines.append(f"eta        {_duration(status.eta_s)}")
    lines += [
        f"engine     {job.engine or '-'}",
        f"runner     {record['runner'] or '-'}",
        f"created    {_when(job.created_at)}",
        f"started    {_when(job.started_at)}",
        f"progress   {_when(job.progress_at)} (last)",
        f"finished   {_when(job.finished_at)}",
    ]
    if job.error:
        lines.append(f"error      {job.error}")
    for failure in status.failures:
        lines.append(f"failed     {failure['uid']}\t{failure['error']}")
    typer.echo("\n".join(lines))


@jobs_app.command("pause")
def pause_command(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(metavar="ID", help="Job id (or its first 6+ "
                                          "characters).")],
) -> None:
    """Pause a queued or running job: its coordinator stores the acquisitions in flight and
    stops. `rasterserver jobs resume ID` continues where it stopped. Exit 4 if the job is
    not queued or running, 3 if there is no such job."""
    from rasterserver.processing_jobs import pause_job

    with open_archive(ctx) as archive:
        job = pause_job(archive, job_id)
    typer.echo(f"job {job.id} paused ({job.done + job.failed} of {job.total} finished); "
               f"resume with `rasterserver jobs resume {job.id}`")


@jobs_app.command("cancel")
def cancel_command(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(metavar="ID", help="Job id (or its first 6+ "
                                          "characters).")],
) -> None:
    """Cancel a job for good: its coordinator drops what is in flight and stops; pending
    acquisitions are never processed by it. Results already stored stay (a later job reuses
    them). Exit 4 if the job is finished or cancelled already, 3 if there is no such job."""
    from rasterserver.processing_jobs import cancel_job

    with open_archive(ctx) as archive:
        job = cancel_job(archive, job_id)
    typer.echo(f"job {job.id} cancelled ({job.done} done, {job.failed} failed, "
               f"{job.total - job.done - job.failed} not processed)")


@jobs_app.command("resume")
def resume_command(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(metavar="ID", help="Job id (or its first 6+ "
                                          "characters).")],
    dask: Annotated[
        bool | None,
        typer.Option("--dask/--no-dask", show_default=False,
                     help="Compute on Dask (RASTERSERVER_DASK_SCHEDULER if set, else a local "
                     "cluster), or here. Default: as `process` decides."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(metavar="ADDRESS", help="Dask scheduler to compute on, e.g. "
                     "tcp://10.0.0.5:8786 (overrides RASTERSERVER_DASK_SCHEDULER)."),
    ] = None,
    force: Annotated[
        bool,
        typer.Option("--force", help="Take over a running job whose process cannot be "
                     "checked from here (another host) because you know it has stopped."),
    ] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress display.")] = False,
) -> None:
    """Resume a paused or interrupted job here, in the foreground, until it is finished.

    Only its pending acquisitions are processed; one whose results were stored just before
    its process was killed finds them stored (reused, not computed again). The plugins
    installed must be the versions the job was created with. Exit 0 when every acquisition
    is done; the failures' exit code when some failed (see `rasterserver process`); 4 when
    the job is finished, cancelled, or running in a live process; 3 for an unknown job.
    """
    from rasterserver.commands.failures import raise_for_failures
    from rasterserver.errors import ConflictError
    from rasterserver.processing_jobs import job_outcomes, run_job

    with open_archive(ctx) as archive, job_progress(enabled=not quiet) as progress:
        status = run_job(archive, job_id, dask=dask, scheduler=scheduler, force=force,
                         progress=progress)
        failed = [o for o in job_outcomes(archive, status.job.id) if o.status == "failed"]
    job = status.job
    typer.echo(f"job {job.id} {job.state}: {job.done} done, {job.failed} failed, "
               f"{status.left} left of {job.total}")
    for outcome in failed[:20]:
        typer.echo(f"{outcome.uid}\tfailed\t{outcome.error}")
    if job.state in ("paused", "cancelled"):
        raise ConflictError(f"job {job.id} was {job.state} by another command")
    raise_for_failures(failed, job.total)


def register(app: typer.Typer) -> None:
    """Add the ``jobs`` command group to ``app``."""
    app.add_typer(jobs_app, name="jobs")
