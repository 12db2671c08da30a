"""``rasterserver demo``: the main job on the embedded default, with simulated data."""

from __future__ import annotations

from typing import Annotated

import typer

from rasterserver.commands.common import settings
from rasterserver.commands.failures import ProcessingFailedError
from rasterserver.errors import IntegrityError


def demo(
    ctx: typer.Context,
    visits: Annotated[int, typer.Option(min=1, max=20, help="Visits to simulate.")] = 3,
) -> None:
    """Run the main job on a simulated patient: render a progressing scoliosis over several
    visits, ingest the frames, process them through the stage plugins (mesh and back-shape
    analysis), export one mesh and one report page per visit (to <archive>/exports), verify
    the archive, and end with the key parameters of every visit side by side.

    Uses the archive and catalogue named by --archive / --database-url (default: ./archive
    with SQLite inside it). Running it again adds further visits of the same demo patient.
    """
    # imported here: the simulator and open3d cost every other command a second at start
    from rasterserver.demo import run_demo

    result = run_demo(settings(ctx), visits=visits, log=typer.echo)
    if result.problems:
        raise IntegrityError("the archive failed verification; run `rasterserver verify`")
    failed = [o for o in result.outcomes if o.status != "done"]
    if failed:
        raise ProcessingFailedError(
            "some visits could not be processed (listed above)",
            exit_code=ProcessingFailedError.code_of(failed),
        )


def register(app: typer.Typer) -> None:
    """Add the ``demo`` command to ``app``."""
    app.command("demo")(demo)
