"""Accounts and API tokens: creation (CLI), lookup (every request), revocation.

Used by the CLI's token commands and by the HTTP API (whose FastAPI dependency,
:func:`rasterserver.api.auth.authorize`, calls :func:`authenticate`); nothing here needs
FastAPI.

A token is 32 random bytes (``secrets.token_urlsafe``) shown once when created; the
catalogue keeps only its SHA-256. Tokens carry enough entropy that a plain hash cannot be
brute-forced, so no per-token salt or slow hash is needed, and a lookup is one indexed
query.

On SQLite every request runs that query. On PostgreSQL, where it is a network round trip,
the server keeps the owners of the tokens it has seen in a
:class:`~rasterserver.services.token_cache.TokenCache`, which the database empties through
LISTEN/NOTIFY whenever a token or account changes: a revoked token is refused as soon as
that notification arrives (milliseconds), and while the notifications cannot be received
the cache is not used.

Every token expires (``expires_at``): after ``RASTERSERVER_TOKEN_DAYS`` days (default 90)
unless created with another end. An account can be disabled: all its tokens are refused
until it is enabled again. Both are checked on every request, cached or not.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import os
import secrets
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy import bindparam, select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session

from rasterserver.catalog.auth_models import ACCOUNT_KINDS, ROLES, ApiAccount, ApiToken
from rasterserver.catalog.lookup import stored_name
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.identifiers import check_name

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog
    from rasterserver.services.token_cache import TokenCache

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
    expires_at : datetime or None
        When the token used for this request expires (None: never, or not known).
    """

    account_id: int
    name: str
    role: str
    kind: str
    # not part of who the caller is: two requests of one account compare equal
    expires_at: dt.datetime | None = field(default=None, compare=False)


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
    expires_at: dt.datetime | None = None
    disabled: bool = False

    def state(self, now: dt.datetime | None = None) -> str:
        """``active``, ``revoked``, ``expired`` or ``account disabled``."""
        now = now or dt.datetime.now(dt.UTC)
        if self.revoked_at is not None:
            return "revoked"
        if self.disabled:
            return "account disabled"
        if self.expires_at is not None and _aware(self.expires_at) <= now:
            return "expired"
        return "active"


#: Lifetime of a new token in days, unless it is given another.
TOKEN_DAYS_ENV = "RASTERSERVER_TOKEN_DAYS"
DEFAULT_TOKEN_DAYS = 90
#: The longest lifetime a token may be given (ten years): beyond it an expiry means little.
MAX_TOKEN_DAYS = 3650


def default_token_days() -> int:
    """Days a new token lives: ``RASTERSERVER_TOKEN_DAYS``, default 90.

    Raises
    ------
    InputError
        Not a whole number of days between 1 and 3650.
    """
    text = os.environ.get(TOKEN_DAYS_ENV, "").strip()
    if not text:
        return DEFAULT_TOKEN_DAYS
    try:
        days = int(text)
    except ValueError:
        raise InputError(f"{TOKEN_DAYS_ENV} must be a whole number of days") from None
    if not 1 <= days <= MAX_TOKEN_DAYS:
        raise InputError(f"{TOKEN_DAYS_ENV} must be between 1 and {MAX_TOKEN_DAYS} days")
    return days


def _aware(when: dt.datetime) -> dt.datetime:
    return when if when.tzinfo else when.replace(tzinfo=dt.UTC)


def token_digest(token: str) -> str:
    """Return the SHA-256 hex digest under which ``token`` is stored."""
    return hashlib.sha256(token.encode()).hexdigest()


