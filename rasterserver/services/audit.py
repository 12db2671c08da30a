"""The audit trail's records: what one request (or CLI command) did, and their group-committed
insertion into the catalogue.

Every routed, non-public HTTP request is recorded, reads included, refused ones too: who
(account, role), what (route template, method, FHIR action code), which patients' data and
acquisition, when, from where and with what outcome. The HTTP middleware that builds the
records is :class:`rasterserver.api.audit.RequestMiddleware`; the CLI's account and token
commands record theirs with :func:`record_admin_action`. Reading the trail back (and its
FHIR form) is :mod:`rasterserver.services.audit_trail`.
"""

from __future__ import annotations

import datetime as dt
import functools
import itertools
import os
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from sqlalchemy import Dialect, text

from rasterserver.catalog.auth_models import AuditEvent
from rasterserver.services.audit_writer import AuditWriter
from rasterserver.services.auth import Principal

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

@dataclass
class AuditNote:
    """What one request did, filled in by the auth dependency and the route handlers."""

    request_id: str = field(default_factory=lambda: new_request_id())
    principal: Principal | None = None
    patient_ids: set[int] = field(default_factory=set)
    acquisition_uid: str | None = None
    detail: str = ""

    def touch(self, patient_id: int | None, acquisition_uid: str | None = None) -> None:
        """Record that the request reads or changes this patient's (or acquisition's) data."""
        if patient_id is not None:
            self.patient_ids.add(patient_id)
        if acquisition_uid is not None:
            self.acquisition_uid = acquisition_uid


def new_request_id() -> str:
    """A request id that sorts by time: 64 bits of nanoseconds, 32 random bits of this
    process, a 32-bit count of its requests.

    The audit table indexes it; random ids (uuid4) land all over that index, and once the
    table holds millions of rows every insert misses the cache. Time-ordered ids append.
    The process's bits keep the servers sharing one catalogue apart, the count the
    requests of one process; drawing 64 random bits per request instead was a system call
    each time, a few percent of the server's work.
    """
    return f"{time.time_ns():016x}{_PROCESS_BITS:08x}{next(_REQUESTS) & 0xFFFFFFFF:08x}"


_PROCESS_BITS = secrets.randbits(32)
_REQUESTS = itertools.count()


def _new_process() -> None:
    global _PROCESS_BITS  # a forked worker must not share its parent's bits
    _PROCESS_BITS = secrets.randbits(32)


os.register_at_fork(after_in_child=_new_process)


def action_code(method: str, route_name: str) -> str:
    """FHIR AuditEvent.action of a request: C, R, U, D or E (execute: processing)."""
    if route_name == "start_job":
        return "E"
    return {"POST": "C", "PUT": "U", "PATCH": "U", "DELETE": "D"}.get(method, "R")


@dataclass(frozen=True)
class AuditRecord:
    """One request's audit event (the ``audit_event`` row) and the patients it touched."""

    event: dict[str, Any]
    patient_ids: tuple[int, ...]


def audit_record(note: AuditNote, *, method: str, route: str, route_name: str, status: int,
                 client: str) -> AuditRecord:
    """What one request leaves in the audit trail."""
    who = note.principal
    return AuditRecord(
        event={
            "request_id": note.request_id,
            "recorded_at": dt.datetime.now(dt.UTC),
            "actor": who.name if who else "-",
            "actor_kind": who.kind if who else "",
            "role": who.role if who else "",
            "action": action_code(method, route_name),
            "method": method[:8],
            "route": route[:200],
            "status": status,
            "patient_id": None,  # see AuditEvent.patient_id: the links name the patients
            "acquisition_uid": note.acquisition_uid,
            "client": client[:100],
            "detail": note.detail,
        },
        patient_ids=tuple(sorted(note.patient_ids)),
    )


_EVENTS = AuditEvent.__table__
_COLUMNS = {"request_id": "varchar", "recorded_at": "timestamptz", "actor": "varchar",
            "actor_kind": "varchar", "role": "varchar", "action": "varchar",
            "method": "varchar", "route": "varchar", "status": "integer",
            "acquisition_uid": "varchar", "client": "varchar", "detail": "text"}
# On PostgreSQL a batch is one statement, run outside a transaction block (a statement is
# atomic and durable by itself): the events from arrays, one per column, and their links
# joined on the request id. As a transaction of three statements it took five round trips
# (BEGIN and COMMIT too), and under load the writer thread waited for the interpreter's
# lock after each: commits of ~10 requests took 13 ms, which the requests waited for. The
# text is the same for every batch, so the server prepares it once per connection.
_PG_RECORDS = text(
    "WITH event AS (INSERT INTO audit_event ({}) SELECT * FROM unnest({}) "
    "RETURNING id, request_id) "
    "INSERT INTO audit_event_patient (event_id, patient_id) "
    "SELECT event.id, link.patient_id FROM event JOIN unnest("
    "CAST(:link_request AS varchar[]), CAST(:link_patient AS integer[])) "
    "AS link (request_id, patient_id) ON link.request_id = event.request_id".format(
        ", ".join(_COLUMNS),
        ", ".join(f"CAST(:{name} AS {kind}[])" for name, kind in _COLUMNS.items())))


