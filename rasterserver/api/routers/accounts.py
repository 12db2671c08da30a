"""``/accounts``: users and service accounts (tokens are made with the CLI only)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Query

from rasterserver.api.deps import NoteDep, PageDep, ServicesDep, protected_router
from rasterserver.api.fields import Role
from rasterserver.api.schemas import AccountIn, AccountOut
from rasterserver.services import auth

router = protected_router("accounts")


@router.get("/accounts", name="list_accounts", response_model=list[AccountOut])
def list_accounts(
    svc: ServicesDep, page: PageDep,
    role: Annotated[Role | None, Query()] = None,
) -> list[AccountOut]:
    """Accounts by name, optionally of one role."""
    found = auth.accounts(svc.catalog, limit=page.limit, offset=page.offset, role=role)
    return [AccountOut(name=p.name, role=p.role, kind=p.kind) for p in found]


@router.post("/accounts", name="add_account", response_model=AccountOut, status_code=201)
def add_account(body: AccountIn, svc: ServicesDep, note: NoteDep) -> AccountOut:
    """Create a user or service account; give it a token with `rasterserver token create`."""
    p = auth.add_account(svc.catalog, body.name, role=body.role, kind=body.kind)
    # the audit event says which account was made, with which role
    note.detail = f"account {p.name} ({p.kind}, {p.role}) created"
    return AccountOut(name=p.name, role=p.role, kind=p.kind)
