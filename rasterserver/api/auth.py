"""The HTTP side of authentication: the bearer scheme and the FastAPI dependency
:func:`authorize` of every protected route.

Accounts and tokens themselves (creation, look-up, revocation, expiry) are the service
:mod:`rasterserver.services.auth`, shared with the CLI.
"""

from __future__ import annotations

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from rasterserver.api.audit import note_of
from rasterserver.api.roles import allowed
from rasterserver.services.auth import Principal, authenticate, cached_owner

__all__ = ["authorize"]

_bearer = HTTPBearer(auto_error=False, description="An API token from `rasterserver token create`.")


async def authorize(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
) -> Principal:
    """FastAPI dependency of every protected route: authenticate, then apply the role rule.

    The rule is looked up by the matched route's name in
    :data:`rasterserver.api.roles.RULES`, so it is written once, in that table.

    On PostgreSQL the token is mostly found in the services' token cache
    (:mod:`rasterserver.services.token_cache`), without a round trip; otherwise it is looked
    up through ``services.read``: on the event loop on SQLite (one indexed read of a small
    table, tens of microseconds, cheaper than a hand-over to a thread), in a thread on
    PostgreSQL.

    Raises
    ------
    HTTPException
        401 without a valid token, 403 when the role may not use the route.
    """
    note = note_of(request)
    # established by the gate before the body was read (rasterserver.api.gate)
    gated: Principal | None = request.scope.get("rasterserver.principal")
    if gated is not None:
        note.principal = gated
        return gated
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(401, "a bearer token is required",
                            headers={"WWW-Authenticate": "Bearer"})
    services = request.app.state.services
    cache = getattr(services, "token_cache", None)
    principal = cached_owner(cache, credentials.credentials)
    if principal is None:
        principal = await services.read(authenticate, services.catalog,
                                        credentials.credentials, cache)
    if principal is None:
        raise HTTPException(401, "invalid, expired or revoked token, or a disabled account",
                            headers={"WWW-Authenticate": "Bearer"})
    note.principal = principal
    route = request.scope.get("route")
    name = getattr(route, "name", "")
    if not allowed(name, principal.role):
        raise HTTPException(403, f"the {principal.role} role may not use this operation")
    return principal
