"""Shared fixtures: a fresh catalogue on SQLite and on PostgreSQL for every test that asks.

The PostgreSQL leg uses ``RASTERSERVER_TEST_POSTGRES_URL`` (default: the local server at
127.0.0.1:5432, database ``test``, trust auth). Each test gets a database of its own, created
from that server and dropped afterwards, so tests cannot see each other's rows. Without a
reachable server the leg is skipped with the reason.
"""

from __future__ import annotations

import functools
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlalchemy.engine import make_url

from rasterserver.catalog.database import make_engine
from rasterserver.config import Settings, sqlite_url

POSTGRES_URL = os.environ.get(
    "RASTERSERVER_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
)


def _postgres_unavailable() -> str | None:
    try:
        engine = make_engine(POSTGRES_URL, connect_args={"connect_timeout": 3})
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        engine.dispose()
    except Exception as exc:  # any failure means: no server to test against here
        return f"PostgreSQL at {make_url(POSTGRES_URL).render_as_string()} unreachable: {exc}"
    return None


@functools.cache
def postgres_skip_reason() -> str | None:
    """Probe the PostgreSQL server once per session; return why it cannot be used, if so."""
    reason = _postgres_unavailable()
    if reason and os.environ.get("RASTERSERVER_REQUIRE_POSTGRES"):
        pytest.fail(f"RASTERSERVER_REQUIRE_POSTGRES is set but {reason}")
    return reason


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A URL of a brand-new, empty PostgreSQL database, dropped after the test."""
    reason = postgres_skip_reason()
    if reason:
        pytest.skip(reason)
    name = f"rs_test_{uuid.uuid4().hex[:12]}"
    admin = make_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    url = make_url(POSTGRES_URL).set(database=name).render_as_string(hide_password=False)
    try:
        yield url
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty catalogue database: SQLite in tmp_path, and PostgreSQL."""
    if request.param == "sqlite":
        return sqlite_url(tmp_path / "archive")
    return request.getfixturevalue("postgres_url")


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    """Settings of an empty archive in tmp_path, on both catalogue backends."""
    return Settings(archive=tmp_path / "archive", database_url=database_url)
