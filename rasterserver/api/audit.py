"""The HTTP side of the audit trail: the request middleware that records every routed,
non-public request before its response starts, and the request's audit note.

The event is committed *before* the response starts (group-committed with other requests'
events, see :mod:`rasterserver.services.audit_writer`), so no data leaves the server without
its audit event; if it cannot be written the client gets a 503 instead of the data. The
records themselves are :mod:`rasterserver.services.audit`.

The application log gets only the route template (``/patients/{identifier}``), the status and
the duration, never the concrete path or query, which may carry patient identifiers.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from fastapi import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from rasterserver.api.errors import send_error, traceback_without_values
from rasterserver.api.roles import PUBLIC
from rasterserver.services.audit import AuditNote, audit_record

access_log = logging.getLogger("rasterserver.api.access")
log = logging.getLogger(__name__)

NOTE_KEY = "rasterserver.audit"


def note_of(request: Request) -> AuditNote:
    """Return the audit note of ``request`` (made by :class:`RequestMiddleware`)."""
    return note_of_scope(request.scope)


def note_of_scope(scope: Scope) -> AuditNote:
    """Return the audit note of the request ``scope`` (for middlewares)."""
    note = scope.get(NOTE_KEY)
    if note is None:  # a route called without the middleware (unit tests of a router)
        note = scope[NOTE_KEY] = AuditNote()
    return note


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
        The app's services (``metrics``, ``audit``: the writer).
    """

    def __init__(self, app: ASGIApp, services: Any) -> None:
        self.app = app
        self.services = services

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
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
