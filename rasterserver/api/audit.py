"""The audit trail: one append-only event per request, linked to every patient it touched,
and its FHIR form.

Every routed, non-public request is recorded, reads included, refused ones too: who (account,
role), what (route template, method, FHIR action code), which patients' data and acquisition,
when, from where and with what outcome. The event is committed *before* the response starts
(group-committed with other requests' events, see :mod:`rasterserver.api.audit_writer`), so
no data leaves the server without its audit event; if it cannot be written the client gets a
503 instead of the data.

The application log gets only the route template (``/patients/{identifier}``), the status and
the duration, never the concrete path or query, which may carry patient identifiers.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import functools
import itertools
import logging
import os
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from fastapi import Request
from sqlalchemy import Dialect, select, text
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from rasterserver.api.audit_index import patient_events
from rasterserver.api.audit_writer import AuditWriter
from rasterserver.api.auth import Principal
from rasterserver.api.errors import send_error, traceback_without_values
from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditEvent, AuditEventPatient
from rasterserver.catalog.models import Patient

access_log = logging.getLogger("rasterserver.api.access")
log = logging.getLogger(__name__)

NOTE_KEY = "rasterserver.audit"


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


def note_of(request: Request) -> AuditNote:
    """Return the audit note of ``request`` (made by :class:`RequestMiddleware`)."""
    return note_of_scope(request.scope)


def note_of_scope(scope: Scope) -> AuditNote:
    """Return the audit note of the request ``scope`` (for middlewares)."""
    note = scope.get(NOTE_KEY)
    if note is None:  # a route called without the middleware (unit tests of a router)
        note = scope[NOTE_KEY] = AuditNote()
    return note


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


def insert_records(archive: Archive, records: Sequence[AuditRecord]) -> None:
    """Insert the events and patient links of ``records`` in one committed transaction."""
    if archive.engine.dialect.name == "postgresql":
        params: dict[str, list[Any]] = {
            name: [r.event[name] for r in records] for name in _COLUMNS}
        params["link_request"] = [r.event["request_id"]
                                  for r in records for _ in r.patient_ids]
        params["link_patient"] = [pid for r in records for pid in r.patient_ids]
        with archive.engine.connect().execution_options(
                isolation_level="AUTOCOMMIT") as conn:
            conn.execute(_PG_RECORDS, params)
        return
    with archive.write_lock(), archive.engine.begin() as conn:
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
    binds = {}
    for name in _COLUMNS:
        process = _EVENTS.c[name].type.bind_processor(dialect)
        if process is not None:
            binds[name] = process
    return binds


def write_events(archive: Archive, note: AuditNote, *, method: str, route: str, route_name: str,
                 status: int, client: str) -> None:
    """Record one request in the audit trail now (outside the server's group commit)."""
    insert_records(archive, [audit_record(note, method=method, route=route,
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


def record_admin_action(archive: Archive, *, action: str, what: str, detail: str) -> None:
    """Record a change of accounts or tokens made with the CLI in the audit trail.

    Over HTTP every request is audited by :class:`RequestMiddleware`; the CLI's commands
    that create accounts and tokens, revoke tokens, or disable and enable accounts write
    their event here, committed before the command reports success.

    Parameters
    ----------
    archive : Archive
        The archive whose audit trail records it.
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
    insert_records(archive, [record])


def audit_writer(archive: Archive) -> AuditWriter:
    """The server's group-committing writer of audit records into ``archive``'s catalogue."""
    # insert_records is looked up at each batch, so a test can make the catalogue refuse
    return AuditWriter(lambda records: insert_records(archive, records))


def _client(scope: Scope) -> str:
    client = scope.get("client")
    return f"{client[0]}" if client else ""


class RequestMiddleware:
    """Per request: audit row before the response, access log without patient data, metrics.

    Parameters
    ----------
    app : ASGIApp
        The application.
    services : object
        The app's services (``archive``, ``metrics``).
    """

    def __init__(self, app: ASGIApp, services: Any) -> None:
        self.app = app
        self.services = services

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        from rasterserver.api.roles import PUBLIC

        note = scope[NOTE_KEY] = AuditNote()
        started = time.perf_counter()
        replaced = False

        async def send_audited(message: Message) -> None:
            nonlocal replaced
            if replaced:
                return
            if message["type"] == "http.response.start":
                route = scope.get("route")
                name = getattr(route, "name", "") or ""
                # without converters: /patients/{patient}, not /patients/{patient:path}
                template = getattr(route, "path_format", "") or "(unrouted)"
                status = int(message["status"])
                elapsed = time.perf_counter() - started
                self.services.metrics.observe(scope["method"], template, status, elapsed)
                access_log.info("%s %s %d %.1f ms", scope["method"], template, status,
                                1000 * elapsed)
                if route is not None and name not in PUBLIC:
                    try:
                        record = audit_record(note, method=scope["method"], route=template,
                                              route_name=name, status=status,
                                              client=_client(scope))
                        # waits, without holding a thread, for the batch with this record
                        await asyncio.wrap_future(self.services.audit.submit(record))
                    except Exception as exc:
                        # fail closed: no data without its audit row
                        log.error("audit row of request %s not written: %s\n%s",
                                  note.request_id, type(exc).__name__,
                                  traceback_without_values(exc))
                        replaced = True
                        await send_error(send, 503, "audit trail unavailable",
                                         "AuditUnavailable")
                        return
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"],
                                      (b"x-request-id", note.request_id.encode())]
            await send(message)

        started_response = False

        async def send_tracked(message: Message) -> None:
            nonlocal started_response
            if message["type"] == "http.response.start":
                started_response = True
            await send_audited(message)

        try:
            await self.app(scope, receive, send_tracked)
        except Exception as exc:
            # Answered and audited here, and not re-raised: the server would log the
            # exception's message, and a database error's message quotes patient data.
            log.error("unexpected %s while handling a request\n%s", type(exc).__name__,
                      traceback_without_values(exc))
            if not started_response:
                # through send_tracked, so that the 500 is audited like any answer
                await send_error(send_tracked, 500, "internal error", "InternalError")


def audit_events(
    archive: Archive,
    *,
    patient: str | None = None,
    actor: str | None = None,
    since: dt.datetime | None = None,
    until: dt.datetime | None = None,
    limit: int = 100,
    offset: int = 0,
) -> list[tuple[AuditEvent, list[str]]]:
    """Audit events oldest first, each with the identifiers of the patients it touched.

    ``patient`` keeps the events that touched that patient; ``since`` is inclusive,
    ``until`` exclusive.
    """
    query = select(AuditEvent)
    if patient is not None:
        query = query.where(AuditEvent.id.in_(patient_events(patient)))
    if actor is not None:
        query = query.where(AuditEvent.actor == actor)
    if since is not None:
        query = query.where(AuditEvent.recorded_at >= since)
    if until is not None:
        query = query.where(AuditEvent.recorded_at < until)
    query = query.order_by(AuditEvent.id).limit(limit).offset(offset)
    with archive.session() as s:
        events = list(s.scalars(query))
        touched: dict[int, list[str]] = {}
        ids = [e.id for e in events]
        # bounded IN lists: SQLite limits the number of parameters of one statement
        for start in range(0, len(ids), 5000):
            for event_id, identifier in s.execute(
                select(AuditEventPatient.event_id, Patient.identifier)
                .join(Patient, Patient.id == AuditEventPatient.patient_id)
                .where(AuditEventPatient.event_id.in_(ids[start:start + 5000]))
                .order_by(AuditEventPatient.event_id, Patient.identifier)
            ):
                touched.setdefault(event_id, []).append(identifier)
    return [(e, touched.get(e.id, [])) for e in events]


_SUBTYPES = {"C": "create", "R": "read", "U": "update", "D": "delete", "E": "operation"}


def event_dict(event: AuditEvent, patients: list[str]) -> dict[str, Any]:
    """The plain JSON form of one audit event."""
    return {
        "id": event.id,
        "request_id": event.request_id,
        "recorded_at": _utc(event.recorded_at).isoformat(),
        "actor": event.actor,
        "actor_kind": event.actor_kind,
        "role": event.role,
        "action": event.action,
        "method": event.method,
        "route": event.route,
        "status": event.status,
        "patients": patients,
        "acquisition": event.acquisition_uid,
        "client": event.client,
    }


def _utc(value: dt.datetime) -> dt.datetime:
    # SQLite hands timestamps back without their zone; they were stored in UTC
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


def to_fhir(event: AuditEvent, patients: list[str]) -> dict[str, Any]:
    """Return one audit event as a FHIR R4 ``AuditEvent`` resource.

    Parameters
    ----------
    event : AuditEvent
        The row.
    patients : list of str
        The site identifiers of the patients whose data the request touched.

    Returns
    -------
    dict
        JSON-ready resource.
    """
    outcome = "0" if event.status < 400 else ("4" if event.status < 500 else "8")
    agent: dict[str, Any] = {
        "type": {"coding": [{
            "system": "http://terminology.hl7.org/CodeSystem/extra-security-role-type",
            "code": "humanuser" if event.actor_kind == "user" else "dataprocessor",
        }]},
        "who": {"display": event.actor},
        "requestor": True,
        "role": [{"text": event.role or "unauthenticated"}],
    }
    if event.client:
        agent["network"] = {"address": event.client, "type": "2"}
    entities: list[dict[str, Any]] = []
    for identifier in patients:
        entities.append({
            "what": {"identifier": {"value": identifier}},
            "type": {"system": "http://terminology.hl7.org/CodeSystem/audit-entity-type",
                     "code": "1", "display": "Person"},
            "role": {"system": "http://terminology.hl7.org/CodeSystem/object-role",
                     "code": "1", "display": "Patient"},
        })
    if event.acquisition_uid:
        entities.append({
            "what": {"identifier": {"system": "urn:rasterserver:acquisition",
                                    "value": event.acquisition_uid}},
            "type": {"system": "http://terminology.hl7.org/CodeSystem/audit-entity-type",
                     "code": "2", "display": "System Object"},
        })
    entities.append({"what": {"display": f"{event.method} {event.route}"},
                     "type": {"system": "http://terminology.hl7.org/CodeSystem/audit-entity-type",
                              "code": "4", "display": "Other"}})
    return {
        "resourceType": "AuditEvent",
        "id": str(event.id),
        "type": {"system": "http://terminology.hl7.org/CodeSystem/audit-event-type",
                 "code": "rest", "display": "RESTful Operation"},
        "subtype": [{"system": "http://hl7.org/fhir/restful-interaction",
                     "code": _SUBTYPES.get(event.action, "read")}],
        "action": event.action,
        "recorded": _utc(event.recorded_at).isoformat(),
        "outcome": outcome,
        "outcomeDesc": f"HTTP {event.status}",
        "agent": [agent],
        "source": {"observer": {"display": "rasterserver"},
                   "type": [{"system": "http://terminology.hl7.org/CodeSystem/security-source-type",
                             "code": "4", "display": "Application Server"}]},
        "entity": entities,
    }


def fhir_bundle(events: list[tuple[AuditEvent, list[str]]]) -> dict[str, Any]:
    """A FHIR ``Bundle`` (type ``collection``) of audit events."""
    return {
        "resourceType": "Bundle",
        "type": "collection",
        "total": len(events),
        "entry": [{"resource": to_fhir(e, patients)} for e, patients in events],
    }
