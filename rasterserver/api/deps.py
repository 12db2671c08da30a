"""Dependencies shared by the routers: services, the caller, pagination, conditional GETs."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated

from fastapi import APIRouter, Depends, Path, Query, Request, Response

from rasterserver.api.audit import note_of
from rasterserver.api.auth import authorize
from rasterserver.services.audit import AuditNote
from rasterserver.services.auth import Principal

if TYPE_CHECKING:
    from rasterserver.api.app import Services

#: An acquisition's uid as a path parameter.
Uid = Annotated[str, Path(max_length=32, description="Acquisition uid.")]

MAX_PAGE = 1000
# SQLite integers are 64-bit; a bound well inside keeps absurd offsets a 422, not a crash
MAX_OFFSET = 10**12


# The dependencies below that do no I/O are ``async def``: FastAPI runs a plain ``def``
# dependency in a worker thread, and the hand-over costs more than the function.


async def services(request: Request) -> Services:
    """The app's :class:`~rasterserver.api.app.Services`."""
    return request.app.state.services


@dataclass(frozen=True)
class Page:
    """``limit`` and ``offset`` of a list."""

    limit: int
    offset: int


async def page(
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description="Items per page.")] = 100,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="Items to skip.")] = 0,
) -> Page:
    """Pagination parameters of every list."""
    return Page(limit, offset)


ServicesDep = Annotated["Services", Depends(services)]
CallerDep = Annotated[Principal, Depends(authorize)]
PageDep = Annotated[Page, Depends(page)]


async def audit_note(request: Request) -> AuditNote:
    """The request's audit note, for handlers to record which patient they touched."""
    return note_of(request)


NoteDep = Annotated[AuditNote, Depends(audit_note)]


def protected_router(tag: str) -> APIRouter:
    """A router whose every route requires a token and passes the role table."""
    return APIRouter(tags=[tag], dependencies=[Depends(authorize)],
                     responses={401: {"description": "No or invalid token"},
                                403: {"description": "The role may not use this route"}})


def not_modified(request: Request, etag: str) -> Response | None:
    """A 304 response when the client's ``If-None-Match`` names ``etag``, else None."""
    quoted = f'"{etag}"'
    wanted = request.headers.get("if-none-match", "")
    if quoted in [part.strip() for part in wanted.split(",")] or wanted.strip() == "*":
        return Response(status_code=304, headers={"ETag": quoted})
    return None


def utc(value: dt.datetime | None) -> dt.datetime | None:
    """Take a time without zone as UTC (SQLite returns them so; clients may send them so)."""
    if value is None:
        return None
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)
