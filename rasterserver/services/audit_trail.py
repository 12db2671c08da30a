"""Reading the audit trail back: events by patient, actor and time, as JSON or as FHIR R4
``AuditEvent`` resources (the CLI's ``audit`` command and ``GET /audit``).
"""

from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from rasterserver.catalog.auth_models import AuditEvent, AuditEventPatient
from rasterserver.catalog.models import Patient
from rasterserver.services.audit_index import patient_events

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

def audit_events(
    catalog: Catalog,
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
    with catalog.session() as s:
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
