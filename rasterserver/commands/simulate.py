"""``rasterserver simulate``: physically based rasterstereographs with exact ground truth.

``simulate back`` renders a parametric human back (a preset, a random back, or either with
its scoliosis and posture overridden); ``simulate calibration-body`` renders the seed's six
control-point frames. Every output folder holds what is needed to process the frames and to
check the result: the images, the ground truth, the station's calibration and the raster.
"""

from __future__ import annotations

import dataclasses
import json
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from rasterserver.errors import InputError
from rasterserver.interrupts import raise_if_interrupted

# NumPy, the simulator and the output files (through the store package: HDF5) are imported by
# the commands that use them, so that every other command starts without them.

sim_app = typer.Typer(
    help=(
        "Simulate rasterstereographs: render a human back or the control-point calibration "
        "body as the station's camera sees it under the projector's line raster, with exact "
        "ground truth (surface points, line numbers, line rows per column, landmarks)."
    ),
    no_args_is_help=True,
)


class ImageFormat(StrEnum):
    """How the frame is written."""

    png = "png"
    npy = "npy"


class TruthFormat(StrEnum):
    """How the ground truth is written."""

    npz = "npz"
    h5 = "h5"


_Out = Annotated[
    Path,
    typer.Option(
        "--out", "-o", help="Output folder (created if needed; existing files are overwritten)."
    ),
]
_Seed = Annotated[int, typer.Option(help="Seed of the sensor noise (>= 0): same seed, same image.")]
_Supersample = Annotated[
    int,
    typer.Option(
        "--supersample",
        help="Sub-samples per pixel along each axis (1-8); 3 resolves the raster lines well.",
    ),
]
_Noise = Annotated[
    bool,
    typer.Option(
        "--noise/--no-noise", help="Shot and read noise; --no-noise gives the expected image."
    ),
]
_BitDepth = Annotated[
    int, typer.Option(help="Digitiser bit depth: 8 (uint8, as in the seed) or 16 (uint16).")
]
_Width = Annotated[
    int, typer.Option(help="Image columns; the field of view stays ~576 mm wide at Z = 0.")
]
_Height = Annotated[int, typer.Option(help="Image rows (the seed's portrait camera: 604).")]
_Format = Annotated[
    ImageFormat, typer.Option("--format", help="Frame file: png (8/16-bit) or npy.")
]
_Truth = Annotated[
    TruthFormat, typer.Option("--ground-truth", help="Ground-truth file: npz or h5 (HDF5).")
]


def _echo_progress(text: str) -> None:
    raise_if_interrupted()  # a Ctrl-C swallowed in a finaliser stops the work here
    typer.echo(text, err=True)


def _check_seed(option: str, value: int | None) -> None:
    # numpy draws from non-negative seeds only; a negative one is a bad option, not a crash
    if value is not None and value < 0:
        raise InputError(f"{option} must be a whole number >= 0, got {value}")


def _station(width: int, height: int) -> Any:
    from rasterserver.optics import default_station

    for name, value in (("--width", width), ("--height", height)):
        if not 64 <= value <= 8192:
            raise InputError(f"{name} must lie in [64, 8192] pixels, got {value}")
    return default_station(width, height)


def _render_settings(
    *, supersample: int, noise: bool, bit_depth: int, projector: bool = True
) -> Any:
    from rasterserver.simulator.render import RenderSettings

    if not 1 <= supersample <= 8:
        raise InputError(f"--supersample must lie in [1, 8], got {supersample}")
    if bit_depth not in (8, 16):
        raise InputError(f"--bit-depth must be 8 or 16, got {bit_depth}")
    base = RenderSettings()
    # Keep the same exposure in electrons; a deeper digitiser spreads it over more levels.
    scale = float(2 ** (bit_depth - 8))
    settings = base.replace(
        supersampling=supersample,
        noise=noise,
        bit_depth=bit_depth,
        gain=base.gain * scale,
        offset=base.offset * scale,
    )
    if not projector:
        # Projector off: the room light alone shows the plates and their dark holes.
        settings = settings.replace(
            projector_electrons=0.0, ambient_electrons=15000.0, line_rows=False
        )
    return settings


