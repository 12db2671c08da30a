"""A progress bar for long commands: count, rate and ETA on stderr, only on a terminal.

``diff``, ``reprocess``, ``prune`` and ``stats`` use :func:`progress_bar`; ``process`` and
``jobs resume`` draw the job's own counts with :func:`rasterserver.commands.jobs.job_progress`
(same columns). In a pipe or a log nothing is drawn: the bar's redraws would be noise there.
rich is imported only when a bar is drawn (it comes with Typer).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rasterserver.interrupts import raise_if_interrupted

__all__ = ["duration", "progress_bar", "rich_bar"]


@contextmanager
def rich_bar(description: str) -> Iterator[tuple[Any, Any]]:
    """Draw a bar on stderr; yield ``(progress, task)`` of rich, to update with ``completed``,
    ``total``, ``description`` and the text fields ``rate`` and ``eta``.

    The one look of every bar of the CLI: description, bar, done/total, percentage, rate and
    ETA; removed when done (the command prints its own summary).
    """
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
    )

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TaskProgressColumn(), TextColumn("{task.fields[rate]}"),
        TextColumn("ETA {task.fields[eta]}"),
        console=Console(stderr=True), transient=True,
    ) as bar:
        yield bar, bar.add_task(description, total=None, rate="", eta="?")


def duration(seconds: float | None) -> str:
    """``m:ss`` or ``h:mm:ss``; ``?`` when unknown."""
    if seconds is None:
        return "?"
    seconds = round(seconds)
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


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
        ``progress(done, total)``; draws nothing when stderr is not a terminal or not
        enabled. Either way it raises ``KeyboardInterrupt`` once Ctrl-C came
        (:func:`~rasterserver.interrupts.raise_if_interrupted`).
    """
    if not enabled or not sys.stderr.isatty():
        yield lambda _done, _total: raise_if_interrupted()
        return
    with rich_bar(description) as (bar, task):
        started = time.monotonic()

        def update(done: int, total: int) -> None:
            raise_if_interrupted()  # a Ctrl-C swallowed in a finaliser stops the work here
            # the mean rate since the start: steadier than a moving window for uneven items
            spent = time.monotonic() - started
            rate = done / spent if done and spent > 0 else None
            eta = (total - done) / rate if rate else None
            bar.update(task, completed=done, total=total,
                       rate=f"{rate:.1f} {unit}/s" if rate else "", eta=duration(eta))

        yield update
