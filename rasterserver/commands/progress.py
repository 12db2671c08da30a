"""A progress bar for long commands: count, rate and ETA on stderr, only on a terminal.

``diff``, ``reprocess``, ``prune`` and ``stats`` use :func:`progress_bar`; ``process`` and
``jobs resume`` draw the job's own counts with :func:`rasterserver.commands.jobs.job_progress`
(same columns). In a pipe or a log nothing is drawn: the bar's redraws would be noise there.
rich is imported only when a bar is drawn (it comes with Typer).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["progress_bar"]


@contextmanager
def progress_bar(
    description: str, *, unit: str = "acq", enabled: bool = True
) -> Iterator[Callable[[int, int], None]]:
    """Yield a ``progress(done, total)`` callback drawing a bar with rate and ETA on stderr.

    Parameters
    ----------
    description : str
        Shown left of the bar (no patient data).
    unit : str
        What is counted, for the rate (``"acq"`` gives ``12.3 acq/s``).
    enabled : bool
        False (``--quiet``) draws nothing.

    Yields
    ------
    callable
        ``progress(done, total)``; a no-op when stderr is not a terminal or not enabled.
    """
    if not enabled or not sys.stderr.isatty():
        yield lambda _done, _total: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[rate]}"), TextColumn("ETA"), TimeRemainingColumn(),
        console=Console(stderr=True), transient=True,
    ) as bar:
        task = bar.add_task(description, total=None, rate="")

        def update(done: int, total: int) -> None:
            speed = bar.tasks[0].speed  # rich's own moving estimate
            bar.update(task, completed=done, total=total,
                       rate=f"{speed:.1f} {unit}/s" if speed else "")

        yield update
