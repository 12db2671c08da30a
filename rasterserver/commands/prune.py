"""``rasterserver prune`` and ``rasterserver stats``: the archive's space."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive

# The catalogue, the chains and the plugins are imported when a command runs.


def _size(count: int) -> str:
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} TiB"  # pragma: no cover


def prune(
    ctx: typer.Context,
    keep: Annotated[list[str] | None, typer.Option(
        metavar="CHAIN", help="Also keep this chain's results: `default` or items "
        "KIND=PLUGIN (or KIND=PLUGIN@VERSION) and KIND.PARAMETER=VALUE, comma-separated; "
        "repeatable.", show_default=False)] = None,
    keep_jobs: Annotated[int, typer.Option(
        min=0, metavar="N", help="Keep the chains of the N newest processing jobs.")] = 1,
    apply: Annotated[bool, typer.Option(
        "--apply", help="Remove them. Without it, only say what would be removed.")] = False,
    force: Annotated[bool, typer.Option(
        "--force", help="Remove although pipeline runs are recorded as running (their "
        "processes, on other hosts, are known to have stopped).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress display.")] = False,
) -> None:
    """Remove derived results that no kept chain needs; a dry run unless --apply.

    Kept: the default chain (installed plugins and versions, default parameters), every
    --keep chain and the chains of the --keep-jobs newest jobs, each the newest stored path
    per acquisition; every comparison and asymmetry result and what it was computed from;
    every result a kept one was computed from. Raw frames are never touched. Catalogue rows
    go first, in one transaction, then their files: a row never names a missing file, and
    files left by a crash in between are reported by `rasterserver verify` as orphaned
    (harmless; `verify --repair` moves them to its quarantine). Exit 4 while a pipeline run
    is in progress.
    """
    from rasterserver.chain_spec import parse_chain
    from rasterserver.commands.progress import progress_bar
    from rasterserver.prune import plan_prune, run_prune

    specs = [parse_chain(text) for text in keep or []]
    with open_archive(ctx) as archive:
        with progress_bar("planning", enabled=not quiet) as progress:
            plan = plan_prune(archive, specs, keep_jobs=keep_jobs, progress=progress)
        report = run_prune(archive, plan, force=force) if apply else None
    if as_json:
        typer.echo(json.dumps({"dry_run": not apply, "plan": plan.to_dict(),
                               "done": report.to_dict() if report else None}))
        return
    lines = ["kept chains:", *(f"  {c}" for c in plan.chains),
             f"{plan.results} stored result(s), {plan.kept} kept"]
    stages = ", ".join(f"{k} {v}" for k, v in sorted(plan.per_stage.items()))
    if report is None:
        lines.append(f"would remove {len(plan.remove)} result(s)"
                     + (f" ({stages})" if stages else "")
                     + f", {len(plan.files)} file(s), {_size(plan.bytes)}")
        if plan.remove:
            lines.append("run again with --apply to remove them")
    else:
        lines.append(f"removed {report.rows_removed} result(s)"
                     + (f" ({stages})" if stages else "")
                     + f", {report.files_removed} file(s), freed {_size(report.bytes_freed)}")
        if report.files_missing:
            lines.append(f"{report.files_missing} file(s) were already missing")
        if report.files_still_used:
            lines.append(f"{report.files_still_used} file(s) kept: new results use them")
    typer.echo("\n".join(lines))


def stats(
    ctx: typer.Context,
    with_prune: Annotated[bool, typer.Option(
        "--prune/--no-prune", help="Also say what `rasterserver prune` (its defaults) would "
        "free.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress display.")] = False,
) -> None:
    """Show the archive's size by kind of file, its acquisitions and results, the stored
    results per chain (plugins, versions and parameters hashes), and what prune would free."""
    from rasterserver.archive_stats import archive_stats
    from rasterserver.commands.progress import progress_bar

    with open_archive(ctx) as archive, progress_bar("measuring", enabled=not quiet) as bar:
        found = archive_stats(archive, prune=with_prune, progress=bar)
    if as_json:
        typer.echo(json.dumps(found.to_dict()))
        return
    lines = [f"archive size {_size(found.total_bytes)}"]
    for kind, entry in found.files.items():
        lines.append(f"  {kind:<24} {_size(entry['bytes']):>10}  {entry['files']} file(s)")
    lines.append("catalogue " + ", ".join(f"{v} {k}" for k, v in found.counts.items()))
    lines.append("results per chain (acquisitions: chain):")
    for chain in found.chains:
        lines.append(f"  {chain['acquisitions']:>6}: {chain['chain']}")
    if found.prune is not None:
        lines.append(f"prune would remove {found.prune['remove']} result(s), "
                     f"{found.prune['files']} file(s), {_size(found.prune['bytes'])} "
                     "(`rasterserver prune` says which)")
    typer.echo("\n".join(lines))


def register(app: typer.Typer) -> None:
    """Add the ``prune`` and ``stats`` commands to ``app``."""
    app.command("prune")(prune)
    app.command("stats")(stats)
