"""Helpers shared by the CLI command modules."""

from __future__ import annotations

import datetime as dt
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeRemainingColumn,
)

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.errors import InputError


def settings(ctx: typer.Context) -> Settings:
    """Return the settings resolved by the root callback (archive, database URL)."""
    obj = ctx.find_root().obj
    if not isinstance(obj, Settings):  # pragma: no cover - only when a command is run bare
        obj = Settings.from_env()
    return obj


def open_archive(ctx: typer.Context) -> Archive:
    """Open the archive named by the global options; its schema must be current."""
    return Archive(settings(ctx))


def parse_date(text: str | None, what: str) -> dt.date | None:
    """Parse an ISO date (``YYYY-MM-DD``) from an option, with a clear error."""
    if text is None:
        return None
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise InputError(f"{what}: {text!r} is not a date (YYYY-MM-DD)") from None


def parse_datetime(text: str | None, what: str) -> dt.datetime | None:
    """Parse an ISO date or date-time; a time without zone is taken as UTC."""
    if text is None:
        return None
    try:
        value = dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(f"{what}: {text!r} is not a date or time (ISO 8601)") from None
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


@contextmanager
def progress_bar(description: str, *, enabled: bool = True) -> Iterator[Callable[[int, int], None]]:
    """Yield a ``progress(done, total)`` callback drawing a bar on stderr.

    The bar is drawn only on a terminal; in a pipe or a CI log it stays silent.
    """
    if not enabled or not sys.stderr.isatty():
        yield lambda _done, _total: None
        return
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeRemainingColumn(), console=Console(stderr=True), transient=True,
    ) as bar:
        task = bar.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update
