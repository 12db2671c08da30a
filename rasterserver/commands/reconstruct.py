"""``rasterserver reconstruct``: one image to a 3-D point cloud, without an archive."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from rasterserver.errors import InputError

if TYPE_CHECKING:
    from rasterserver.optics import Station
    from rasterserver.raster import Raster

# OpenCV, NumPy, pydantic and the stage chain are imported by the functions that use them, so
# that every other command starts without them.


def load_station(path: Path) -> Station:
    """Read and check a calibration JSON file (:mod:`rasterserver.documents`)."""
    from rasterserver.documents import load_calibration_document

    return load_calibration_document(path)


def load_raster(path: Path | None, station: Station) -> Raster:
    """The raster named by ``--raster``, else the one the calibration names or holds."""
    from rasterserver.documents import calibration_raster

    return calibration_raster(
        station, path, source="the calibration", hint="; give its definition with --raster"
    )


def reconstruct(
    image: Annotated[
        Path,
        typer.Argument(help="The camera frame: PNG, TIFF (8/16 bit) or NPY.", show_default=False),
    ],
    calibration: Annotated[
        Path,
        typer.Option(help="Calibration JSON (rasterserver.calibration/1) of the station."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Point cloud to write (.ply).")],
    raster: Annotated[
        Path | None,
        typer.Option(help="Raster definition JSON; default: the one the calibration names."),
    ] = None,
    stage: Annotated[
        list[str] | None,
        typer.Option(
            help="KIND=PLUGIN: use another plugin for a stage (see `rasterserver plugins`); "
            "repeatable.",
        ),
    ] = None,
    overlay: Annotated[
        Path | None,
        typer.Option(
            help="Also write the frame with the lines coloured and numbered (PNG), and under "
            "it why the grey ones were left unnumbered."
        ),
    ] = None,
    smoothed: Annotated[
        bool,
        typer.Option(
            "--smoothed",
            help="Write the smoothed points (one per three peaks along each line) instead of "
            "one point per peak.",
        ),
    ] = False,
) -> None:
    """Reconstruct the 3-D surface points of one frame and write them as a PLY point cloud.

    Works without an archive. Every point has x, y, z (mm, in the calibration's world frame),
    its raster line number, image column and peak area (and row). Exits with code 2 and the
    reason when nothing could be reconstructed (no raster lines, a frame that does not fit the
    calibration).
    """
    import cv2

    from rasterserver.export import overlay_image, write_points
    from rasterserver.imageio import read_frame
    from rasterserver.output_files import check_output, output_file
    from rasterserver.pipeline import parse_stage_options, run_chain
    from rasterserver.records_surface import Points, Surface
    from rasterserver.stage import StageContext

    if out.suffix.lower() != ".ply":
        raise InputError(f"--out {out.name}: the point cloud is written as PLY (.ply)")
    # refuse outputs that cannot be written before the work, not after it
    check_output(out, what="--out")
    if overlay is not None:
        check_output(overlay, what="--overlay")
        if not cv2.haveImageWriter(str(overlay)):
            raise InputError(f"--overlay {overlay.name}: not an image name OpenCV can write (.png)")
    frame = read_frame(image)
    station = load_station(calibration)
    context = StageContext(calibration=station, raster=load_raster(raster, station))
    results = run_chain(
        frame,
        chain=parse_stage_options(stage or []),
        context=context,
        until="surface" if smoothed else "points",
    )
    # the overlay first: when nothing is reconstructed it is what shows why
    numbers = results.get("numbers")
    if overlay is not None and numbers is not None:
        with output_file(overlay, what="--overlay") as temp:
            # OpenCV picks the image format from the suffix, which the temporary name keeps
            if not cv2.imwrite(str(temp), overlay_image(frame, numbers)):
                raise InputError(f"could not write the overlay {overlay} (a .png path?)")
    points = results["points"]
    assert isinstance(points, Points)
    if smoothed:
        surface = results["surface"]
        assert isinstance(surface, Surface)
        samples = surface.sample_points()
        if samples is None:
            raise InputError("the surface plugin keeps no smoothed points")
        written = samples
    else:
        written = points
    write_points(written, out)
    what = "smoothed points" if smoothed else "points"
    peaks = int(getattr(numbers, "col", points.col).size)
    typer.echo(
        f"{len(written)} {what} written to {out} ({len(points)} of {peaks} peaks reconstructed)"
    )
    if written.reason:
        typer.echo(f"note: {written.reason}", err=True)


def register(app: typer.Typer) -> None:
    """Add the ``reconstruct`` command to ``app``."""
    app.command("reconstruct")(reconstruct)
