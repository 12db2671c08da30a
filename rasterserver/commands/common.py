"""Helpers shared by the CLI command modules."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import typer

from rasterserver.config import Settings
from rasterserver.times import parse_day, parse_instant

if TYPE_CHECKING:
    from rasterserver.archive import Archive
    from rasterserver.catalog.catalog import Catalog

# Heavy modules (the archive with SQLAlchemy, HDF5 and NumPy; rich's progress bars) are
# imported inside the functions that use them, so that `--help` and light commands start fast.


def settings(ctx: typer.Context) -> Settings:
    """Return the settings resolved by the root callback (archive, database URL)."""
    obj = ctx.find_root().obj
    if not isinstance(obj, Settings):  # pragma: no cover - only when a command is run bare
        obj = Settings.from_env()
    return obj


def open_archive(ctx: typer.Context) -> Archive:
    """Open the archive named by the global options; its schema must be current."""
    from rasterserver.archive import Archive

    return Archive(settings(ctx))


def open_catalog(ctx: typer.Context) -> Catalog:
    """Open only the catalogue named by the global options (its schema must be current).

    For commands that read the database alone (``list``): no file stores, no NumPy or HDF5.
    """
    from rasterserver.catalog.catalog import Catalog

    return Catalog(settings(ctx).database_url)


def parse_date(text: str | None, what: str) -> dt.date | None:
    """Parse an ISO date (``YYYY-MM-DD``) from an option, with a clear error."""
    return None if text is None else parse_day(text, what)


def parse_datetime(text: str | None, what: str) -> dt.datetime | None:
    """Parse a time with its zone, or a date alone (00:00 UTC): :mod:`rasterserver.times`.

    A time without zone is refused (exit 2), never guessed.
    """
    return None if text is None else parse_instant(text, what)


@contextmanager
def progress_bar(description: str, *, enabled: bool = True) -> Iterator[Callable[[int, int], None]]:
    """Yield a ``progress(done, total)`` callback drawing a bar on stderr, with rate and ETA.

    The bar is drawn only on a terminal; in a pipe or a CI log it stays silent. See
    :func:`rasterserver.commands.progress.progress_bar`.
    """
    from rasterserver.commands.progress import progress_bar as bar

    with bar(description, unit="item", enabled=enabled) as update:
        yield update
