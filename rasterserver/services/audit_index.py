"""The audit trail's index by patient, filled in the background in large sorted batches.

The audit writer appends each request's patient links keyed by event
(:class:`~rasterserver.catalog.auth_models.AuditEventPatient`): cheap, because a commit of
many requests' links lands on a page or two. "Who saw patient X" needs them keyed by patient
(:class:`~rasterserver.catalog.auth_models.AuditPatientIndex`). Written at once, that key
took a hundred-patient list into a hundred places of the index, and under load the audit
commits rewrote hundreds of pages each: a quarter of the server's CPU. The indexer instead
takes every link recorded since :class:`~rasterserver.catalog.auth_models.AuditIndexMark`,
sorts it by patient and adds it a few thousand at a time, so each page is rewritten once per
batch, not once per request.

Nothing waits for it: a query by patient reads the index *and* the links after the mark
(:func:`patient_events`), so it is complete however far behind the indexer is. Every step
is idempotent (links already indexed are skipped, the mark only moves forward), so an
indexer killed half-way leaves nothing to repair; the next run redoes the rest.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from typing import TYPE_CHECKING, cast

from sqlalchemy import (
    CompoundSelect,
    Connection,
    Select,
    Table,
    func,
    or_,
    select,
    text,
    union,
    update,
)
from sqlalchemy.exc import OperationalError

from rasterserver.catalog.auth_models import (
    AuditEvent,
    AuditEventPatient,
    AuditIndexMark,
    AuditPatientIndex,
)
from rasterserver.catalog.lookup import patient_id_of

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

log = logging.getLogger(__name__)

#: Seconds between runs of a server's indexer.
INDEX_EVERY_S = 10.0
#: Most events indexed in one run (the rest wait for the next).
MAX_EVENTS = 50_000
#: Links per transaction on SQLite. Each holds the catalogue's write lock, which the audit
#: writer of every request waits for: a few milliseconds at a time, not a whole batch's worth.
CHUNK = 2_000
#: How long a run may hold the lease before another indexer may take over.
LEASE_S = 120.0
#: PostgreSQL: how long the indexer waits for its lock on ``audit_event`` (see
#: :func:`committed_through`), during which the audit writers wait behind it.
LOCK_WAIT_MS = 200

# Tables, as Core sees them (the ORM declares __table__ as a FromClause)
_MARK = cast(Table, AuditIndexMark.__table__)
_LINKS = cast(Table, AuditEventPatient.__table__)
_INDEX = cast(Table, AuditPatientIndex.__table__)


def indexed_through() -> Select[tuple[int]]:
    """The mark as a scalar query: every link of the events up to it is in the index."""
    return select(func.coalesce(func.max(_MARK.c.indexed_through), 0))


def patient_events(patient: str) -> CompoundSelect[tuple[int]]:
    """The ids of the audit events that touched the patient with site identifier ``patient``:
    those in the index, and those after its mark still only in the links."""
    pid = patient_id_of(patient)
    return union(
        select(_INDEX.c.event_id).where(_INDEX.c.patient_id == pid),
        select(_LINKS.c.event_id).where(_LINKS.c.event_id > indexed_through().scalar_subquery(),
                                        _LINKS.c.patient_id == pid),
    )


def committed_through(conn: Connection) -> int:
    """The newest event id such that no event with a smaller one can still commit.

    On SQLite writers take turns and ids grow with each, so the newest visible id is it.
    On PostgreSQL ids come from a sequence and transactions commit in any order: a writer
    holds ROW EXCLUSIVE on ``audit_event`` from the insert that drew its id to its commit,
    so taking SHARE (which waits for those and admits no new ones while held) before
    reading the newest id makes it exact. Must run inside a transaction.

    While the lock request waits, new audit writers queue behind it, so it waits at most
    :data:`LOCK_WAIT_MS`: normally it only waits for commits in flight (milliseconds), but an
    anti-wraparound vacuum of the table, which does not yield, could hold it for minutes.

    Raises
    ------
    IndexerBusyError
        PostgreSQL: the lock was not granted in time; the next run tries again.
    """
    if conn.dialect.name == "postgresql":
        conn.execute(text(f"SET LOCAL lock_timeout = '{LOCK_WAIT_MS}ms'"))
        try:
            conn.execute(text("LOCK TABLE audit_event IN SHARE MODE"))
        except OperationalError as exc:
            if getattr(exc.orig, "sqlstate", None) == "55P03":  # lock_not_available
                raise IndexerBusyError("audit_event is locked; the index waits for the next run") \
                    from None
            raise
    return conn.execute(select(func.max(AuditEvent.id))).scalar() or 0


class IndexerBusyError(Exception):
    """The indexer could not start its run now; nothing was changed."""


def _take_lease(catalog: Catalog, lease_s: float) -> int | None:
    """Claim the indexer's lease; return the mark, or None when another indexer holds it."""
    now = dt.datetime.now(dt.UTC)
    with catalog.write_lock(), catalog.engine.begin() as conn:
        row = conn.execute(
            update(_MARK)
            .where(_MARK.c.id == 1,
                   or_(_MARK.c.lease_until.is_(None), _MARK.c.lease_until < now))
            .values(lease_until=now + dt.timedelta(seconds=lease_s))
            .returning(_MARK.c.indexed_through)
        ).first()
    return None if row is None else int(row[0])


