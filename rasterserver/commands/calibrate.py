"""``rasterserver calibrate``: calibrate a station from its six control-point frames.

``rasterserver export-calibration STATION[:VERSION]`` writes a stored calibration back out as
the calibration JSON (``rasterserver station add-calibration`` imports one).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.commands.common import open_archive, parse_datetime
from rasterserver.errors import InputError, NotFoundError, RasterServerError
from rasterserver.times import TIME_RULE

if TYPE_CHECKING:
    from rasterserver.optics import Station

# OpenCV, NumPy and the calibration are imported when a command runs, not at start.

__all__ = ["CalibrationRejectedError", "register"]


class CalibrationRejectedError(RasterServerError):
    """The calibration was computed but is worse than the bounds; nothing was stored.

    Exit 7, a code of its own: 6 means the catalogue's schema is not current, which a script
    running ``calibrate`` must be able to tell apart from a rejected calibration.
    """

    exit_code = 7


_HELP = (
    "Calibrate camera and projector from the control-point frames and store the result as "
    "the station's next calibration version.\n\n"
    "FRAMES_DIR holds config<k>-projector-off and config<k>-projector-on frames (PNG, TIFF or "
    "NPY), as `rasterserver simulate calibration-body` writes them. Prints the residuals and a "
    "verdict; exits 7 without storing anything when the residuals exceed the bounds. On "
    "success the six frames are ingested as a calibration acquisition and the calibration is "
    "stored (unless --dry-run); its version is printed."
)


def calibrate(
    ctx: typer.Context,
    frames_dir: Annotated[Path, typer.Argument(help="Folder with the six frames.")],
    control_points: Annotated[
        Path | None,
        typer.Option(
            "--control-points",
            help="Control-point coordinates (JSON or CSV); default FRAMES_DIR/control_points.json.",
            show_default=False,
        ),
    ] = None,
    station: Annotated[
        str | None,
        typer.Option(
            help="Station to store the calibration for (registered if new); "
            "needed unless --dry-run.",
            show_default=False,
        ),
    ] = None,
    raster: Annotated[
        Path | None,
        typer.Option(
            help="Raster definition JSON; default FRAMES_DIR/raster.json, else the built-in.",
            show_default=False,
        ),
    ] = None,
    reference: Annotated[
        Path | None,
        typer.Option(
            help="Calibration JSON supplying what lines cannot determine (the projector's "
            "centre along the lines, its u principal point); default the station's newest "
            "calibration, else the nominal design.",
            show_default=False,
        ),
    ] = None,
    report: Annotated[
        Path | None,
        typer.Option(
            help="Write the residual plot here (PNG) and the text report beside it (.txt).",
            show_default=False,
        ),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option(
            "--output", "-o", help="Also write the calibration JSON here.", show_default=False
        ),
    ] = None,
    max_rms_px: Annotated[
        float, typer.Option(help="Bound on the control points' rms reprojection error (px).")
    ] = 0.1,
    max_point_px: Annotated[
        float, typer.Option(help="Bound on any single control point's residual (px).")
    ] = 0.3,
    max_line_mm: Annotated[
        float, typer.Option(help="Bound on the raster peaks' rms residual across lines (mm).")
    ] = 0.1,
    camera_distortion: Annotated[
        str,
        typer.Option(
            help="Camera distortion terms to estimate, comma-separated "
            "(of k1,k2,p1,p2,k3; 'none' for a distortion-free model)."
        ),
    ] = "k1",
    projector_distortion: Annotated[
        str, typer.Option(help="Projector distortion terms to estimate, as above.")
    ] = "k1",
    valid_from: Annotated[
        str | None,
        typer.Option(
            help=f"From when the calibration applies: {TIME_RULE}. Default: now.",
            show_default=False,
        ),
    ] = None,
    notes: Annotated[str, typer.Option(help="Free text stored with the calibration.")] = "",
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Compute and report, store nothing.")
    ] = False,
) -> None:
    """Calibrate camera and projector from the six control-point frames."""
    import cv2

    from rasterserver.calibration import calibrate_station, load_control_points, load_frames
    from rasterserver.calibration.report import Bounds, judge, plot_residuals, text_report
    from rasterserver.documents import load_raster_document
    from rasterserver.optics import default_station
    from rasterserver.output_files import check_output, output_file
    from rasterserver.raster import default_raster

    if station is None and not dry_run:
        raise InputError("--station is needed to store the calibration (or use --dry-run)")
    name = station or "calibrated"
    when = parse_datetime(valid_from, "--valid-from")
    for option, value in (
        ("--max-rms-px", max_rms_px),
        ("--max-point-px", max_point_px),
        ("--max-line-mm", max_line_mm),
    ):
        if not value > 0:
            raise InputError(f"{option} must be positive, got {value}")
    # outputs that cannot be written are refused before the minutes of work, not after
    if output is not None:
        check_output(output, what="--output")
    if report is not None:
        check_output(report, what="--report")
        if not cv2.haveImageWriter(str(report)) or report.suffix.lower() == ".txt":
            raise InputError(
                f"--report {report.name}: name an image (.png); the text goes beside it (.txt)"
            )
        check_output(report.with_suffix(".txt"), what="--report text")
    frames = load_frames(frames_dir)
    control = load_control_points(control_points or frames_dir / "control_points.json")
    raster_path = raster or frames_dir / "raster.json"
    if raster is not None or raster_path.exists():
        raster_def = load_raster_document(raster_path)
    else:
        raster_def = default_raster()
    height, width = next(iter(frames.off.values() or frames.on.values())).shape
    ref = _reference(ctx, reference, name, dry_run=dry_run)
    if ref is None:
        ref = default_station(width, height)
        typer.echo("reference: the nominal design (no earlier calibration)", err=True)
    result = calibrate_station(
        frames,
        control,
        raster=raster_def,
        reference=ref,
        name=name,
        camera_distortion=_terms(camera_distortion),
        projector_distortion=_terms(projector_distortion),
    )
    bounds = Bounds(max_rms_px=max_rms_px, max_point_px=max_point_px, max_line_rms_mm=max_line_mm)
    verdict = judge(result, bounds)
    text = text_report(result, verdict)
    typer.echo(text, nl=False)
    if report is not None:
        with output_file(report, what="--report") as temp:
            plot_residuals(result, frames, temp, bounds=bounds)
        with output_file(report.with_suffix(".txt"), what="--report text") as temp:
            temp.write_text(text, encoding="utf-8")
        typer.echo(f"report: {report} and {report.with_suffix('.txt')}")
    if output is not None:
        with output_file(output, what="--output") as temp:
            temp.write_text(json.dumps(result.station.to_dict(), indent=2) + "\n", encoding="utf-8")
        typer.echo(f"calibration JSON: {output}")
    if not verdict.ok:
        reasons = "; ".join(verdict.reasons)
        raise CalibrationRejectedError(f"calibration rejected, nothing stored: {reasons}")
    if dry_run:
        typer.echo("dry run: nothing stored")
        return
    from rasterserver.calibration.store import store_calibration

    with open_archive(ctx) as archive:
        stored = store_calibration(
            archive, result, frames, station=name, valid_from=when, notes=notes
        )
    typer.echo(
        f"station {stored.station}: calibration version {stored.version} stored "
        f"(frames in acquisition {stored.acquisition}, raster {stored.raster})"
    )


def _terms(text: str) -> tuple[str, ...]:
    """Parse a comma-separated list of distortion terms ('none' or empty: no term)."""
    terms = tuple(t.strip().lower() for t in text.split(",") if t.strip())
    return () if terms in ((), ("none",)) else terms


def _reference(
    ctx: typer.Context, path: Path | None, station: str, *, dry_run: bool
) -> Station | None:
    """The reference station: a file, else the station's newest calibration (not in a dry
    run, which touches no archive), else None for the nominal design."""
    from rasterserver.documents import load_calibration_document, stored_calibration

    if path is not None:
        return load_calibration_document(path)
    if dry_run:
        return None
    with open_archive(ctx) as archive:
        try:
            row = archive.calibration(station)
        except NotFoundError:
            return None
        return stored_calibration(row.parameters, label=f"{station}:{row.version}")


def export_calibration(
    ctx: typer.Context,
    which: Annotated[
        str, typer.Argument(help="STATION:VERSION, or STATION for its newest calibration.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="JSON file to write.")],
    residuals: Annotated[
        bool, typer.Option("--residuals", help="Write the stored residuals instead.")
    ] = False,
) -> None:
    """Write a stored calibration as its calibration JSON (rasterserver.calibration/1)."""
    from rasterserver.commands.process import parse_calibration
    from rasterserver.output_files import check_output, output_file

    parsed = parse_calibration(which)
    assert parsed is not None
    check_output(out, what="--out")
    with open_archive(ctx) as archive:
        row = archive.calibration(parsed[0], parsed[1])
        document = row.residuals if residuals else row.parameters
        version = row.version
    with output_file(out, what="--out") as temp:
        temp.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    typer.echo(f"station {parsed[0]}: calibration version {version} written to {out}")


def register(app: typer.Typer) -> None:
    """Add the ``calibrate`` and ``export-calibration`` commands to ``app``."""
    app.command("calibrate", help=_HELP)(calibrate)
    app.command("export-calibration")(export_calibration)
