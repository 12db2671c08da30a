"""``rasterserver diff`` and ``rasterserver reprocess``: what a new chain changed.

``reprocess`` is a command of its own rather than a ``process --compare-with`` option: it
runs a job exactly as ``process`` does and then compares, and keeping it apart leaves
``process`` (the everyday command) with the options it has and one job of work.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.commands.common import open_archive
from rasterserver.commands.selection_options import (
    Before,
    Every,
    FromPlugin,
    Patient,
    Since,
    StationName,
    Uids,
    selection,
)

if TYPE_CHECKING:
    from rasterserver.chain_spec import ChainSpec
    from rasterserver.processing_jobs import Selection

# The chains, the pipeline, NumPy and matplotlib are imported when a command runs.

_CHAIN_HELP = (
    "A chain: `default` (the installed plugins, default parameters) or comma-separated "
    "items KIND=PLUGIN (or KIND=PLUGIN@VERSION) and KIND.PARAMETER=VALUE, e.g. "
    "'peaks=peaks.first-moment@3,peaks.bias_fraction=0.2'."
)

Out = Annotated[
    Path | None,
    typer.Option("-o", "--out", help="Folder for diff.json and the PNG plots (created).",
                 show_default=False),
]
Targets = Annotated[
    list[str] | None,
    typer.Option("--until", metavar="KIND", help="Last stage kinds whose chains are compared; "
                 "repeatable (default: mesh and analysis).", show_default=False),
]
Json = Annotated[bool, typer.Option("--json", help="The whole report as JSON on stdout.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress display.")]


def diff(
    ctx: typer.Context,
    chain_a: Annotated[str, typer.Argument(metavar="CHAIN_A", help="The chain before. "
                                           + _CHAIN_HELP)],
    chain_b: Annotated[str, typer.Argument(metavar="CHAIN_B", help="The chain after.")],
    uids: Uids = None,
    every: Every = False,
    patient: Patient = None,
    since: Since = None,
    before: Before = None,
    station: StationName = None,
    from_plugin: FromPlugin = None,
    until: Targets = None,
    out: Out = None,
    as_json: Json = False,
    quiet: Quiet = False,
) -> None:
    """Compare the stored results of two chains: which acquisitions changed, and how.

    Over the selection (every acquisition when none is given), the results each chain stored
    are found by their provenance (nothing is recomputed: process with both chains first).
    An acquisition changed when any stage's output differs; for those, the displacement of
    the surface (z_B - z_A over the cells both measured), lines renumbered, coverage gained
    or lost, and each clinical parameter's shift are measured. Printed: counts,
    distributions and the worst cases by uid; with --out, diff.json and PNG plots too.
    Exit 3 when no acquisition has results of both chains.
    """
    from rasterserver.chain_spec import parse_chain

    chosen = selection(uids, every, patient, since, before, station, from_plugin,
                       default_all=True)
    _run_diff(ctx, parse_chain(chain_a), parse_chain(chain_b), chosen, until, out, as_json,
              quiet)


def _run_diff(ctx: typer.Context, spec_a: ChainSpec, spec_b: ChainSpec,
              chosen: Selection | None,
              until: list[str] | None, out: Path | None, as_json: bool, quiet: bool,
              acquisitions: list[tuple[str, int | None]] | None = None,
              *, strict: bool = True) -> None:
    from rasterserver.chain_diff import DEFAULT_TARGETS, diff_chains
    from rasterserver.chain_diff_report import summary_lines, write_report
    from rasterserver.commands.progress import progress_bar
    from rasterserver.errors import NotFoundError
    from rasterserver.processing_jobs import resolve_selection

    with open_archive(ctx) as archive:
        if acquisitions is None:
            assert chosen is not None
            acquisitions = resolve_selection(archive, chosen)
        unknown = [uid for uid, acquisition_id in acquisitions if acquisition_id is None]
        if unknown:
            raise NotFoundError(f"no acquisition {', '.join(unknown[:5])}"
                                + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""))
        with progress_bar("comparing", enabled=not quiet) as progress:
            report = diff_chains(archive, spec_a, spec_b, acquisitions,
                                 targets=until or DEFAULT_TARGETS, progress=progress)
    if out is not None:
        for path in write_report(report, out):
            typer.echo(f"wrote {path}", err=True)
    if as_json:
        typer.echo(report.to_json())
    else:
        typer.echo("\n".join(summary_lines(report)))
    summary = report.summary()
    if summary["acquisitions"] and not (summary["changed"] + summary["unchanged"]):
        if not strict:  # reprocess: the new results are stored, there was nothing before
            typer.echo("nothing to compare: no acquisition had results of the previous chain",
                       err=True)
            return
        raise NotFoundError(
            "no selected acquisition has stored results of both chains: process them with "
            "each chain first (`rasterserver process --stage ...`)"
        )


def reprocess(
    ctx: typer.Context,
    uids: Uids = None,
    every: Every = False,
    patient: Patient = None,
    since: Since = None,
    before: Before = None,
    station: StationName = None,
    from_plugin: FromPlugin = None,
    stage: Annotated[list[str] | None, typer.Option(
        metavar="KIND=PLUGIN", help="The new plugin for a stage; repeatable.")] = None,
    param: Annotated[list[str] | None, typer.Option(
        metavar="KIND.NAME=VALUE", help="A parameter of the new chain (JSON value, else "
        "text); repeatable.")] = None,
    against: Annotated[str, typer.Option(
        metavar="CHAIN", help="The previous chain, compared with. " + _CHAIN_HELP)] = "default",
    until: Targets = None,
    out: Out = None,
    dask: Annotated[bool | None, typer.Option(
        "--dask/--no-dask", help="Compute on Dask, or here; default as `process`.",
        show_default=False)] = None,
    scheduler: Annotated[str | None, typer.Option(
        metavar="ADDRESS", help="Dask scheduler to compute on.", show_default=False)] = None,
    as_json: Json = False,
    quiet: Quiet = False,
) -> None:
    """Process the selection with a new chain, then report what it changed.

    The new chain is the previous one (--against, the installed default chain unless given)
    with the --stage and --param given, run with the installed plugin versions. It runs as a
    job, exactly like `rasterserver process` (its id printed first; `jobs resume` finishes it
    if stopped); then the new results are compared with the previous chain's over the job's
    acquisitions, as `rasterserver diff` does (--out for diff.json and the plots). The exit
    code is that of `process` when acquisitions failed.
    """
    from rasterserver.chain_diff import DEFAULT_TARGETS
    from rasterserver.chain_spec import ChainSpec, parse_chain
    from rasterserver.commands.failures import raise_for_failures
    from rasterserver.commands.jobs import job_progress
    from rasterserver.errors import ConflictError, InputError
    from rasterserver.processing_jobs import create_job, job_outcomes, run_job

    if not stage and not param:
        raise InputError("give the new chain's --stage KIND=PLUGIN or --param KIND.NAME=VALUE")
    chosen = selection(uids, every, patient, since, before, station, from_plugin)
    previous = parse_chain(against)
    change = parse_chain("", extra=[*(stage or []), *(param or [])])
    params = {k: dict(v) for k, v in previous.params.items()}
    for kind, values in change.params.items():
        params.setdefault(kind, {}).update(values)
    # the new chain runs the installed versions: pins of the previous one are dropped
    new = ChainSpec(",".join(filter(None, [previous.text if previous.text != "default" else "",
                                           change.text])),
                    {**previous.stages, **change.stages}, dict(change.versions), params)
    chain, new_params = new.to_process()
    targets = list(until or DEFAULT_TARGETS)
    with open_archive(ctx) as archive:
        job, count = create_job(archive, chosen, chain=chain, params=new_params,
                                targets=targets)
        if not count:
            typer.echo("nothing to process", err=True)
            return
        typer.echo(f"job {job.id}: {count} acquisition(s); if stopped, `rasterserver jobs "
                   f"resume {job.id}` finishes it, and `rasterserver diff` compares", err=True)
        with job_progress(enabled=not quiet) as progress:
            status = run_job(archive, job.id, dask=dask, scheduler=scheduler, progress=progress)
        outcomes = job_outcomes(archive, job.id)
    if status.job.state in ("paused", "cancelled"):
        raise ConflictError(f"job {job.id} was {status.job.state} by another command")
    failed = [o for o in outcomes if o.status == "failed"]
    for outcome in failed[:20]:
        typer.echo(f"{outcome.uid}\tfailed\t{outcome.error}", err=True)
    done = [(o.uid, None) for o in outcomes if o.status == "done"]
    if done:
        from rasterserver.processing_jobs import Selection, resolve_selection

        with open_archive(ctx) as archive:
            acquisitions = resolve_selection(archive, Selection(uids=tuple(u for u, _ in done)))
        _run_diff(ctx, previous, new, None, targets, out or Path(f"diff-{job.id[:8]}"),
                  as_json, quiet, acquisitions, strict=False)
    raise_for_failures(failed, len(outcomes))


def register(app: typer.Typer) -> None:
    """Add the ``diff`` and ``reprocess`` commands to ``app``."""
    app.command("diff")(diff)
    app.command("reprocess")(reprocess)