def _write(
    out: Path,
    rendering: Any,
    scene: Any,
    station: Any,
    *,
    stem: str,
    image_format: ImageFormat,
    truth_format: TruthFormat,
) -> dict[str, Path]:
    from rasterserver.simulator.io import write_simulation

    paths = write_simulation(
        out, rendering, scene, station, stem=stem, ground_truth_format=truth_format.value
    )
    # write_simulation writes both image files; keep the one asked for.
    drop = "image_npy" if image_format is ImageFormat.png else "image_png"
    paths.pop(drop).unlink(missing_ok=True)
    return paths


_BACK_HELP = (
    "Render a simulated back and write frame, ground truth, calibration and raster.\n\n"
    "Files in --out (in --out/visit-NN with several visits): frame.png or frame.npy (the "
    "camera frame); frame_truth.npz or .h5 (exact surface points, normals, object labels, "
    "line numbers, line rows per column, landmarks C7 / dimples / spinal midline, and the "
    "applied lateral deviation and rotation per height); back.json (the parameters); "
    "calibration.json (the station) and raster.json (the diapositive).\n\n"
    "With --ingest, every visit is also stored in the archive for --patient, six months "
    "apart, with the simulated station's calibration."
)


@sim_app.command("back", help=_BACK_HELP)
def back(
    ctx: typer.Context,
    preset: Annotated[
        str,
        typer.Option(
            help="Named back: normal (straight spine), moderate (right thoracic curve 15 mm, "
            "8° rotation, small lumbar counter-curve) or severe (double curve 35/-20 mm, "
            "16°/-9° rotation, flat thoracic spine).",
        ),
    ] = "moderate",
    random_back: Annotated[
        int | None,
        typer.Option(
            "--random-back",
            help="Draw a varied back (size, posture, scoliosis, skin) from this seed (>= 0) "
            "instead of using a preset.",
            show_default=False,
        ),
    ] = None,
    lateral_deviation: Annotated[
        float | None,
        typer.Option(
            help="Lateral deviation (mm) of the main curve's apex; + towards the patient's "
            "right (+X). A straight back gains a thoracic curve.",
            show_default=False,
        ),
    ] = None,
    rotation: Annotated[
        float | None,
        typer.Option(
            help="Axial trunk rotation (degrees, |r| <= 60) at the main curve's apex; + lifts "
            "the right side (rib hump on the right).",
            show_default=False,
        ),
    ] = None,
    trunk_length: Annotated[
        float | None,
        typer.Option(help="C7 to sacrum (DM) length, mm (300-650).", show_default=False),
    ] = None,
    inclination: Annotated[
        float | None,
        typer.Option(
            help="Sagittal trunk inclination, degrees (+ leans forwards).", show_default=False
        ),
    ] = None,
    kyphosis: Annotated[
        float | None, typer.Option(help="Thoracic kyphosis depth, mm.", show_default=False)
    ] = None,
    lordosis: Annotated[
        float | None, typer.Option(help="Lumbar lordosis depth, mm.", show_default=False)
    ] = None,
    arm_gap: Annotated[
        float | None,
        typer.Option(help="Smallest gap between arms and waist, mm.", show_default=False),
    ] = None,
    visits: Annotated[
        int,
        typer.Option(
            help="Simulate this many visits of a progressing scoliosis (the curves grow by "
            "--progression per visit), one sub-folder visit-NN each.",
        ),
    ] = 1,
    progression: Annotated[
        float,
        typer.Option(help="Relative growth of deviation and rotation per visit (0.15 = 15 %)."),
    ] = 0.15,
    ingest: Annotated[
        bool,
        typer.Option(
            "--ingest/--no-ingest",
            help="Also store every visit in the archive (global --archive / "
            "RASTERSERVER_ARCHIVE) for --patient, with the simulated station's calibration.",
        ),
    ] = False,
    patient: Annotated[
        str | None,
        typer.Option(help="Patient identifier for --ingest (created if new).", show_default=False),
    ] = None,
    station_name: Annotated[
        str, typer.Option("--station", help="Station name for --ingest (created if new).")
    ] = "simulator",
    seed: _Seed = 0,
    supersample: _Supersample = 3,
    noise: _Noise = True,
    bit_depth: _BitDepth = 8,
    width: _Width = 576,
    height: _Height = 604,
    out: _Out = Path("simulated-back"),
    image_format: _Format = ImageFormat.png,
    truth_format: _Truth = TruthFormat.npz,
) -> None:
    """Render a simulated back and write frame, ground truth, calibration and raster.

    Files in --out (or in --out/visit-NN with several visits): frame.png or frame.npy (the
    camera frame), frame_truth.npz or .h5 (exact surface points, normals, object labels, line
    numbers, line rows per column, landmarks C7 / dimples / spinal midline, and the back's
    parameters with the applied lateral deviation and rotation per height), back.json (the
    parameters, reusable), calibration.json (the station) and raster.json (the diapositive).
    """
    from rasterserver.output_files import check_output_folder
    from rasterserver.simulated_visits import progressed
    from rasterserver.simulator.back import BackParameters
    from rasterserver.simulator.back import preset as get_preset
    from rasterserver.simulator.back import random_back as rb
    from rasterserver.simulator.render import render

    _check_seed("--seed", seed)
    _check_seed("--random-back", random_back)
    if visits < 1 or visits > 50:
        raise InputError(f"--visits must lie in [1, 50], got {visits}")
    if not 0.0 <= progression <= 2.0:
        raise InputError(f"--progression must lie in [0, 2], got {progression}")
    if ingest and not patient:
        raise InputError("--ingest needs --patient")
    params: BackParameters = rb(random_back) if random_back is not None else get_preset(preset)
    # float fields of BackParameters; replace() rejects an unknown name at run time
    changes: dict[str, Any] = {
        name: value
        for name, value in (
            ("trunk_length", trunk_length),
            ("inclination", inclination),
            ("kyphosis", kyphosis),
            ("lordosis", lordosis),
            ("arm_gap", arm_gap),
        )
        if value is not None
    }
    params = dataclasses.replace(params, **changes)
    if lateral_deviation is not None or rotation is not None:
        params = params.with_primary_curve(lateral_deviation=lateral_deviation, rotation=rotation)
    station = _station(width, height)
    settings = _render_settings(supersample=supersample, noise=noise, bit_depth=bit_depth)
    folders = [out] if visits == 1 else [out / f"visit-{v + 1:02d}" for v in range(visits)]
    for folder in folders:  # before rendering: a folder that cannot be written is an option
        check_output_folder(folder, what="--out")

    written: list[tuple[Path, BackParameters, Any]] = []
    for visit, folder in enumerate(folders):
        visit_params = progressed(params, visit, progression)
        _echo_progress(f"[{visit + 1}/{visits}] rendering back -> {folder}")
        scene = _make_back(visit_params)
        rendering = render(scene, station, settings=settings, seed=seed + visit)
        paths = _write(
            folder,
            rendering,
            scene,
            station,
            stem="frame",
            image_format=image_format,
            truth_format=truth_format,
        )
        (folder / "back.json").write_text(
            json.dumps(visit_params.to_dict(), indent=2) + "\n", encoding="utf-8"
        )
        written.append((folder, visit_params, rendering))
        typer.echo(f"wrote {paths['ground_truth'].parent}")
    if ingest:
        assert patient is not None
        _ingest_visits(ctx, written, station, patient=patient, station_name=station_name)


