"""Run the Alembic migrations programmatically: the only way the schema changes."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, inspect

from rasterserver.catalog.schema import SchemaError
from rasterserver.catalog.schema import require_current as require_current

__all__ = ["SchemaError", "alembic_config", "create_embedded", "current_revision", "downgrade",
           "head_revision", "require_current", "upgrade"]


def alembic_config(engine: Engine) -> Config:
    """Return an Alembic configuration for the migrations shipped with the package."""
    cfg = Config()
    import rasterserver_migrations

    cfg.set_main_option("script_location", str(Path(rasterserver_migrations.__file__).parent))
    cfg.set_main_option(
        "sqlalchemy.url", engine.url.render_as_string(hide_password=False).replace("%", "%%")
    )
    return cfg


def upgrade(engine: Engine, revision: str = "head", *, key_file: Path | None = None) -> None:
    """Migrate the catalogue at ``engine`` up to ``revision`` (creating it if empty).

    Parameters
    ----------
    engine : sqlalchemy.Engine
        The catalogue's engine.
    revision : str, optional
        Target revision, ``"head"`` by default.
    key_file : Path, optional
        The archive's pseudonym key file (:func:`rasterserver.pseudonym_key.key_file`):
        where revision 0010 moves a key the catalogue held. Without it that revision
        refuses to run on a catalogue holding a key.
    """
    cfg = alembic_config(engine)
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        cfg.attributes["pseudonym_key_file"] = key_file
        command.upgrade(cfg, revision)


def downgrade(engine: Engine, revision: str, *, key_file: Path | None = None) -> None:
    """Migrate the catalogue at ``engine`` down to ``revision`` (``"base"`` empties it).

    ``key_file`` as for :func:`upgrade`: below 0010 the key goes back into the catalogue.
    """
    cfg = alembic_config(engine)
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        cfg.attributes["pseudonym_key_file"] = key_file
        command.downgrade(cfg, revision)


def current_revision(engine: Engine) -> str | None:
    """Return the catalogue's current schema revision, or None for an empty database."""
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def head_revision(engine: Engine) -> str | None:
    """Return the newest revision shipped with this version of rasterserver."""
    return ScriptDirectory.from_config(alembic_config(engine)).get_current_head()


def create_embedded(engine: Engine) -> bool:
    """Create the catalogue if it is a new, empty SQLite database; return whether it did.

    The embedded default is set up by its first use, as ``rasterserver demo`` does, so that
    ``rasterserver serve`` on a new archive just starts. PostgreSQL is never touched here:
    its operators migrate on purpose (``rasterserver db upgrade``), and an SQLite catalogue
    that holds anything already (an older revision, foreign tables) is left for
    :func:`require_current` to explain: migrating it is a step to take with a backup.

    Parameters
    ----------
    engine : sqlalchemy.Engine
        The catalogue's engine.

    Returns
    -------
    bool
        True if the catalogue was created.
    """
    if engine.dialect.name != "sqlite" or current_revision(engine) is not None:
        return False
    if inspect(engine).get_table_names():
        return False
    upgrade(engine)
    return True