def add_account(catalog: Catalog, name: str, *, role: str, kind: str = "user") -> Principal:
    """Create a user or service account.

    Parameters
    ----------
    catalog : Catalog
        The catalogue that holds the accounts.
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
        with catalog.session() as s:
            if other := stored_name(s, ApiAccount.name, name, exact=False):
                raise ConflictError(f"an account called {other!r} exists already")
            s.add(account)
    except SQLIntegrityError:
        raise ConflictError(f"an account called {name!r} exists already") from None
    return Principal(account.id, account.name, account.role, account.kind)


def accounts(catalog: Catalog, *, limit: int = 100, offset: int = 0,
             role: str | None = None) -> list[Principal]:
    """List accounts by name, optionally of one role."""
    query = select(ApiAccount).order_by(ApiAccount.name)
    if role is not None:
        query = query.where(ApiAccount.role == role)
    with catalog.session() as s:
        rows = s.scalars(query.limit(limit).offset(offset))
        return [Principal(a.id, a.name, a.role, a.kind) for a in rows]


def account_states(catalog: Catalog) -> list[tuple[Principal, bool]]:
    """Every account by name, each with whether it is disabled."""
    with catalog.session() as s:
        return [(Principal(a.id, a.name, a.role, a.kind), a.disabled_at is not None)
                for a in s.scalars(select(ApiAccount).order_by(ApiAccount.name))]


def _account_row(s: Session, account: str) -> ApiAccount:
    named = stored_name(s, ApiAccount.name, account)
    row = None if named is None else s.scalar(select(ApiAccount).where(ApiAccount.name == named))
    if row is None:
        raise NotFoundError(f"unknown account {account!r}: add it with `rasterserver user add`")
    return row


def set_account_disabled(catalog: Catalog, account: str, disabled: bool) -> bool:
    """Disable ``account`` (every token of it is refused from the next request on) or enable
    it again; return whether anything changed.

    Raises
    ------
    NotFoundError
        Unknown account.
    """
    with catalog.session() as s:
        row = _account_row(s, account)
        if (row.disabled_at is not None) == disabled:
            return False
        row.disabled_at = dt.datetime.now(dt.UTC) if disabled else None
    return True


def create_token(catalog: Catalog, account: str, *, label: str = "",
                 days: int | None = None, expires_at: dt.datetime | None = None) -> str:
    """Create a token for ``account`` and return it; it cannot be shown again.

    Parameters
    ----------
    catalog : Catalog
        The catalogue that holds the tokens.
    account : str
        The owner.
    label : str
        What the token is for.
    days : int, optional
        Lifetime in days (1 to 3650); by default :func:`default_token_days`.
    expires_at : datetime, optional
        Expiry as a time with zone, instead of ``days``; must be in the future and within
        3650 days.

    Raises
    ------
    NotFoundError
        Unknown account.
    InputError
        A lifetime out of range, both ``days`` and ``expires_at``, a time without zone.
    """
    now = dt.datetime.now(dt.UTC)
    if days is not None and expires_at is not None:
        raise InputError("give the token's lifetime in days or its expiry time, not both")
    if expires_at is None:
        days = default_token_days() if days is None else days
        if not 1 <= days <= MAX_TOKEN_DAYS:
            raise InputError(f"a token lives between 1 and {MAX_TOKEN_DAYS} days")
        expires_at = now + dt.timedelta(days=days)
    elif expires_at.tzinfo is None:
        raise InputError("the token's expiry must carry its time zone")
    elif not now < expires_at <= now + dt.timedelta(days=MAX_TOKEN_DAYS):
        raise InputError(f"the token's expiry must be in the future, within {MAX_TOKEN_DAYS} "
                         "days")
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with catalog.session() as s:
        row = _account_row(s, account)
        s.add(ApiToken(account_id=row.id, token_sha256=token_digest(token),
                       prefix=token[: len(TOKEN_PREFIX) + 6], label=label[:100],
                       expires_at=expires_at))
    return token


def tokens(catalog: Catalog, *, account: str | None = None) -> list[TokenInfo]:
    """List tokens (prefix, owner, state, expiry), oldest first."""
    query = select(ApiToken, ApiAccount).join(ApiAccount).order_by(ApiToken.id)
    with catalog.session() as s:
        if account is not None:
            query = query.where(ApiAccount.name == stored_name(s, ApiAccount.name, account))
        return [
            TokenInfo(t.id, a.name, a.role, t.prefix, t.label, t.created_at, t.revoked_at,
                      t.expires_at, a.disabled_at is not None)
            for t, a in s.execute(query)
        ]


def revoke_token(catalog: Catalog, token_id: int) -> str:
    """Revoke token ``token_id``; a revoked token is refused from the next request on.

    Returns the name of the token's account."""
    with catalog.session() as s:
        row = s.get(ApiToken, token_id)
        if row is None:
            raise NotFoundError(f"unknown token {token_id}")
        if row.revoked_at is None:
            row.revoked_at = dt.datetime.now(dt.UTC)
        return s.get_one(ApiAccount, row.account_id).name


# Built once: every request runs it, and building the statement cost more than running it.
# Expiry is compared in Python (see usable()), so that a cached owner expires as well.
_OWNER = (
    select(ApiAccount.id, ApiAccount.name, ApiAccount.role, ApiAccount.kind,
           ApiToken.expires_at)
    .join(ApiToken, ApiToken.account_id == ApiAccount.id)
    .where(ApiToken.token_sha256 == bindparam("digest"), ApiToken.revoked_at.is_(None),
           ApiAccount.disabled_at.is_(None))
)


def usable(principal: Principal | None) -> Principal | None:
    """``principal`` unless its token has expired."""
    if principal is None or principal.expires_at is None:
        return principal
    if _aware(principal.expires_at) <= dt.datetime.now(dt.UTC):
        return None
    return principal


def authenticate(catalog: Catalog, token: str,
                 cache: TokenCache | None = None) -> Principal | None:
    """Return the owner of a valid token (not revoked, not expired, of an enabled account),
    or None.

    Parameters
    ----------
    catalog : Catalog
        The catalogue that holds the tokens.
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
            return usable(principal)
        # before the read: a change announced while it runs makes its answer unusable
        generation = cache.generation
    with catalog.reading() as conn:
        row = conn.execute(_OWNER, {"digest": digest}).first()
    if row is None:
        return None
    principal = Principal(*row)
    if cache is not None:
        cache.put(digest, principal, generation)
    return usable(principal)


def cached_owner(cache: TokenCache | None, token: str) -> Principal | None:
    """The owner of ``token`` if ``cache`` knows it (None: ask :func:`authenticate`)."""
    if cache is None or not token.startswith(TOKEN_PREFIX) or len(token) > 200:
        return None
    principal = cache.get(token_digest(token))
    if principal is not None and usable(principal) is None:
        # expired: authenticate() says so (None) without a round trip either
        return None
    return principal


def has_role(catalog: Catalog, role: str) -> bool:
    """Whether any account has ``role`` (the server asks for researchers, whose requests
    use pseudonyms)."""
    with catalog.reading() as conn:
        return conn.execute(select(ApiAccount.id).where(ApiAccount.role == role)
                            .limit(1)).first() is not None