def _make_back(params: Any) -> Any:
    from rasterserver.simulator.back import make_back

    return make_back(params)


def _ingest_visits(
    ctx: typer.Context,
    written: list[tuple[Path, Any, Any]],
    station: Any,
    *,
    patient: str,
    station_name: str,
) -> None:
    from rasterserver.archive import Archive
    from rasterserver.commands.common import settings as cli_settings
    from rasterserver.simulated_visits import SimulatedVisit, archive_visits

    visits = [
        SimulatedVisit(params, rendering.image, note=f"; parameters in {folder / 'back.json'}")
        for folder, params, rendering in written
    ]
    with Archive.create(cli_settings(ctx)) as archive:
        rows = archive_visits(
            archive,
            visits,
            station=station,
            patient=patient,
            station_name=station_name,
            log=_echo_progress,
        )
    for acq in rows:
        typer.echo(f"ingested {acq.uid}")


_CALIBRATION_HELP = (
    "Render the seed's six control-point frames: 3 plate configurations x projector on/off."
    "\n\n"
    "In each configuration a high plate (Z = -100 mm) and a low plate (Z = +100 mm), each with "
    "seven black holes (a 2x3 grid plus an orientation marker), stand at two of the three "
    "lateral places (X = -180, 0, +180 mm); over the three configurations each place carries "
    "a high and a low plate once.\n\n"
    "Files in --out: config<k>-projector-on.png and config<k>-projector-off.png (or .npy) "
    "with their _truth.npz/.h5; control_points.json (id, configuration, plate, lateral, "
    "index, x, y, z in world mm); calibration.json (the true station) and raster.json."
)


