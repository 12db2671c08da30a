"""``rasterserver verify``: prove that files and catalogue agree, and clean up leftovers."""

from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.commands.common import open_archive, progress_bar
from rasterserver.errors import InputError, IntegrityError

if TYPE_CHECKING:
    from rasterserver.integrity import Problem

# The archive and the integrity checks are imported when the command runs: `--help` starts
# without them.


def verify(
    ctx: typer.Context,
    repair: Annotated[
        bool,
        typer.Option(
            "--repair",
            help="Then clean up: delete temporary files, move orphaned files into "
            "<archive>/quarantine/<date>/ (with a manifest.json), leave stray files alone. "
            "Missing, corrupt and unreadable files are never touched.",
        ),
    ] = False,
    dry_run: Annotated[
        bool,
        typer.Option("--dry-run", help="Show what --repair would do and change nothing "
                                       "(implies --repair)."),
    ] = False,
    min_age: Annotated[
        float | None,
        typer.Option(
            "--min-age", metavar="MINUTES", min=0, show_default=False,
            help="With --repair: leave files younger than this (default 60) for a later run, "
            "since an ingest or a processing run may still be at work on them.",
        ),
    ] = None,
) -> None:
    """Re-hash every raw frame and stored result; report missing, corrupt, orphaned and
    leftover files.

    Exits 0 when the archive is intact, 5 when anything is wrong (each problem is listed
    with what it means).

    With --repair (or --dry-run), the harmless leftovers of interrupted writes are cleaned up
    afterwards: temporary files are deleted, orphaned files are moved into the quarantine
    folder, stray files are left alone. Missing, corrupt and unreadable files need a person
    (restore from backup) and are only listed. Exits 0 when nothing is left to report, 5
    otherwise (always 5 after a dry run that found problems: it changed nothing), 4 if another
    repair is running.
    """
    from rasterserver.integrity import VerifyReport, verify_archive

    repair = repair or dry_run
    if min_age is not None and not repair:
        raise InputError("--min-age goes with --repair or --dry-run")
    with open_archive(ctx) as archive:
        with progress_bar("verifying raw frames and stored results") as progress:
            found = verify_archive(archive, progress=progress)
        raw, derived = found.raw, found.derived
        problems: list[Problem] = found.problems
        if not repair:
            for problem in problems:
                typer.echo(f"{problem.kind}\t{_where(problem)}\t{problem.detail}")
        typer.echo(
            f"checked {raw.acquisitions_checked} acquisitions, {raw.frames_checked} frames, "
            f"{derived.frames_checked} stored results: "
            + ("OK" if not problems else f"{len(problems)} problem(s)")
        )
        if not problems:
            return
        if not repair:
            raise IntegrityError(f"the archive has {len(problems)} problem(s), listed above")
        with progress_bar("repairing") as progress:
            outcome = archive.repair(
                VerifyReport(problems=problems), dry_run=dry_run, progress=progress,
                min_age=None if min_age is None else dt.timedelta(minutes=min_age),
            )
    for action in outcome.actions:
        where = action.uid or action.path or "-"
        moved = f" -> {action.destination}" if action.destination else ""
        typer.echo(f"{action.verb(dry_run)}\t{action.kind}\t{where}{moved}\t{action.detail}")
    typer.echo(outcome.summary())
    if not outcome.ok:
        raise IntegrityError(
            f"{len(outcome.remaining)} problem(s) remain, listed above"
            + (" (dry run: nothing was changed)" if dry_run else "")
        )


def _where(problem: Problem) -> str:
    return problem.uid or (problem.path.name if problem.path else "-")


def register(app: typer.Typer) -> None:
    """Add the ``verify`` command to ``app``."""
    app.command("verify")(verify)