def _finish(conn: Connection, through: int) -> None:
    conn.execute(update(_MARK).where(_MARK.c.id == 1, _MARK.c.indexed_through < through)
                 .values(indexed_through=through))
    conn.execute(update(_MARK).where(_MARK.c.id == 1).values(lease_until=None))


# The batch sorted by patient, in a temporary table of the indexer's connection: rowids
# follow the sort, so the chunks below are ranges of them. Filled and read inside SQLite:
# taken through Python, a batch of some 100,000 links held the server's interpreter lock
# for a good part of a second, and every request of that worker waited.
_SQLITE_STAGE = (
    "CREATE TEMP TABLE IF NOT EXISTS audit_index_batch "
    "(patient_id INTEGER NOT NULL, event_id INTEGER NOT NULL)",
    "DELETE FROM temp.audit_index_batch",
)
_SQLITE_FILL = text(
    "INSERT INTO temp.audit_index_batch (patient_id, event_id) "
    "SELECT patient_id, event_id FROM audit_event_patient "
    "WHERE event_id > :mark AND event_id <= :through ORDER BY patient_id, event_id")
_SQLITE_ADD = text(
    "INSERT OR IGNORE INTO audit_patient_index (patient_id, event_id) "
    "SELECT patient_id, event_id FROM temp.audit_index_batch WHERE rowid BETWEEN :lo AND :hi")
# PostgreSQL's writers do not wait for this transaction, so one statement does it all.
_PG_ADD = text(
    "INSERT INTO audit_patient_index (patient_id, event_id) "
    "SELECT patient_id, event_id FROM audit_event_patient "
    "WHERE event_id > :mark AND event_id <= :through ORDER BY patient_id, event_id "
    "ON CONFLICT DO NOTHING")