@sim_app.command("calibration-body", help=_CALIBRATION_HELP)
def calibration_body(
    seed: _Seed = 0,
    supersample: _Supersample = 3,
    noise: _Noise = True,
    bit_depth: _BitDepth = 8,
    width: _Width = 576,
    height: _Height = 604,
    hole_radius: Annotated[
        float, typer.Option(help="Radius of the control-point holes, mm (1-15).")
    ] = 4.5,
    clinic_body: Annotated[
        bool,
        typer.Option(
            "--clinic-body",
            help="The body as a clinic's camera sees it: a cast base as bright as the plates "
            "with mounting holes, columns and plate sides in view, uneven light.",
        ),
    ] = False,
    layout_seed: Annotated[
        int | None,
        typer.Option(help="Drill an irregular seven-hole layout drawn from this seed (>= 0); "
                     "control_points.json carries it."),
    ] = None,
    out: _Out = Path("simulated-calibration"),
    image_format: _Format = ImageFormat.png,
    truth_format: _Truth = TruthFormat.npz,
) -> None:
    """Render the seed's six control-point frames: 3 plate configurations x projector on/off.

    In each configuration a high plate (Z = -100 mm) and a low plate (Z = +100 mm), each with
    seven black holes (a 2x3 grid plus an orientation marker), stand at two of the three
    lateral places (X = -180, 0, +180 mm); over the three configurations each place carries
    a high and a low plate once. Files in --out: config<k>-projector-on.png and
    config<k>-projector-off.png (or .npy) with their _truth.npz/.h5, control_points.json (id,
    configuration, plate, lateral, index, x, y, z in world mm; see its "frame" entry),
    calibration.json (the true station) and raster.json.
    """
    import numpy as np

    from rasterserver.output_files import check_output_folder
    from rasterserver.simulator.calibration_body import (
        REAL_BODY,
        control_points,
        make_calibration_body,
        random_hole_layout,
        write_control_points,
    )
    from rasterserver.simulator.ground_truth import LineRows
    from rasterserver.simulator.render import render

    _check_seed("--seed", seed)
    layout = None
    if layout_seed is not None:
        _check_seed("--layout-seed", layout_seed)
        layout = random_hole_layout(np.random.default_rng(layout_seed))
    body: dict[str, Any] = dict(REAL_BODY) if clinic_body else {}
    station = _station(width, height)
    check_output_folder(out, what="--out")
    frames = [(k, on) for k in range(3) for on in (True, False)]
    for i, (k, on) in enumerate(frames):
        stem = f"config{k}-projector-{'on' if on else 'off'}"
        _echo_progress(f"[{i + 1}/{len(frames)}] rendering {stem}")
        scene = make_calibration_body(k, hole_radius=hole_radius, layout=layout, **body)
        settings = _render_settings(
            supersample=supersample, noise=noise, bit_depth=bit_depth, projector=on
        )
        rendering = render(scene, station, settings=settings, seed=seed + i)
        if not on:
            # The renderer's ground truth is geometric; with the projector off no raster
            # line reaches the plates, so say so instead of listing the lines' positions.
            rendering = dataclasses.replace(
                rendering,
                line_number=np.full_like(rendering.line_number, -1),
                line_rows=LineRows.empty(),
                shadow=rendering.visible.copy(),
            )
        _write(
            out,
            rendering,
            scene,
            station,
            stem=stem,
            image_format=image_format,
            truth_format=truth_format,
        )
    path = write_control_points(out / "control_points.json", control_points(layout=layout),
                                layout=layout)
    typer.echo(f"wrote {len(frames)} frames and {path.name} to {out}")


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command group to ``app``."""
    app.add_typer(sim_app, name="simulate")
