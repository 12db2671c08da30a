"""Is the catalogue at the schema revision this code needs? Answered without Alembic.

Alembic's own answer (a migration context and the script directory) costs about 0.2 s of
imports at every start of every command. The question needs much less: the revision the
catalogue is at is the one row of its ``alembic_version`` table, and the newest revision
shipped is the one no migration in ``rasterserver_migrations/versions`` names as its
``down_revision``, which the migration files state in plain assignments. Running migrations
still goes through Alembic (:mod:`rasterserver.catalog.migrate`); a test checks that both
agree on the head.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
import re
from pathlib import Path

from sqlalchemy import Engine, inspect, text

from rasterserver.errors import RasterServerError

__all__ = ["SchemaError", "current_revision", "head_revision_id", "require_current"]

#: Alembic's table of the applied revision (its default name).
VERSION_TABLE = "alembic_version"

# `revision: str = "0012"` or `down_revision = None` at the start of a line of a migration
_ASSIGNMENT = re.compile(r"^(revision|down_revision)\s*(?::[^=]*)?=\s*(.+?)\s*$", re.MULTILINE)


class SchemaError(RasterServerError):
    """The catalogue's schema is not at the version this code expects."""

    exit_code = 6
    http_status = 503


def migrations_folder() -> Path:
    """The folder of the installed migrations (``rasterserver_migrations``), not imported."""
    spec = importlib.util.find_spec("rasterserver_migrations")
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover - broken install
        raise SchemaError("the migrations (rasterserver_migrations) are not installed")
    return Path(next(iter(spec.submodule_search_locations)))


@functools.cache
def head_revision_id(folder: Path | None = None) -> str | None:
    """The newest revision shipped: the one no other migration revises.

    Parameters
    ----------
    folder : Path, optional
        The migrations folder (its ``versions`` subfolder is read); the installed one by
        default.

    Returns
    -------
    str or None
        The head revision, None when there are no migrations.

    Raises
    ------
    SchemaError
        The migrations have several heads (a merge is missing): no single answer.
    """
    versions = (folder or migrations_folder()) / "versions"
    revisions: set[str] = set()
    revised: set[str] = set()
    for path in versions.glob("*.py"):
        found = dict(
            (name, ast.literal_eval(value))
            for name, value in _ASSIGNMENT.findall(path.read_text(encoding="utf-8"))
        )
        if "revision" not in found:
            continue  # __init__.py
        revisions.add(found["revision"])
        down = found.get("down_revision")
        revised.update((down,) if isinstance(down, str) else (down or ()))
    heads = sorted(revisions - revised)
    if len(heads) > 1:  # pragma: no cover - a development state, never shipped
        raise SchemaError(f"the migrations have several heads: {', '.join(heads)}")
    return heads[0] if heads else None


def current_revision(engine: Engine) -> str | None:
    """The catalogue's revision, or None for a catalogue without Alembic's table."""
    with engine.connect() as conn:
        if not inspect(conn).has_table(VERSION_TABLE):
            return None
        rows = [row[0] for row in conn.execute(text(f"SELECT version_num FROM {VERSION_TABLE}"))]
    if len(rows) > 1:  # pragma: no cover - only with branches, which this project has not
        raise SchemaError(f"the catalogue is at several revisions: {', '.join(sorted(rows))}")
    return rows[0] if rows else None


def require_current(engine: Engine) -> None:
    """Raise :class:`SchemaError` unless the catalogue is at the newest revision.

    Services call this before touching the catalogue, so an old or empty database gets a
    message that says what to run instead of an SQL error.
    """
    current, head = current_revision(engine), head_revision_id()
    if current != head:
        state = "is empty" if current is None else f"is at revision {current}"
        raise SchemaError(
            f"the catalogue {state}, this rasterserver needs {head}: "
            "run `rasterserver db upgrade`"
        )
