"""One router module per resource; :data:`ROUTERS` is what the app includes."""

from __future__ import annotations

from fastapi import APIRouter

from rasterserver.api.routers import (
    accounts,
    acquisitions,
    analysis,
    audit,
    comparison,
    health,
    jobs,
    patients,
    plugins,
    results,
    stations,
)

# Matched in this order, route by route: the busiest (clinicians' reads) first.
ROUTERS: list[APIRouter] = [
    acquisitions.router,
    # before patients: /patients/{patient:path} would take /patients/X/trends
    comparison.router,
    patients.router,
    health.router,
    plugins.router,
    accounts.router,
    stations.router,
    results.router,
    analysis.router,
    jobs.router,
    audit.router,
]
