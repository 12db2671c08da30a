"""``/audit``: the audit trail, as JSON or as a FHIR ``Bundle`` of ``AuditEvent`` (admin)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Query

from rasterserver.api.deps import PageDep, ServicesDep, protected_router, utc
from rasterserver.api.fields import Instant
from rasterserver.api.schemas import AuditOut
from rasterserver.services.audit_trail import audit_events, event_dict, fhir_bundle
from rasterserver.times import TIME_RULE

router = protected_router("audit")


@router.get("/audit", name="get_audit", response_model=list[AuditOut] | dict[str, Any])
def get_audit(
    svc: ServicesDep, page: PageDep,
    format: Annotated[Literal["json", "fhir"], Query(description="json, or fhir: a FHIR R4 "
                                                     "Bundle of AuditEvent resources")] = "json",
    patient: Annotated[str | None, Query(max_length=64)] = None,
    actor: Annotated[str | None, Query(max_length=100)] = None,
    since: Annotated[Instant | None, Query(description=f"At or after: {TIME_RULE}.")] = None,
    until: Annotated[Instant | None, Query(description="Before (as since).")] = None,
) -> list[AuditOut] | dict[str, Any]:
    """Audit events, oldest first, by patient, actor and time."""
    events = audit_events(svc.catalog, patient=patient, actor=actor, since=utc(since),
                          until=utc(until), limit=page.limit, offset=page.offset)
    if format == "fhir":
        return fhir_bundle(events)
    return [AuditOut(**event_dict(e, patients)) for e, patients in events]
