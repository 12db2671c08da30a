"""One router module per resource; :data:`ROUTERS` is what the app includes."""

from __future__ import annotations

from fastapi import APIRouter

from rasterserver.api.routers import (
    accounts,
    acquisitions,
    audit,
    health,
    jobs,
    patients,
    plugins,
    results,
    stations,
)

ROUTERS: list[APIRouter] = [
    health.router,
    plugins.router,
    accounts.router,
    stations.router,
    patients.router,
    acquisitions.router,
    results.router,
    jobs.router,
    audit.router,
]
