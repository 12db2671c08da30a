"""``rasterserver verify``: prove that files and catalogue agree."""

from __future__ import annotations

import typer

from rasterserver.commands.common import open_archive, progress_bar
from rasterserver.errors import IntegrityError


def verify(ctx: typer.Context) -> None:
    """Re-hash every stored frame and report missing, corrupt, orphaned and leftover files.

    Exits 0 when the archive is intact, 5 when anything is wrong (each problem is listed
    with what it means).
    """
    with open_archive(ctx) as archive, progress_bar("verifying") as progress:
        report = archive.verify(progress=progress)
    for problem in report.problems:
        where = problem.uid or (problem.path.name if problem.path else "-")
        typer.echo(f"{problem.kind}\t{where}\t{problem.detail}")
    typer.echo(
        f"checked {report.acquisitions_checked} acquisitions, {report.frames_checked} frames: "
        + ("OK" if report.ok else f"{len(report.problems)} problem(s)")
    )
    if not report.ok:
        raise IntegrityError(f"the archive has {len(report.problems)} problem(s), listed above")


def register(app: typer.Typer) -> None:
    """Add the ``verify`` command to ``app``."""
    app.command("verify")(verify)
