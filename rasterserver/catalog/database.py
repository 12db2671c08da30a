"""Engines and sessions for the catalogue (SQLite embedded, PostgreSQL in production)."""

from __future__ import annotations

import fcntl
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url

from rasterserver.store.modes import file_mode

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

# The ORM (sqlalchemy.orm) is imported by session_factory when a session is first needed:
# readers of the catalogue with SQLAlchemy Core (`rasterserver list`) start without it.


def make_engine(url: str, **kwargs: Any) -> Engine:
    """Create an engine for the catalogue at ``url``.

    SQLite gets foreign keys switched on (off by default in SQLite), write-ahead logging so
    readers do not block the ingesting writer, ``synchronous=FULL`` so that a committed
    ingest survives a power cut, and a page cache sized for a large catalogue.
    A plain ``postgresql://`` URL is taken to mean psycopg 3.

    Parameters
    ----------
    url : str
        SQLAlchemy database URL.
    **kwargs
        Passed on to :func:`sqlalchemy.create_engine`.

    Returns
    -------
    sqlalchemy.Engine
    """
    parsed = make_url(url)
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")
    if parsed.get_backend_name() == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            _private_sqlite_file(Path(parsed.database))
        engine = create_engine(parsed, **kwargs)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    kwargs.setdefault("pool_pre_ping", True)
    # fail in seconds, not minutes, when the server is unreachable: the HTTP API reads
    # metadata on its event loop, which a hanging connect would stall
    kwargs.setdefault("connect_args", {}).setdefault("connect_timeout", 10)
    return create_engine(parsed, **kwargs)


def _private_sqlite_file(database: Path) -> None:
    """Create a new SQLite catalogue's folder and (empty) file owner-only.

    SQLite would create the file with 0644 less the umask: readable by every account on the
    machine. Made here first with the archive's mode (:mod:`rasterserver.store.modes`), it
    keeps that mode, and SQLite gives its WAL and shared-memory files the mode of the
    database file. An existing catalogue is left as it is.
    """
    from rasterserver.store.durable import ensure_dir
    from rasterserver.store.modes import make_private_file

    ensure_dir(database.parent)
    make_private_file(database)


def _sqlite_pragmas(dbapi_conn: sqlite3.Connection, _record: object) -> None:
    cursor = dbapi_conn.cursor()
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=FULL")
    cursor.execute("PRAGMA busy_timeout=30000")
    # SQLite's default page cache is 2 MB; the catalogue's indexes (acquisitions, the audit
    # trail, which grows by a row per patient shown) outgrow that soon, and then every insert
    # rereads index pages. 64 MB per connection, allocated only as used.
    cursor.execute("PRAGMA cache_size=-65536")
    cursor.close()


class WriteLock:
    """Serialises the writers of one SQLite catalogue across threads and processes.

    SQLite admits one writer; another that finds the database locked waits in SQLite's busy
    handler, which polls with sleeps growing to 100 ms. Two busy server processes writing
    audit events turned that into tail latencies of a second. Writers that take this lock
    first (a ``flock`` on ``<database>.lock``, plus a thread lock, since ``flock`` does not
    exclude threads sharing the file) wait in the kernel instead and are woken the moment
    it is free. For PostgreSQL, which locks rows, it does nothing.

    Parameters
    ----------
    engine : sqlalchemy.Engine
        The catalogue's engine.
    """

    def __init__(self, engine: Engine) -> None:
        database = engine.url.database if engine.url.get_backend_name() == "sqlite" else None
        self._path = (Path(database).with_name(Path(database).name + ".lock")
                      if database and database != ":memory:" else None)
        self._threads = threading.Lock()
        self._fd: int | None = None

    @contextmanager
    def __call__(self) -> Iterator[None]:
        """Hold the lock for the duration of the ``with`` block."""
        if self._path is None:
            yield
            return
        with self._threads:
            if self._fd is None:
                self._fd = os.open(self._path, os.O_RDWR | os.O_CREAT, file_mode())
            fcntl.flock(self._fd, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(self._fd, fcntl.LOCK_UN)

    def close(self) -> None:
        """Close the lock file (the lock itself is released with each block)."""
        with self._threads:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


def session_factory(engine: Engine) -> sessionmaker[Session]:
    """Return a session factory bound to ``engine`` that keeps objects usable after commit."""
    from sqlalchemy.orm import sessionmaker

    return sessionmaker(engine, expire_on_commit=False)
