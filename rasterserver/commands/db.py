"""``rasterserver db``: create and migrate the catalogue's schema."""

from __future__ import annotations

from typing import Annotated

import typer

from rasterserver.commands.common import settings
from rasterserver.errors import InputError

# Alembic and SQLAlchemy are imported by the commands, not at start: `--help` stays fast.

db_app = typer.Typer(
    help="Create or migrate the catalogue's SQL schema (Alembic migrations).",
    no_args_is_help=True,
)


@db_app.command("upgrade")
def upgrade(
    ctx: typer.Context,
    revision: Annotated[str, typer.Argument(help="Target revision.")] = "head",
) -> None:
    """Create the catalogue, or migrate it to the newest schema (safe to repeat)."""
    from alembic.util.exc import CommandError

    from rasterserver.catalog import migrate
    from rasterserver.catalog.database import make_engine
    from rasterserver.pseudonym_key import key_file

    chosen = settings(ctx)
    engine = make_engine(chosen.database_url)
    try:
        before = migrate.current_revision(engine)
        try:
            # 0010 moves the pseudonym key out of the catalogue into this file
            migrate.upgrade(engine, revision, key_file=key_file(chosen))
        except CommandError as exc:
            # Alembic's words ("Can't locate revision ...") for a revision that is no option
            raise InputError(
                f"db upgrade {revision!r}: {exc}; the newest is {migrate.head_revision(engine)}"
            ) from None
        after = migrate.current_revision(engine)
    finally:
        engine.dispose()
    typer.echo(f"catalogue schema: {before or 'empty'} -> {after}")


@db_app.command("current")
def current(ctx: typer.Context) -> None:
    """Show the catalogue's schema revision and the newest one this version knows."""
    from rasterserver.catalog import migrate
    from rasterserver.catalog.database import make_engine

    engine = make_engine(settings(ctx).database_url)
    try:
        typer.echo(f"current: {migrate.current_revision(engine) or 'empty'}")
        typer.echo(f"newest:  {migrate.head_revision(engine)}")
    finally:
        engine.dispose()


def register(app: typer.Typer) -> None:
    """Add the ``db`` command group to ``app``."""
    app.add_typer(db_app, name="db")
