"""``rasterserver user``, ``token``, ``audit`` and ``keys``: accounts, API tokens, the audit
trail, the pseudonym key.

Every change of accounts or tokens made here is recorded in the audit trail (actor
``cli:<login>``), as the HTTP API's requests are.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.commands.common import open_catalog, parse_datetime
from rasterserver.errors import InputError
from rasterserver.identifiers import lookup_key
from rasterserver.times import TIME_RULE

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

users = typer.Typer(
    help="API accounts: people and service accounts (stations).", no_args_is_help=True
)
tokens = typer.Typer(
    help="API bearer tokens: shown once when created, stored as SHA-256.", no_args_is_help=True
)
audit = typer.Typer(help="The audit trail of the HTTP API.", no_args_is_help=True)
keys = typer.Typer(help="The researchers' pseudonym key (kept outside the catalogue).",
                   no_args_is_help=True)


def _auth() -> ModuleType:
    # imported by the commands that use it: the ORM and the account tables cost other
    # commands' start-up
    from rasterserver.services import auth

    return auth


@users.command("add")
def user_add(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Account name.", show_default=False)],
    role: Annotated[str, typer.Option(help="admin, clinician, station or researcher.")],
    service_account: Annotated[
        bool, typer.Option("--service-account", help="A machine (e.g. a station), not a person.")
    ] = False,
) -> None:
    """Create an API account."""
    with open_catalog(ctx) as catalog:
        p = _auth().add_account(
            catalog, name, role=role, kind="service" if service_account else "user"
        )
        _admin_event(catalog, "C", "user add", f"account {p.name} ({p.kind}, {p.role}) created")
    typer.echo(f"account {p.name} ({p.kind}, {p.role}) created")


def _admin_event(catalog: Catalog, action: str, what: str, detail: str) -> None:
    from rasterserver.services.audit import record_admin_action

    record_admin_action(catalog, action=action, what=what, detail=detail)


@users.command("list")
def user_list(ctx: typer.Context) -> None:
    """List API accounts (name, role, kind, and "disabled" for a disabled one)."""
    with open_catalog(ctx) as catalog:
        found = _auth().account_states(catalog)
    for a, disabled in found:
        state = "\tdisabled" if disabled else ""
        typer.echo(f"{a.name}\t{a.role}\t{a.kind}{state}")


def _set_disabled(ctx: typer.Context, name: str, disabled: bool) -> None:
    word = "disabled" if disabled else "enabled"
    with open_catalog(ctx) as catalog:
        changed = _auth().set_account_disabled(catalog, name, disabled)
        if changed:
            _admin_event(catalog, "U", f"user {word[:-1]}", f"account {name} {word}")
    typer.echo(f"account {name} {word}" if changed else f"account {name} was {word} already")


@users.command("disable")
def user_disable(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Account name.", show_default=False)],
) -> None:
    """Disable an account: every token of it is refused from the next request on, until
    `user enable`."""
    _set_disabled(ctx, name, True)


@users.command("enable")
def user_enable(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Account name.", show_default=False)],
) -> None:
    """Enable a disabled account again (its tokens that have not expired or been revoked
    work again)."""
    _set_disabled(ctx, name, False)


@tokens.command("create")
def token_create(
    ctx: typer.Context,
    account: Annotated[str, typer.Argument(help="Account name.", show_default=False)],
    label: Annotated[str, typer.Option(help="What the token is for.")] = "",
    service_account: Annotated[
        bool,
        typer.Option(
            "--service-account",
            help="Create the account as a service account first if it does not exist "
            "(needs --role).",
        ),
    ] = False,
    role: Annotated[str | None, typer.Option(help="Role of an account created here.")] = None,
    days: Annotated[
        int | None,
        typer.Option(help="Lifetime in days, 1 to 3650 (default: RASTERSERVER_TOKEN_DAYS, "
                     "else 90).", show_default=False),
    ] = None,
    expires_at: Annotated[
        str | None,
        typer.Option(help=f"Expiry instead of --days: {TIME_RULE}.", show_default=False),
    ] = None,
) -> None:
    """Create a token and print it ONCE: only its SHA-256 is kept. Every token expires."""
    until = parse_datetime(expires_at, "--expires-at")
    with open_catalog(ctx) as catalog:
        # the same account if the names differ only in case or look-alike characters
        if service_account and not any(
            lookup_key(p.name) == lookup_key(account)
            for p in _auth().accounts(catalog, limit=1_000_000)
        ):
            p = _auth().add_account(catalog, account, role=role or "station", kind="service")
            _admin_event(catalog, "C", "token create",
                         f"account {p.name} ({p.kind}, {p.role}) created")
        token = _auth().create_token(catalog, account, label=label, days=days,
                                     expires_at=until)
        info = _auth().tokens(catalog, account=account)[-1]
        _admin_event(catalog, "C", "token create",
                     f"token {info.id} ({info.prefix}...) for account {info.account}, "
                     f"expires {info.expires_at:%Y-%m-%d %H:%M} UTC")
    typer.echo(f"expires {info.expires_at:%Y-%m-%d %H:%M} UTC", err=True)
    typer.echo(token)


@tokens.command("list")
def token_list(
    ctx: typer.Context,
    account: Annotated[str | None, typer.Option(help="Only this account's tokens.")] = None,
) -> None:
    """List tokens: id, account, role, prefix, created, state (active, revoked, expired,
    account disabled), expires, label."""
    with open_catalog(ctx) as catalog:
        for t in _auth().tokens(catalog, account=account):
            state = t.state()
            if state == "revoked":
                state = f"revoked {t.revoked_at:%Y-%m-%d %H:%M}"
            expires = f"{t.expires_at:%Y-%m-%d %H:%M}" if t.expires_at else "never"
            typer.echo(
                f"{t.id}\t{t.account}\t{t.role}\t{t.prefix}...\t"
                f"{t.created_at:%Y-%m-%d %H:%M}\t{state}\texpires {expires}\t{t.label}"
            )


@tokens.command("revoke")
def token_revoke(
    ctx: typer.Context,
    token_id: Annotated[
        int, typer.Argument(help="Token id (see `token list`).", show_default=False)
    ],
) -> None:
    """Revoke a token; it is refused from the next request on."""
    with open_catalog(ctx) as catalog:
        owner = _auth().revoke_token(catalog, token_id)
        _admin_event(catalog, "U", "token revoke", f"token {token_id} of account {owner} revoked")
    typer.echo(f"token {token_id} revoked")


@audit.command("export")
def audit_export(
    ctx: typer.Context,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="File to write (default: stdout).")
    ] = None,
    patient: Annotated[str | None, typer.Option(help="Only this patient's events.")] = None,
    since: Annotated[str | None, typer.Option(help=f"From this time: {TIME_RULE}.")] = None,
    until: Annotated[str | None, typer.Option(help="Before this time (as --since).")] = None,
) -> None:
    """Export the audit trail as a FHIR R4 Bundle of AuditEvent resources (JSON)."""
    from rasterserver.output_files import check_output, output_file
    from rasterserver.services.audit_trail import audit_events, fhir_bundle

    if out is not None:
        check_output(out, what="--out")
    with open_catalog(ctx) as catalog:
        events = audit_events(
            catalog,
            patient=patient,
            since=parse_datetime(since, "--since"),
            until=parse_datetime(until, "--until"),
            limit=10**9,
        )
    text = json.dumps(fhir_bundle(events), indent=1)
    if out is None:
        typer.echo(text)
    else:
        with output_file(out, what="--out") as temp:
            temp.write_text(text + "\n", encoding="utf-8")
        typer.echo(f"{len(events)} audit event(s) written to {out}", err=True)


@keys.command("rotate-pseudonyms")
def keys_rotate_pseudonyms(
    ctx: typer.Context,
    keep_old: Annotated[
        Path | None,
        typer.Option("--keep-old", help="Keep the old key in this new file (mode 0600). "
                     "Without it the old key is destroyed.", show_default=False),
    ] = None,
    yes: Annotated[
        bool, typer.Option("--yes", help="Confirm: every pseudonym and date shift changes.")
    ] = False,
) -> None:
    """Replace the pseudonym key with a new random one.

    Every patient gets a new pseudonym and a new date shift: research data exported before
    cannot be linked to data exported after, and old pseudonyms are no longer accepted.
    Without --keep-old nobody can map earlier pseudonyms back any more. Restart the servers
    (they hold the key in memory).
    """
    from rasterserver.commands.common import settings
    from rasterserver.pseudonym_key import rotate_key

    if not yes:
        raise InputError("rotating the pseudonym key changes every pseudonym and date shift "
                         "for good; run again with --yes to do it")
    if keep_old is not None and keep_old.exists():
        raise InputError(f"--keep-old {keep_old} exists; name a new file")
    with open_catalog(ctx) as catalog:
        path = rotate_key(settings(ctx), keep_old=keep_old)
        _admin_event(catalog, "U", "keys rotate-pseudonyms",
                     "pseudonym key rotated" + (" (old key kept)" if keep_old else ""))
    typer.echo(f"new pseudonym key in {path}; restart the servers to use it")


def register(app: typer.Typer) -> None:
    """Add the ``user``, ``token``, ``audit`` and ``keys`` groups to ``app``."""
    app.add_typer(users, name="user")
    app.add_typer(tokens, name="token")
    app.add_typer(audit, name="audit")
    app.add_typer(keys, name="keys")
