"""``rasterserver patient``: register and list patients."""

from __future__ import annotations

from typing import Annotated

import typer

from rasterserver.commands.common import open_archive, parse_date

patient_app = typer.Typer(help="Register and list patients.", no_args_is_help=True)


@patient_app.command("add")
def add(
    ctx: typer.Context,
    identifier: Annotated[str, typer.Argument(
        help="The site's unique patient identifier: printable, no '/', at most 64 characters; "
             "case is kept, but one differing only in case or look-alike characters from a "
             "registered one is refused (README, 'Names and identifiers').")],
    name: Annotated[str, typer.Option(help="Full name.")] = "",
    birth_date: Annotated[
        str | None, typer.Option(help="Birth date, YYYY-MM-DD.", show_default=False)
    ] = None,
    sex: Annotated[str, typer.Option(help="female, male, other or unknown.")] = "unknown",
) -> None:
    """Register a patient so that acquisitions can be ingested for it."""
    with open_archive(ctx) as archive:
        patient = archive.add_patient(
            identifier, name=name, birth_date=parse_date(birth_date, "--birth-date"), sex=sex
        )
    typer.echo(f"patient {patient.identifier} registered")


@patient_app.command("list")
def list_patients(
    ctx: typer.Context,
    limit: Annotated[int, typer.Option(min=1, help="Rows per page.")] = 100,
    offset: Annotated[int, typer.Option(min=0, help="Rows to skip.")] = 0,
) -> None:
    """List registered patients by identifier."""
    with open_archive(ctx) as archive:
        for p in archive.patients(limit=limit, offset=offset):
            born = p.birth_date.isoformat() if p.birth_date else "-"
            typer.echo(f"{p.identifier}\t{p.name or '-'}\t{born}\t{p.sex}")


def register(app: typer.Typer) -> None:
    """Add the ``patient`` command group to ``app``."""
    app.add_typer(patient_app, name="patient")
