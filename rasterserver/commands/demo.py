"""``rasterserver demo``: the main job on the embedded default, with simulated data."""

from __future__ import annotations

from typing import Annotated

import typer

from rasterserver.commands.common import settings
from rasterserver.demo import run_demo
from rasterserver.errors import IntegrityError


def demo(
    ctx: typer.Context,
    visits: Annotated[int, typer.Option(min=1, max=20, help="Visits to simulate.")] = 3,
) -> None:
    """Set up the archive (SQLite + local folder by default) and run the main job on a demo
    patient: generate frames, ingest them, list them and verify the archive."""
    result = run_demo(settings(ctx), visits=visits, log=typer.echo)
    if result.problems:
        raise IntegrityError("the archive failed verification; run `rasterserver verify`")


def register(app: typer.Typer) -> None:
    """Add the ``demo`` command to ``app``."""
    app.command("demo")(demo)
