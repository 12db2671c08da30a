"""``rasterserver user``, ``token`` and ``audit``: accounts, API tokens, the audit trail."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, parse_datetime
from rasterserver.identifiers import lookup_key
from rasterserver.output_files import check_output, output_file
from rasterserver.times import TIME_RULE

users = typer.Typer(
    help="API accounts: people and service accounts (stations).", no_args_is_help=True
)
tokens = typer.Typer(
    help="API bearer tokens: shown once when created, stored as SHA-256.", no_args_is_help=True
)
audit = typer.Typer(help="The audit trail of the HTTP API.", no_args_is_help=True)


def _auth() -> ModuleType:
    # imported by the commands that use it: the HTTP API (FastAPI) would cost every other
    # command a fifth of a second at start
    from rasterserver.api import auth

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
    with open_archive(ctx) as archive:
        p = _auth().add_account(
            archive, name, role=role, kind="service" if service_account else "user"
        )
    typer.echo(f"account {p.name} ({p.kind}, {p.role}) created")


@users.command("list")
def user_list(ctx: typer.Context) -> None:
    """List API accounts."""
    with open_archive(ctx) as archive:
        for p in _auth().accounts(archive, limit=1_000_000):
            typer.echo(f"{p.name}\t{p.role}\t{p.kind}")


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
) -> None:
    """Create a token and print it ONCE: only its SHA-256 is kept."""
    with open_archive(ctx) as archive:
        # the same account if the names differ only in case or look-alike characters
        if service_account and not any(
            lookup_key(p.name) == lookup_key(account)
            for p in _auth().accounts(archive, limit=1_000_000)
        ):
            _auth().add_account(archive, account, role=role or "station", kind="service")
        token = _auth().create_token(archive, account, label=label)
    typer.echo(token)


@tokens.command("list")
def token_list(
    ctx: typer.Context,
    account: Annotated[str | None, typer.Option(help="Only this account's tokens.")] = None,
) -> None:
    """List tokens: id, account, role, prefix, created, revoked."""
    with open_archive(ctx) as archive:
        for t in _auth().tokens(archive, account=account):
            state = f"revoked {t.revoked_at:%Y-%m-%d %H:%M}" if t.revoked_at else "active"
            typer.echo(
                f"{t.id}\t{t.account}\t{t.role}\t{t.prefix}...\t"
                f"{t.created_at:%Y-%m-%d %H:%M}\t{state}\t{t.label}"
            )


@tokens.command("revoke")
def token_revoke(
    ctx: typer.Context,
    token_id: Annotated[
        int, typer.Argument(help="Token id (see `token list`).", show_default=False)
    ],
) -> None:
    """Revoke a token; it is refused from the next request on."""
    with open_archive(ctx) as archive:
        _auth().revoke_token(archive, token_id)
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
    from rasterserver.api.audit import audit_events, fhir_bundle

    if out is not None:
        check_output(out, what="--out")
    with open_archive(ctx) as archive:
        events = audit_events(
            archive,
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


def register(app: typer.Typer) -> None:
    """Add the ``user``, ``token`` and ``audit`` groups to ``app``."""
    app.add_typer(users, name="user")
    app.add_typer(tokens, name="token")
    app.add_typer(audit, name="audit")
