"""Authenticate a request before its body is read.

FastAPI resolves a route's dependencies, the token check among them, only after it has read
and parsed the body: a 250 MB upload without a token was received whole before its 401.
:class:`AuthGate` checks the token and the role of every request that may carry a body as
soon as its headers are in, and refuses it (401, 403) without reading a byte of the body,
closing the connection so the client stops sending. The route's ``authorize`` dependency
then finds the caller the gate established and does not look the token up again.

Requests without a body (GET, HEAD, OPTIONS without ``Content-Length`` or
``Transfer-Encoding``) are left to the dependency, which costs them no route matching here.
"""

from __future__ import annotations

import json
from typing import Any

from starlette.routing import Match
from starlette.types import ASGIApp, Receive, Scope, Send

from rasterserver.api.audit import note_of_scope
from rasterserver.api.errors import all_routes
from rasterserver.services.audit import AuditNote
from rasterserver.services.auth import Principal, authenticate, cached_owner

#: Where the gate leaves the caller for :func:`rasterserver.api.auth.authorize`.
PRINCIPAL_KEY = "rasterserver.principal"

_BODILESS = frozenset({"GET", "HEAD", "OPTIONS"})


def may_have_body(scope: Scope) -> bool:
    """Whether the request may carry a body: a method that takes one, or a header that
    announces one."""
    if scope["method"] not in _BODILESS:
        return True
    return any(name in (b"content-length", b"transfer-encoding") and value not in (b"0", b"")
               for name, value in scope.get("headers", []))


def bearer_token(scope: Scope) -> str | None:
    """The bearer token of the request's ``Authorization`` header, if any."""
    for name, value in scope.get("headers", []):
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                return token.strip()
    return None


class AuthGate:
    """Refuse unauthenticated or unauthorised requests before their body is received.

    Parameters
    ----------
    app : ASGIApp
        The application.
    services : object
        The app's services (``catalog``, ``token_cache``, ``read``).
    routes : list
        The app's routes (``app.router.routes``), to find the route's name and so its rule.
    """

    def __init__(self, app: ASGIApp, services: Any, routes: list[Any]) -> None:
        self.app = app
        self.services = services
        self._routes = routes

    def _route(self, scope: Scope) -> Any:
        for route in all_routes(self._routes):
            match, _ = route.matches(scope)
            if match is Match.FULL:
                return route
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not may_have_body(scope):
            await self.app(scope, receive, send)
            return
        from rasterserver.api.roles import PUBLIC, allowed

        route = self._route(scope)
        name: str = getattr(route, "name", None) or ""
        if route is None or name in PUBLIC:
            await self.app(scope, receive, send)
            return
        token = bearer_token(scope)
        principal: Principal | None = None
        if token is not None:
            cache = getattr(self.services, "token_cache", None)
            principal = cached_owner(cache, token)
            if principal is None:
                principal = await self.services.read(authenticate, self.services.catalog,
                                                     token, cache)
        # the audit trail names the route the refusal was for (see RequestMiddleware)
        scope["route"] = route
        note: AuditNote = note_of_scope(scope)
        if principal is None:
            detail = ("a bearer token is required" if token is None else
                      "invalid, expired or revoked token, or a disabled account")
            await _refuse(send, 401, detail, "Unauthorized",
                          [(b"www-authenticate", b"Bearer")])
            return
        note.principal = principal
        if not allowed(name, principal.role):
            await _refuse(send, 403, f"the {principal.role} role may not use this operation",
                          "Forbidden", [])
            return
        scope[PRINCIPAL_KEY] = principal
        await self.app(scope, receive, send)


async def _refuse(send: Send, status: int, detail: str, kind: str,
                  extra: list[tuple[bytes, bytes]]) -> None:
    """Answer without reading the body, and close the connection: the client may still be
    sending it, and a connection with an unread body cannot carry another request."""
    body = json.dumps({"detail": detail, "error": kind, "status": status}).encode()
    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode()), (b"connection", b"close"),
               *extra]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
