"""``rasterserver compare``: two acquisitions, or all visits of a patient, compared."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rasterserver.commands.common import open_archive


def compare(
    ctx: typer.Context,
    uids: Annotated[
        list[str] | None,
        typer.Argument(
            help="Two (or more) acquisition uids of one patient (see `rasterserver list`).",
            show_default=False,
        ),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(
            "-o",
            "--out",
            help="Folder to create for the files (must not exist or be empty).",
            show_default=False,
        ),
    ] = Path("comparison"),
    patient: Annotated[
        str | None,
        typer.Option(help="Compare every acquisition of this patient instead.", show_default=False),
    ] = None,
    process: Annotated[
        bool,
        typer.Option(
            "--process/--no-process",
            help="Process acquisitions that have no stored analysis first.",
        ),
    ] = False,
    stage: Annotated[
        list[str] | None,
        typer.Option(
            help="KIND=PLUGIN: another plugin for the comparison or asymmetry stage "
            "(see `rasterserver plugins --graph`); repeatable.",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Compare visits of one patient: registration, distance maps, trends, a report.

    Visit B is registered onto visit A (body-fixed landmark frames, then point-to-plane ICP on
    the trunk); the signed distance along A's normals (positive: B posterior of A) is written
    as a PLY mesh with a per-vertex scalar (MeshLab's quality, CloudCompare's scalar field) and
    a PNG; each visit's asymmetry map, the statistics (comparison.json), every parameter's
    trend (trends.csv, trends.json, trends.png; a change is flagged only beyond the smallest
    detectable change) and report.html go into the same folder, which is written whole or not
    at all. With --patient, consecutive visits and the first with the last are compared.
    Each comparison is stored in the archive (a result of the comparison stage, plugin
    comparison.landmark-icp, keyed by the analyses and meshes compared) and reused when asked
    again. Where a visit's analysis did not find VP (hair or a shadow over the nape), the VP
    of the nearest compared visit that found it is carried across, and the parameters
    measured along the symmetry line (lateral deviation, surface rotation, scoliosis angle)
    are given for it, marked with the visit the VP came from (trends.csv's vp_carried_from);
    the stored analysis is not changed. Details: docs/comparison.md.

    Exits 2 when the visits cannot be compared (a landmark frame missing, no overlap, ICP not
    converging: the reason is given) or the folder cannot be written, 3 for an unknown or
    unprocessed acquisition or patient.
    """
    from rasterserver.errors import InputError
    from rasterserver.pipeline import Pipeline, parse_stage_options
    from rasterserver.visit_comparison import compare_visits, patient_visits

    if (patient is None) == (not uids):
        raise InputError("give two acquisition uids or --patient ID (not both)")
    with open_archive(ctx) as archive:
        pipeline = Pipeline(archive)
        chosen = patient_visits(pipeline, patient) if patient is not None else list(uids or [])
        if len(chosen) < 2:
            raise InputError("a comparison needs two acquisitions")
        document = compare_visits(
            pipeline,
            chosen,
            out,
            process=process,
            plugins=parse_stage_options(stage or []),
            log=lambda line: typer.echo(line, err=True),
        )
    for pair in document["pairs"]:
        if "refused" in pair:
            typer.echo(f"{pair['a']} -> {pair['b']}: not compared: {pair['refused']}")
            continue
        s, r = pair["distance"], pair["registration"]
        typer.echo(
            f"{pair['a']} -> {pair['b']}: registered (fitness {r['fitness']:.2f}, residual "
            f"{r['rmse_mm']:.2f} mm); distance rms {s['rms_mm']:.2f} mm, largest "
            f"{s['max_abs_mm']:+.1f} mm; {_stored(pair.get('provenance'))}"
        )
    for uid, carried in document.get("carried_vp", {}).items():
        if "from" in carried:
            typer.echo(
                f"{uid}: VP not found; the midline's parameters measured with VP carried from "
                f"{carried['from']}"
            )
        else:
            typer.echo(f"{uid}: VP not found, none carried: {carried['refused']}")
    typer.echo(f"written to {out} (report.html)")


def _stored(provenance: dict | None) -> str:
    if not provenance:
        return "not stored"
    how = "reused" if provenance["reused"] else "computed and stored as"
    return f"{how} result {provenance['result_id']}"


def register(app: typer.Typer) -> None:
    """Add the ``compare`` command to ``app``."""
    app.command("compare")(compare)