def _index_sqlite(catalog: Catalog, conn: Connection, mark: int, through: int,
                  chunk: int) -> int:
    for statement in _SQLITE_STAGE:
        conn.exec_driver_sql(statement)
    # writes only the temporary table: no wait for, and no hold of, the catalogue's lock
    conn.execute(_SQLITE_FILL, {"mark": mark, "through": through})
    conn.commit()
    first, last = conn.exec_driver_sql(
        "SELECT min(rowid), max(rowid) FROM temp.audit_index_batch").one()
    conn.commit()
    first, last = (first or 1), (last or 0)
    added = 0
    lo = first
    # The index is derived data: its chunks commit without an fsync of their own (each
    # would hold the write lock the audit writers wait for through a disk flush). Every
    # audit commit (synchronous=FULL) flushes the log up to itself, these chunks included;
    # a power cut can take back only chunks written after the last audit commit, and a
    # run that lost its chunks, or its mark, is simply redone. NORMAL, not OFF: the log is
    # still flushed before it is copied into the database, so nothing can be corrupted.
    conn.exec_driver_sql("PRAGMA synchronous=NORMAL")
    try:
        while True:
            hi = min(lo + chunk - 1, last)
            with catalog.write_lock():
                if lo <= hi:
                    added += conn.execute(_SQLITE_ADD, {"lo": lo, "hi": hi}).rowcount
                if hi >= last:
                    # the mark moves in the transaction of the last links, never before
                    _finish(conn, through)
                conn.commit()
            if hi >= last:
                break
            lo = hi + 1
    finally:
        conn.rollback()
        # the connection goes back to the pool, where every other user expects FULL
        conn.exec_driver_sql("PRAGMA synchronous=FULL")
    conn.exec_driver_sql("DELETE FROM temp.audit_index_batch")
    conn.commit()
    return added


def _index_postgresql(conn: Connection, mark: int, through: int) -> int:
    added = conn.execute(_PG_ADD, {"mark": mark, "through": through}).rowcount
    _finish(conn, through)
    conn.commit()
    return added


def index_patient_links(catalog: Catalog, *, max_events: int = MAX_EVENTS,
                        chunk: int = CHUNK, lease_s: float = LEASE_S) -> int:
    """Add the patient links recorded since the mark to the index by patient.

    Parameters
    ----------
    catalog : Catalog
        The catalogue whose audit trail to index.
    max_events : int
        Most events to take in this run; the mark moves only as far.
    chunk : int
        Links per transaction on SQLite, where each holds the catalogue's write lock.
    lease_s : float
        Seconds this run may take before another indexer may take over.

    Returns
    -------
    int
        Links added; 0 also when another indexer is at work.
    """
    mark = _take_lease(catalog, lease_s)
    if mark is None:
        return 0
    done = False
    try:
        with catalog.engine.connect() as conn:
            try:
                through = min(committed_through(conn), mark + max_events)
            except IndexerBusyError:
                return 0  # the lease is given back below
            conn.commit()
            if conn.dialect.name == "postgresql":
                added = _index_postgresql(conn, mark, through)
            else:
                added = _index_sqlite(catalog, conn, mark, through, chunk)
        done = True
        return added
    finally:
        if not done:
            _release(catalog)


def _release(catalog: Catalog) -> None:
    """Give the lease back after a failed run, so the next starts at once, not after it."""
    try:
        with catalog.write_lock(), catalog.engine.begin() as conn:
            conn.execute(update(_MARK).where(_MARK.c.id == 1).values(lease_until=None))
    except Exception as exc:  # the lease runs out by itself; the run's own error matters
        log.warning("audit index lease not released: %s", type(exc).__name__)


class AuditIndexer:
    """A thread that runs :func:`index_patient_links` every ``every_s`` seconds.

    Each server process runs one; the lease lets one work at a time.

    Parameters
    ----------
    catalog : Catalog
        The catalogue whose audit trail to index.
    every_s : float
        Seconds between runs.
    """

    def __init__(self, catalog: Catalog, *, every_s: float = INDEX_EVERY_S) -> None:
        self._catalog = catalog
        self._every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="audit-indexer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._every_s):
            try:
                index_patient_links(self._catalog)
            except Exception as exc:  # retried next time; queries read the links meanwhile
                # the type only: a database error's message can quote patient data
                log.warning("audit index not brought up to date: %s", type(exc).__name__)

    def close(self) -> None:
        """Stop the thread (a run under way is finished first)."""
        self._stop.set()
        self._thread.join()
