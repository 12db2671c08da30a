"""``/health`` (no token) and ``/metrics`` (admin)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4

from rasterserver import __version__
from rasterserver.api.auth import authorize
from rasterserver.api.deps import ServicesDep
from rasterserver.api.schemas import Health
from rasterserver.catalog import migrate

router = APIRouter(tags=["service"])


@router.get("/health", name="health", response_model=Health)
def health(svc: ServicesDep) -> Health:
    """Liveness and the catalogue's schema revision; needs no token."""
    return Health(status="ok", version=__version__,
                  schema_revision=migrate.current_revision(svc.catalog.engine))


@router.get("/metrics", name="metrics", response_class=PlainTextResponse,
            dependencies=[Depends(authorize)],
            responses={200: {"content": {"text/plain": {}}}})
def metrics(svc: ServicesDep) -> PlainTextResponse:
    """Request counts and latencies of every worker, and the jobs, as Prometheus text."""
    extra = {f"rasterserver_jobs_{state}": len(svc.jobs.list(status=state, limit=10**6))
             for state in ("running", "queued")}
    return PlainTextResponse(svc.metrics.render(extra), media_type=CONTENT_TYPE_PLAIN_0_0_4)
