"""``rasterserver analyse`` (frames, no archive) and ``rasterserver show`` (an archived
acquisition): the back-shape analysis's landmarks and parameters, as a table, JSON or a
one-page report."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from rasterserver.commands.common import open_archive

if TYPE_CHECKING:
    from rasterserver.analysis import Analysis

# The analysis (NumPy, SciPy, the plugins) is imported inside the commands that run it, so
# that every other command starts without it.

_JSON_HELP = (
    "Print one JSON object (rasterserver.back-shape/1): landmarks (VP, DL, DR, DM, SP as "
    "(x, y, z) mm in the calibration's world frame, named in 'frame'), parameters (name: "
    "value, unit, spread), reasons (what was not found, and why), frames."
)
_REPORT_HELP = "Also write the one-page report: PNG, or PDF if the name ends in .pdf."


def _cell(value: float | None, width: int) -> str:
    return f"{'-':>{width}}" if value is None else f"{round(value, 1) + 0.0:>{width}.1f}"


def format_analysis(document: dict[str, Any], *, heading: str) -> str:
    """The analysis ``document`` as text: heading, landmarks, parameters, what was not found.

    Parameters
    ----------
    document : dict
        :meth:`rasterserver.analysis.Analysis.document`.
    heading : str
        First line (what was analysed).

    Returns
    -------
    str
    """
    from rasterserver.analysis import WORLD_FRAME, ordered_parameters, parameter_label
    from rasterserver.records_analysis import LANDMARKS

    lines = [heading]
    lines.append(
        f"landmarks ({document['frame']['unit']}, {WORLD_FRAME['name']} frame: X to "
        "the patient's right, Y down, Z away from the camera)"
    )
    lines.append(f"  {'':4}{'X':>9}{'Y':>9}{'Z':>9}  confidence")
    reasons = {r["what"]: r["why"] for r in document["reasons"]}
    for name in LANDMARKS:
        point = document["landmarks"][name]
        if point is None:
            lines.append(
                f"  {name:4}{'-':>9}{'-':>9}{'-':>9}  not found: "
                f"{reasons.get(name, 'no reason given')}"
            )
        else:
            confidence = document["landmark_confidence"][name]
            lines.append(
                f"  {name:4}" + "".join(_cell(v, 9) for v in point) + f"  {confidence:.2f}"
            )
    parameters = document["parameters"]
    several = len(document["frames"]) > 1
    lines.append("parameters" + (" (mean and spread over the frames)" if several else ""))
    width = max([len(parameter_label(n)) for n in parameters] + [10])
    lines.append(f"  {'':{width}}{'value':>9}{'spread':>9}  unit")
    for name in ordered_parameters(parameters):
        entry = parameters[name]
        lines.append(
            f"  {parameter_label(name):{width}}{_cell(entry['value'], 9)}"
            f"{_cell(entry['spread'], 9)}  {entry['unit']}"
        )
    if not parameters:
        lines.append("  none")
    others = [r for r in document["reasons"] if r["what"] not in LANDMARKS]
    if others:
        lines.append("not computed")
        lines.extend(f"  {r['what']}: {r['why']}" for r in others)
    return "\n".join(lines)


def _emit(
    analysis: Analysis,
    document: dict[str, Any],
    *,
    as_json: bool,
    heading: str,
    report: Path | None,
    header: list[str],
) -> None:
    import json

    if report is not None:
        from rasterserver.analysis_report import write_report

        write_report(analysis, report, header=header)
    if as_json:
        typer.echo(json.dumps(document, indent=2))
    else:
        typer.echo(format_analysis(document, heading=heading))
    if report is not None:
        typer.echo(f"report written to {report}", err=True)
    for frame in analysis.frames:
        if not frame.analysed:
            typer.echo(f"note: {frame.name}: {frame.shape.reason}", err=True)


def _check_report(report: Path | None) -> None:
    """Refuse a report path that cannot be written, before the work starts."""
    if report is not None:
        from rasterserver.analysis_report import report_format
        from rasterserver.output_files import check_output

        report_format(report)
        check_output(report, what="--report")


def analyse(
    frames: Annotated[
        list[Path],
        typer.Argument(
            help="Camera frames of one patient session (PNG, TIFF 8/16 bit or NPY); with "
            "several, each parameter is reported as mean and spread over the frames.",
            show_default=False,
        ),
    ],
    calibration: Annotated[
        Path,
        typer.Option(
            help="Calibration JSON (rasterserver.calibration/1) of the station; it "
            "must give the direction of gravity."
        ),
    ],
    raster: Annotated[
        Path | None,
        typer.Option(help="Raster definition JSON; default: the one the calibration names."),
    ] = None,
    stage: Annotated[
        list[str] | None,
        typer.Option(
            help="KIND=PLUGIN: use another plugin for a stage (see `rasterserver "
            "plugins`); repeatable."
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help=_JSON_HELP)] = False,
    report: Annotated[Path | None, typer.Option(help=_REPORT_HELP, show_default=False)] = None,
) -> None:
    """Analyse the shape of a back in camera frames, without an archive.

    Each frame is reconstructed and analysed (curvature, landmarks VP, DL, DR, DM and SP,
    symmetry line, spinal midline, clinical parameters); the result is printed as a table, or
    as JSON with --json. Positions are millimetres in the calibration's world frame, the one
    the reconstructed points are in. Parameter definitions: docs/analysis.md.

    Exits 2 with the reason when a file is missing or unusable or nothing could be analysed
    (a calibration without gravity, no back in view, a frame that does not fit the
    calibration). A landmark or parameter that could not be found is listed with its reason,
    never guessed; a frame in which nothing was found is named on stderr and left out of the
    mean.
    """
    from rasterserver.analysis import analyse_frames
    from rasterserver.commands.reconstruct import load_raster, load_station
    from rasterserver.imageio import read_frame
    from rasterserver.pipeline import parse_stage_options

    chain = parse_stage_options(stage or [])
    _check_report(report)
    station = load_station(calibration)
    definition = load_raster(raster, station)
    images = [(path.name, read_frame(path)) for path in frames]
    analysis = analyse_frames(images, calibration=station, raster=definition, chain=chain).check()
    analysed = sum(f.analysed for f in analysis.frames)
    names = ", ".join(path.name for path in frames)
    heading = (
        f"back-shape analysis of {names}"
        if len(frames) == 1
        else f"back-shape analysis of {len(frames)} frames ({analysed} analysed): {names}"
    )
    _emit(
        analysis,
        analysis.document(),
        as_json=as_json,
        heading=heading,
        report=report,
        header=[] if len(frames) == 1 else [f"frames: {names}"],
    )


def show(
    ctx: typer.Context,
    uid: Annotated[
        str, typer.Argument(help="Acquisition uid (see `rasterserver list`).", show_default=False)
    ],
    process: Annotated[
        bool,
        typer.Option(
            "--process/--no-process",
            help="Process the acquisition first when it has no stored analysis "
            "(stored results of earlier stages are reused).",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help=_JSON_HELP)] = False,
    report: Annotated[Path | None, typer.Option(help=_REPORT_HELP, show_default=False)] = None,
) -> None:
    """Show the back-shape analysis of an archived acquisition: landmarks and parameters.

    Reads the stored analysis (`rasterserver process` computes it, with provenance); with
    several raster frames, their analyses are combined into mean and spread. Without a stored
    analysis it exits 3 and says so, unless --process is given, which computes and stores it
    first. With --json the document carries each frame's provenance (plugin, version,
    parameters, checksums).

    Exits 2 with the reason when the analysis found nothing (a calibration without gravity,
    no back in view).
    """
    from rasterserver.analysis import acquisition_analysis

    _check_report(report)
    with open_archive(ctx) as archive:
        from rasterserver.pipeline import Pipeline

        info = archive.info(uid)
        analysis = acquisition_analysis(
            Pipeline(archive), uid, process=process, surfaces=report is not None
        ).check()
    when = f"{info.acquired_at:%Y-%m-%d %H:%M} UTC"
    who = f"patient {info.patient}" if info.patient else "no patient"
    heading = f"acquisition {uid} ({who}, acquired {when}), calibration {analysis.calibration}"
    _emit(
        analysis,
        analysis.document(),
        as_json=as_json,
        heading=heading,
        report=report,
        header=[f"acquisition {uid}", who, f"acquired {when}"],
    )


def register(app: typer.Typer) -> None:
    """Add the ``analyse`` and ``show`` commands to ``app``."""
    app.command("analyse")(analyse)
    app.command("show")(show)
