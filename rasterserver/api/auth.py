"""Accounts and API tokens: creation (CLI), lookup (every request), revocation.

A token is 32 random bytes (``secrets.token_urlsafe``) shown once when created; the
catalogue keeps only its SHA-256. Tokens carry enough entropy that a plain hash cannot be
brute-forced, so no per-token salt or slow hash is needed, and a lookup is one indexed
query.

On SQLite every request runs that query. On PostgreSQL, where it is a network round trip,
the server keeps the owners of the tokens it has seen in a
:class:`~rasterserver.api.token_cache.TokenCache`, which the database empties through
LISTEN/NOTIFY whenever a token or account changes: a revoked token is refused as soon as
that notification arrives (milliseconds), and while the notifications cannot be received
the cache is not used.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import secrets
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import bindparam, select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import ACCOUNT_KINDS, ROLES, ApiAccount, ApiToken
from rasterserver.catalog.lookup import stored_name
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.identifiers import check_name

if TYPE_CHECKING:
    from rasterserver.api.token_cache import TokenCache

TOKEN_PREFIX = "rs_"


@dataclass(frozen=True)
class Principal:
    """Who is making a request.

    Attributes
    ----------
    account_id : int
        Row id of the account.
    name : str
        Account name (a person's login or a station's service name).
    role : str
        One of :data:`rasterserver.catalog.auth_models.ROLES`.
    kind : str
        ``user`` or ``service``.
    """

    account_id: int
    name: str
    role: str
    kind: str


@dataclass(frozen=True)
class TokenInfo:
    """A token as listed: never the secret itself."""

    id: int
    account: str
    role: str
    prefix: str
    label: str
    created_at: dt.datetime
    revoked_at: dt.datetime | None


def token_digest(token: str) -> str:
    """Return the SHA-256 hex digest under which ``token`` is stored."""
    return hashlib.sha256(token.encode()).hexdigest()


def add_account(archive: Archive, name: str, *, role: str, kind: str = "user") -> Principal:
    """Create a user or service account.

    Parameters
    ----------
    archive : Archive
        The archive whose catalogue holds the accounts.
    name : str
        Unique account name.
    role : str
        ``admin``, ``clinician``, ``station`` or ``researcher``.
    kind : str
        ``user`` (a person) or ``service`` (a machine, e.g. a station).

    Returns
    -------
    Principal

    Raises
    ------
    InputError
        A name that breaks the rules of :mod:`rasterserver.identifiers`, an unknown role or
        kind.
    ConflictError
        The name, or one that differs only in case or look-alike characters, is taken.
    """
    name = check_name(name, "an account name")
    if role not in ROLES:
        raise InputError(f"role must be one of {', '.join(ROLES)}")
    if kind not in ACCOUNT_KINDS:
        raise InputError(f"kind must be one of {', '.join(ACCOUNT_KINDS)}")
    account = ApiAccount(name=name, role=role, kind=kind)
    try:
        with archive.session() as s:
            if other := stored_name(s, ApiAccount.name, name, exact=False):
                raise ConflictError(f"an account called {other!r} exists already")
            s.add(account)
    except SQLIntegrityError:
        raise ConflictError(f"an account called {name!r} exists already") from None
    return Principal(account.id, account.name, account.role, account.kind)


def accounts(archive: Archive, *, limit: int = 100, offset: int = 0,
             role: str | None = None) -> list[Principal]:
    """List accounts by name, optionally of one role."""
    query = select(ApiAccount).order_by(ApiAccount.name)
    if role is not None:
        query = query.where(ApiAccount.role == role)
    with archive.session() as s:
        rows = s.scalars(query.limit(limit).offset(offset))
        return [Principal(a.id, a.name, a.role, a.kind) for a in rows]


def create_token(archive: Archive, account: str, *, label: str = "") -> str:
    """Create a token for ``account`` and return it; it cannot be shown again.

    Raises
    ------
    NotFoundError
        Unknown account.
    """
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with archive.session() as s:
        named = stored_name(s, ApiAccount.name, account)
        row = None if named is None else s.scalar(select(ApiAccount)
                                                  .where(ApiAccount.name == named))
        if row is None:
            raise NotFoundError(f"unknown account {account!r}: add it with `rasterserver user add`")
        s.add(ApiToken(account_id=row.id, token_sha256=token_digest(token),
                       prefix=token[: len(TOKEN_PREFIX) + 6], label=label[:100]))
    return token


def tokens(archive: Archive, *, account: str | None = None) -> list[TokenInfo]:
    """List tokens (prefix, owner, state), oldest first."""
    query = select(ApiToken, ApiAccount).join(ApiAccount).order_by(ApiToken.id)
    with archive.session() as s:
        if account is not None:
            query = query.where(ApiAccount.name == stored_name(s, ApiAccount.name, account))
        return [
            TokenInfo(t.id, a.name, a.role, t.prefix, t.label, t.created_at, t.revoked_at)
            for t, a in s.execute(query)
        ]


def revoke_token(archive: Archive, token_id: int) -> None:
    """Revoke token ``token_id``; a revoked token is refused from the next request on."""
    with archive.session() as s:
        row = s.get(ApiToken, token_id)
        if row is None:
            raise NotFoundError(f"unknown token {token_id}")
        if row.revoked_at is None:
            row.revoked_at = dt.datetime.now(dt.UTC)


# Built once: every request runs it, and building the statement cost more than running it.
_OWNER = (
    select(ApiAccount.id, ApiAccount.name, ApiAccount.role, ApiAccount.kind)
    .join(ApiToken, ApiToken.account_id == ApiAccount.id)
    .where(ApiToken.token_sha256 == bindparam("digest"), ApiToken.revoked_at.is_(None))
)


def authenticate(archive: Archive, token: str,
                 cache: TokenCache | None = None) -> Principal | None:
    """Return the owner of a valid, unrevoked ``token``, or None.

    Parameters
    ----------
    archive : Archive
        The archive whose catalogue holds the tokens.
    token : str
        The bearer token as sent.
    cache : TokenCache, optional
        The server's cache (PostgreSQL only). Without one every call reads the database.
        Only found tokens are cached; the cache is emptied on every change to tokens or
        accounts, so a revoked token is refused as soon as the database's notification
        has arrived.
    """
    if not token.startswith(TOKEN_PREFIX) or len(token) > 200:
        return None
    digest = token_digest(token)
    generation = 0
    if cache is not None:
        principal = cache.get(digest)
        if principal is not None:
            return principal
        # before the read: a change announced while it runs makes its answer unusable
        generation = cache.generation
    with archive.reading() as conn:
        row = conn.execute(_OWNER, {"digest": digest}).first()
    if row is None:
        return None
    principal = Principal(*row)
    if cache is not None:
        cache.put(digest, principal, generation)
    return principal


def cached_owner(cache: TokenCache | None, token: str) -> Principal | None:
    """The owner of ``token`` if ``cache`` knows it (None: ask :func:`authenticate`)."""
    if cache is None or not token.startswith(TOKEN_PREFIX) or len(token) > 200:
        return None
    return cache.get(token_digest(token))


_bearer = HTTPBearer(auto_error=False, description="An API token from `rasterserver token create`.")


async def authorize(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
) -> Principal:
    """FastAPI dependency of every protected route: authenticate, then apply the role rule.

    The rule is looked up by the matched route's name in
    :data:`rasterserver.api.roles.RULES`, so it is written once, in that table.

    On PostgreSQL the token is mostly found in the services' token cache
    (:mod:`rasterserver.api.token_cache`), without a round trip; otherwise it is looked up
    through ``services.read``: on the event loop on SQLite (one indexed read of a small
    table, tens of microseconds, cheaper than a hand-over to a thread), in a thread on
    PostgreSQL.

    Raises
    ------
    HTTPException
        401 without a valid token, 403 when the role may not use the route.
    """
    from rasterserver.api.audit import note_of
    from rasterserver.api.roles import allowed

    note = note_of(request)
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(401, "a bearer token is required",
                            headers={"WWW-Authenticate": "Bearer"})
    services = request.app.state.services
    cache = getattr(services, "token_cache", None)
    principal = cached_owner(cache, credentials.credentials)
    if principal is None:
        principal = await services.read(authenticate, services.archive,
                                        credentials.credentials, cache)
    if principal is None:
        raise HTTPException(401, "invalid or revoked token",
                            headers={"WWW-Authenticate": "Bearer"})
    note.principal = principal
    route = request.scope.get("route")
    name = getattr(route, "name", "")
    if not allowed(name, principal.role):
        raise HTTPException(403, f"the {principal.role} role may not use this operation")
    return principal