def insert_records(catalog: Catalog, records: Sequence[AuditRecord]) -> None:
    """Insert the events and patient links of ``records`` in one committed transaction."""
    if catalog.engine.dialect.name == "postgresql":
        params: dict[str, list[Any]] = {
            name: [r.event[name] for r in records] for name in _COLUMNS}
        params["link_request"] = [r.event["request_id"]
                                  for r in records for _ in r.patient_ids]
        params["link_patient"] = [pid for r in records for pid in r.patient_ids]
        with catalog.engine.connect().execution_options(
                isolation_level="AUTOCOMMIT") as conn:
            conn.execute(_PG_RECORDS, params)
        return
    with catalog.write_lock(), catalog.engine.begin() as conn:
        # Straight to the driver: the writer thread runs this while holding the
        # interpreter, so the event loop of the same process waits for it; through the ORM's
        # executemany with RETURNING it cost three times as much.
        to_db = _sqlite_binds(conn.dialect)
        cursor = conn.connection.cursor()
        try:
            cursor.executemany(_SQLITE_EVENTS, [
                tuple(to_db[name](r.event[name]) if name in to_db else r.event[name]
                      for name in _COLUMNS) for r in records])
            # This transaction holds SQLite's only write lock from its first insert on, so
            # the new ids are consecutive and end at the last one.
            last = cursor.execute("SELECT last_insert_rowid()").fetchone()[0]
            first = last - len(records) + 1
            links = [(event_id, pid) for event_id, r in enumerate(records, start=first)
                     for pid in r.patient_ids]
            if links:
                cursor.executemany(_SQLITE_LINKS, links)
        finally:
            cursor.close()


_SQLITE_EVENTS = "INSERT INTO audit_event ({}) VALUES ({})".format(
    ", ".join(_COLUMNS), ", ".join("?" * len(_COLUMNS)))
_SQLITE_LINKS = "INSERT INTO audit_event_patient (event_id, patient_id) VALUES (?, ?)"


@functools.cache
def _sqlite_binds(dialect: Dialect) -> dict[str, Callable[[Any], Any]]:
    """The dialect's conversions of the event columns that need one (the timestamps)."""
    binds: dict[str, Callable[[Any], Any]] = {}
    for name in _COLUMNS:
        process = _EVENTS.c[name].type.bind_processor(dialect)
        if process is not None:
            binds[name] = process
    return binds


def write_events(catalog: Catalog, note: AuditNote, *, method: str, route: str, route_name: str,
                 status: int, client: str) -> None:
    """Record one request in the audit trail now (outside the server's group commit)."""
    insert_records(catalog, [audit_record(note, method=method, route=route,
                                          route_name=route_name, status=status, client=client)])


def cli_actor() -> str:
    """Who runs this command, for the audit trail: ``cli:<login>`` (``cli:uid-N`` without
    a name, e.g. in a container whose user has no passwd entry)."""
    import getpass

    try:
        login = getpass.getuser()
    except (KeyError, OSError):
        login = f"uid-{os.getuid()}"
    return f"cli:{login}"[:100]


def record_admin_action(catalog: Catalog, *, action: str, what: str, detail: str) -> None:
    """Record a change of accounts or tokens made with the CLI in the audit trail.

    Over HTTP every request is audited by
    :class:`rasterserver.api.audit.RequestMiddleware`; the CLI's commands
    that create accounts and tokens, revoke tokens, or disable and enable accounts write
    their event here, committed before the command reports success.

    Parameters
    ----------
    catalog : Catalog
        The catalogue whose audit trail records it.
    action : str
        FHIR action code: ``C`` create, ``U`` update, ``D`` delete.
    what : str
        The command, e.g. ``token create`` (the event's route).
    detail : str
        What was done to what: account names, token ids, never a token.
    """
    note = AuditNote(principal=Principal(0, cli_actor(), "admin", "user"), detail=detail)
    record = audit_record(note, method="CLI", route=f"cli: {what}", route_name="",
                          status=200, client="local")
    record.event["action"] = action
    insert_records(catalog, [record])


def audit_writer(catalog: Catalog) -> AuditWriter:
    """The server's group-committing writer of audit records into ``catalog``."""
    # insert_records is looked up at each batch, so a test can make the catalogue refuse
    return AuditWriter(lambda records: insert_records(catalog, records))
