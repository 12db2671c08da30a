"""``rasterserver verify``: prove that files and catalogue agree."""

from __future__ import annotations

import typer

from rasterserver.archive import Problem
from rasterserver.commands.common import open_archive, progress_bar
from rasterserver.errors import IntegrityError
from rasterserver.pipeline import Pipeline


def verify(ctx: typer.Context) -> None:
    """Re-hash every raw frame and stored result; report missing, corrupt, orphaned and
    leftover files.

    Exits 0 when the archive is intact, 5 when anything is wrong (each problem is listed
    with what it means).
    """
    with open_archive(ctx) as archive:
        with progress_bar("verifying raw frames") as progress:
            raw = archive.verify(progress=progress)
        with progress_bar("verifying stored results") as progress:
            derived = Pipeline(archive).verify(progress=progress)
    problems: list[Problem] = [*raw.problems, *derived.problems]
    for problem in problems:
        where = problem.uid or (problem.path.name if problem.path else "-")
        typer.echo(f"{problem.kind}\t{where}\t{problem.detail}")
    typer.echo(
        f"checked {raw.acquisitions_checked} acquisitions, {raw.frames_checked} frames, "
        f"{derived.frames_checked} stored results: "
        + ("OK" if not problems else f"{len(problems)} problem(s)")
    )
    if problems:
        raise IntegrityError(f"the archive has {len(problems)} problem(s), listed above")


def register(app: typer.Typer) -> None:
    """Add the ``verify`` command to ``app``."""
    app.command("verify")(verify)
