"""The simulator's six control-point frames, rendered once per test process.

Supersampling 2 (not the CLI's default 3) keeps the rendering to a few seconds; the hole
centres and line peaks it gives are as accurate as the calibration needs (the figures tested
are met with margin). Default noise, fixed seeds.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

from rasterserver.cli import main

if TYPE_CHECKING:
    from rasterserver.calibration.station_calibration import CalibrationFrames
    from rasterserver.optics import Station


@cache
def rendered_dir() -> Path:
    """A folder written by ``rasterserver simulate calibration-body --supersample 2``."""
    out = Path(tempfile.mkdtemp(prefix="rs-calibration-frames-"))
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    code = main(["simulate", "calibration-body", "--supersample", "2", "--seed", "0",
                 "--out", str(out)])
    if code != 0:
        raise RuntimeError(f"simulate calibration-body failed with exit code {code}")
    return out


def perturbed_station() -> Station:
    """The default station with both devices turned, moved and re-focused a little.

    Not the simulator's identity rotations: shows the calibration does not lean on them, and
    that what the lines cannot determine (taken from the nominal reference) does no harm.
    """
    import numpy as np

    from rasterserver.optics import Camera, Projector, Station, default_station, rotation_matrix

    base = default_station()
    cam, proj = base.camera, base.projector
    r_cam = rotation_matrix(0.6, -0.3, 0.5)
    camera = Camera(
        K=cam.K + np.array([[40.0, 0, 3.0], [0, 40.0, -2.0], [0, 0, 0]]),
        dist=np.array([-0.07, 0.0, 0.0, 0.0, 0.0]),
        R=r_cam, t=-r_cam @ np.array([5.0, -8.0, -1985.0]), width=cam.width, height=cam.height,
    )
    r_proj = rotation_matrix(-1.5, 2.0, -0.7)
    projector = Projector(
        K=proj.K + np.array([[30.0, 0, 0], [0, 30.0, 12.0], [0, 0, 0]]),
        dist=np.array([-0.02, 0.0, 0.0, 0.0, 0.0]),
        R=r_proj, t=-r_proj @ np.array([-20.0, -790.0, -2010.0]),
        width=proj.width, height=proj.height,
    )
    return Station(camera=camera, projector=projector, raster=base.raster, name="perturbed")


@cache
def perturbed_frames() -> CalibrationFrames:
    """The six frames of :func:`perturbed_station` (supersampling 2, default noise, seed 5)."""
    from rasterserver.calibration.station_calibration import (
        CalibrationFrames,
    )
    from rasterserver.simulator.calibration_body import make_calibration_body
    from rasterserver.simulator.render import RenderSettings, render

    lit = RenderSettings(supersampling=2)
    dark = lit.replace(projector_electrons=0.0, ambient_electrons=15000.0, line_rows=False)
    station = perturbed_station()
    off, on = {}, {}
    for i, (k, projector_on) in enumerate((k, p) for k in range(3) for p in (True, False)):
        image = render(make_calibration_body(k), station, settings=lit if projector_on else dark,
                       seed=5 + i).image
        (on if projector_on else off)[k] = image
    return CalibrationFrames(off, on)


#: The irregular hole layout of :func:`real_body_frames` (seed 11 of ``random_hole_layout``).
REAL_LAYOUT_SEED = 11


@cache
def real_body_frames() -> tuple[CalibrationFrames, Path]:
    """The six frames of the body as a clinic's camera sees it, with :func:`perturbed_station`.

    Bright cast base (as bright as the plates), columns and plate sides in view, mounting
    holes on the base, uneven light, an irregular seven-hole layout; supersampling 2, default
    noise, seed 40. Returns the frames and the control-point file (JSON, with the layout).
    """
    import numpy as np

    from rasterserver.calibration.station_calibration import CalibrationFrames
    from rasterserver.simulator.calibration_body import (
        control_points,
        random_hole_layout,
        real_body,
        write_control_points,
    )
    from rasterserver.simulator.render import RenderSettings, render

    layout = random_hole_layout(np.random.default_rng(REAL_LAYOUT_SEED))
    lit = RenderSettings(supersampling=2)
    dark = lit.replace(projector_electrons=0.0, ambient_electrons=15000.0, line_rows=False)
    station = perturbed_station()
    off, on = {}, {}
    for i, (k, projector_on) in enumerate((k, p) for k in range(3) for p in (True, False)):
        image = render(real_body(k, layout=layout), station,
                       settings=lit if projector_on else dark, seed=40 + i).image
        (on if projector_on else off)[k] = image
    out = Path(tempfile.mkdtemp(prefix="rs-real-body-"))
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    path = write_control_points(out / "control_points.json", control_points(layout=layout),
                                layout=layout)
    return CalibrationFrames(off, on), path
