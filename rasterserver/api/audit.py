"""The audit trail: one append-only row per request and patient touched, and its FHIR form.

Every routed, non-public request is recorded, reads included, refused ones too: who (account,
role), what (route template, method, FHIR action code), which patient's data and acquisition,
when, from where and with what outcome. The row is committed *before* the response starts, so
no data leaves the server without its audit row; if the row cannot be written the client gets
a 503 instead of the data.

The application log gets only the route template (``/patients/{identifier}``), the status and
the duration, never the concrete path or query, which may carry patient identifiers.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import secrets
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from fastapi import Request
from sqlalchemy import select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from rasterserver.api.audit_writer import AuditWriter
from rasterserver.api.auth import Principal
from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import AuditEvent
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
    """A request id that sorts by time: 64 bits of nanoseconds, then 64 random bits.

    The audit table indexes it; random ids (uuid4) land all over that index, and once the
    table holds millions of rows every insert misses the cache. Time-ordered ids append.
    """
    return f"{time.time_ns():016x}{secrets.randbits(64):016x}"


def note_of(request: Request) -> AuditNote:
    """Return the audit note of ``request`` (made by :class:`RequestMiddleware`)."""
    note = request.scope.get(NOTE_KEY)
    if note is None:  # a route called without the middleware (unit tests of a router)
        note = request.scope[NOTE_KEY] = AuditNote()
    return note


def action_code(method: str, route_name: str) -> str:
    """FHIR AuditEvent.action of a request: C, R, U, D or E (execute: processing)."""
    if route_name == "start_job":
        return "E"
    return {"POST": "C", "PUT": "U", "PATCH": "U", "DELETE": "D"}.get(method, "R")


def event_rows(note: AuditNote, *, method: str, route: str, route_name: str, status: int,
               client: str) -> list[dict[str, Any]]:
    """The audit rows of one request: one per patient touched, or one without a patient."""
    who = note.principal
    base = {
        "request_id": note.request_id,
        "recorded_at": dt.datetime.now(dt.UTC),
        "actor": who.name if who else "-",
        "actor_kind": who.kind if who else "",
        "role": who.role if who else "",
        "action": action_code(method, route_name),
        "method": method[:8],
        "route": route[:200],
        "status": status,
        "acquisition_uid": note.acquisition_uid,
        "client": client[:100],
        "detail": note.detail,
    }
    return [base | {"patient_id": pid} for pid in sorted(note.patient_ids)] or [
        base | {"patient_id": None}
    ]


def insert_rows(archive: Archive, rows: Sequence[dict[str, Any]]) -> None:
    """Insert audit rows in one committed transaction (Core: no ORM objects to build)."""
    with archive.engine.begin() as conn:
        conn.execute(AuditEvent.__table__.insert(), list(rows))


def write_events(archive: Archive, note: AuditNote, *, method: str, route: str, route_name: str,
                 status: int, client: str) -> None:
    """Insert and commit the audit rows of one request (outside the server's group commit)."""
    insert_rows(archive, event_rows(note, method=method, route=route, route_name=route_name,
                                    status=status, client=client))


def audit_writer(archive: Archive) -> AuditWriter:
    """The server's group-committing writer of audit rows into ``archive``'s catalogue."""
    # looked up at each batch, so a test can make the catalogue refuse the rows
    return AuditWriter(lambda rows: insert_rows(archive, rows))


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
                template = getattr(route, "path", "") or "(unrouted)"
                status = int(message["status"])
                elapsed = time.perf_counter() - started
                self.services.metrics.observe(scope["method"], template, status, elapsed)
                access_log.info("%s %s %d %.1f ms", scope["method"], template, status,
                                1000 * elapsed)
                if route is not None and name not in PUBLIC:
                    try:
                        rows = event_rows(note, method=scope["method"], route=template,
                                          route_name=name, status=status,
                                          client=_client(scope))
                        # waits, without holding a thread, for the batch with these rows
                        await asyncio.wrap_future(self.services.audit.submit(rows))
                    except Exception as exc:
                        # fail closed: no data without its audit row
                        from rasterserver.api.errors import traceback_without_values

                        log.error("audit row of request %s not written: %s\n%s",
                                  note.request_id, type(exc).__name__,
                                  traceback_without_values(exc))
                        replaced = True
                        body = json.dumps({"detail": "audit trail unavailable",
                                           "error": "AuditUnavailable"}).encode()
                        await send({"type": "http.response.start", "status": 503,
                                    "headers": [(b"content-type", b"application/json"),
                                                (b"content-length", str(len(body)).encode())]})
                        await send({"type": "http.response.body", "body": body})
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
            from rasterserver.api.errors import error_body, traceback_without_values

            log.error("unexpected %s while handling a request\n%s", type(exc).__name__,
                      traceback_without_values(exc))
            if not started_response:
                body = json.dumps(error_body(500, "internal error", "InternalError")).encode()
                await send_tracked({"type": "http.response.start", "status": 500,
                                    "headers": [(b"content-type", b"application/json"),
                                                (b"content-length", str(len(body)).encode())]})
                await send_tracked({"type": "http.response.body", "body": body})


def audit_events(
    archive: Archive,
    *,
    patient: str | None = None,
    actor: str | None = None,
    since: dt.datetime | None = None,
    until: dt.datetime | None = None,
    limit: int = 100,
    offset: int = 0,
) -> list[tuple[AuditEvent, str | None]]:
    """Audit events oldest first, each with its patient's identifier (or None).

    ``since`` is inclusive, ``until`` exclusive.
    """
    query = select(AuditEvent, Patient.identifier).outerjoin(
        Patient, Patient.id == AuditEvent.patient_id
    )
    if patient is not None:
        query = query.where(Patient.identifier == patient)
    if actor is not None:
        query = query.where(AuditEvent.actor == actor)
    if since is not None:
        query = query.where(AuditEvent.recorded_at >= since)
    if until is not None:
        query = query.where(AuditEvent.recorded_at < until)
    query = query.order_by(AuditEvent.id).limit(limit).offset(offset)
    with archive.session() as s:
        return [(row, ident) for row, ident in s.execute(query)]


_SUBTYPES = {"C": "create", "R": "read", "U": "update", "D": "delete", "E": "operation"}


def event_dict(event: AuditEvent, patient_identifier: str | None) -> dict[str, Any]:
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
        "patient": patient_identifier,
        "acquisition": event.acquisition_uid,
        "client": event.client,
    }


def _utc(value: dt.datetime) -> dt.datetime:
    # SQLite hands timestamps back without their zone; they were stored in UTC
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


def to_fhir(event: AuditEvent, patient_identifier: str | None) -> dict[str, Any]:
    """Return one audit event as a FHIR R4 ``AuditEvent`` resource.

    Parameters
    ----------
    event : AuditEvent
        The row.
    patient_identifier : str or None
        The site identifier of the patient concerned.

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
    if patient_identifier is not None:
        entities.append({
            "what": {"identifier": {"value": patient_identifier}},
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


def fhir_bundle(events: list[tuple[AuditEvent, str | None]]) -> dict[str, Any]:
    """A FHIR ``Bundle`` (type ``collection``) of audit events."""
    return {
        "resourceType": "Bundle",
        "type": "collection",
        "total": len(events),
        "entry": [{"resource": to_fhir(e, ident)} for e, ident in events],
    }
