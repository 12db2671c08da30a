"""The catalogue handle: one engine, its sessions, reads outside transactions, the write lock.

Everything that needs the SQL catalogue (the archive, the pipeline, the services of the HTTP
API and of the CLI: auth, audit, pseudonyms, jobs) takes a :class:`Catalog` rather than an
:class:`~rasterserver.archive.Archive`: a database handle does not need the file stores,
ingest or verification, nor their imports (NumPy, HDF5). An ``Archive`` holds one
(``archive.catalog``) and lends it out.

Opening a catalog checks the schema revision cheaply (:mod:`rasterserver.catalog.schema`,
no Alembic); :meth:`Catalog.create` migrates first.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, Engine

from rasterserver.catalog.database import WriteLock, make_engine
from rasterserver.catalog.schema import require_current

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

__all__ = ["Catalog"]


class Catalog:
    """The SQL catalogue at ``database_url``.

    Use as a context manager (``with Catalog(url) as catalog:``) or call :meth:`close`.

    Parameters
    ----------
    database_url : str
        SQLAlchemy URL of the catalogue (SQLite file or PostgreSQL).
    check_schema : bool, default True
        Refuse (:class:`~rasterserver.catalog.schema.SchemaError`) a catalogue that is not
        migrated to the current revision.
    connections : int, optional
        Connections kept open for reuse: as many as threads that use the catalogue at once
        (the HTTP server's). By default SQLAlchemy's pool of 5. Such a pool also skips the
        liveness check (a round trip) before each use: after a database restart the first
        use of each stale connection fails (the HTTP API answers 503) and the pool replaces
        them all.

    Attributes
    ----------
    engine : sqlalchemy.Engine
        For transactions of several statements (``engine.begin()``) and for SQLAlchemy
        Core; prefer :meth:`session` for ORM work and :meth:`reading` for one read.
    write_lock : WriteLock
        Taken by the catalogue's frequent writers (ingest, the audit trail): see
        :class:`~rasterserver.catalog.database.WriteLock`.
    """

    def __init__(
        self,
        database_url: str,
        *,
        check_schema: bool = True,
        connections: int | None = None,
    ) -> None:
        # Connections beyond the pool are closed when given back: a busy server would open
        # (and, on SQLite, set up) one per request. So the pool holds them all.
        pool = {} if connections is None else {"pool_size": connections, "max_overflow": 4,
                                               "pool_pre_ping": False}
        self.engine: Engine = make_engine(database_url, **pool)
        self.write_lock = WriteLock(self.engine)
        # PostgreSQL wraps even a lone SELECT in a transaction: BEGIN before it and a
        # ROLLBACK when the connection goes back to the pool, two round trips more than the
        # query, which doubled the time of a one-row read. A single statement sees one
        # snapshot anyway. SQLite begins no transaction for a SELECT, so it keeps its engine.
        self._reader: Engine = (
            self.engine.execution_options(isolation_level="AUTOCOMMIT")
            if self.engine.dialect.name == "postgresql" else self.engine)
        # made on first use: the ORM is not needed by readers of the catalogue (`list`)
        self._sessions: sessionmaker[Session] | None = None
        if check_schema:
            try:
                require_current(self.engine)
            except BaseException:
                self.close()
                raise

    @classmethod
    def create(cls, database_url: str, *, key_file: Path | None = None,
               **kwargs: Any) -> Catalog:
        """Open the catalogue, first migrating it to the newest schema.

        Parameters
        ----------
        database_url : str
            As for :class:`Catalog`.
        key_file : Path, optional
            The archive's pseudonym key file, for migration 0010
            (:func:`rasterserver.catalog.migrate.upgrade`).
        **kwargs
            As for :class:`Catalog`.
        """
        from rasterserver.catalog import migrate

        engine = make_engine(database_url)
        try:
            migrate.upgrade(engine, key_file=key_file)
        finally:
            engine.dispose()
        return cls(database_url, **kwargs)

    @property
    def dialect(self) -> str:
        """The backend's name: ``sqlite`` or ``postgresql``."""
        return self.engine.dialect.name

    def reading(self) -> Connection:
        """A connection for *one* read-only statement, outside a transaction.

        Use as ``with catalog.reading() as conn: conn.execute(...)``. For several statements
        that must agree with each other, use :meth:`session` or ``engine.begin()``.
        """
        return self._reader.connect()

    @contextmanager
    def session(self) -> Iterator[Session]:
        """An ORM session committed on success and rolled back on any error.

        Objects stay usable after the commit (``expire_on_commit=False``).
        """
        if self._sessions is None:
            from rasterserver.catalog.database import session_factory

            self._sessions = session_factory(self.engine)
        with self._sessions() as session:
            try:
                yield session
                session.commit()
            except BaseException:
                session.rollback()
                raise

    def close(self) -> None:
        """Release the catalogue's connections and the write lock's file."""
        self.engine.dispose()
        self.write_lock.close()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
