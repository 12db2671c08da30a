"""Simulated scenes with exact ground truth for the reconstruction, smoothing and mesh tests.

Renderings are cached per process (one rendering takes seconds). ``numbered_lines`` turns the
simulator's exact per-column line-centre rows into the record the line-numbering stage
produces, optionally with Gaussian row noise of a realistic peak detector, so stages 5-7 are
measured in isolation from stages 1-4.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import open3d as o3d

from rasterserver.optics import Station, default_station
from rasterserver.simulator.ground_truth import LineRows
from rasterserver.simulator.render import Rendering, RenderSettings, render
from rasterserver.simulator.scene import Scene


def plane_scene() -> Scene:
    """A flat wall 10 mm behind the origin, turned 10° about the vertical axis."""
    from rasterserver.simulator.shapes import tilted_plane

    return tilted_plane(10.0, tilt_y=10.0)


def sphere_scene() -> Scene:
    """A sphere of radius 250 mm whose front pole lies at ``z = -20``."""
    from rasterserver.simulator.shapes import sphere

    return sphere(centre=(0.0, 0.0, 230.0), radius=250.0)


def back_scene(preset: str = "moderate") -> Scene:
    """The simulator's back preset (trunk and arms)."""
    from rasterserver.simulator.back import make_back
    from rasterserver.simulator.back import preset as back_preset

    return make_back(back_preset(preset))


_SCENES = {"plane": plane_scene, "sphere": sphere_scene, "back": back_scene}


@lru_cache(maxsize=8)
def scene(name: str) -> Scene:
    """The named scene: ``plane``, ``sphere`` or ``back``."""
    return _SCENES[name]()


@lru_cache(maxsize=8)
def rendering(name: str, seed: int = 1) -> Rendering:
    """Render the named scene with the default station (cached)."""
    return render(scene(name), station(), settings=RenderSettings(), seed=seed)


@lru_cache(maxsize=1)
def station() -> Station:
    """The default station (seed's geometry, with lens distortion on both devices)."""
    return default_station()


def numbered_lines(
    line_rows: LineRows,
    image_shape: tuple[int, int],
    *,
    noise: float = 0.0,
    seed: int = 0,
    raster: Any = None,
) -> Any:
    """A ``NumberedLines`` record holding exact (or noisy) line-centre rows.

    Parameters
    ----------
    line_rows : LineRows
        The simulator's ground truth.
    image_shape : tuple of int
        ``(rows, columns)``.
    noise : float
        Standard deviation (px) of Gaussian noise added to the rows.
    seed : int
        Noise seed.
    raster : Raster, optional
        To fill the observed kinds; all light when omitted.
    """
    from rasterserver.records_lines import NumberedLines

    order = np.lexsort((line_rows.row, line_rows.column))
    col = line_rows.column[order].astype(np.int32)
    row = line_rows.row[order].astype(np.float64)
    number = line_rows.number[order].astype(np.int32)
    if noise > 0:
        row = row + np.random.default_rng(seed).normal(0.0, noise, row.size)
    lines, line_id = np.unique(number, return_inverse=True)
    n = col.size
    kinds = np.zeros(lines.size, dtype=np.int8)
    if raster is not None:
        pairs = zip(raster.numbers, raster.kinds, strict=True)
        heavy = {int(k) for k, kind in pairs if kind == "heavy"}
        kinds = np.array([1 if int(k) in heavy else 0 for k in lines], dtype=np.int8)
    area = np.where(kinds[line_id] == 1, 150.0, 100.0).astype(np.float32)
    return NumberedLines(
        col=col,
        row=row,
        area=area,
        height=np.full(n, 50.0, np.float32),
        width=np.full(n, 5, np.int16),
        image_shape=np.asarray(image_shape, dtype=np.int64),
        line_id=line_id.astype(np.int32),
        order=line_id.astype(np.int32),
        line_order=np.arange(lines.size, dtype=np.int32),
        line_component=np.zeros(lines.size, dtype=np.int32),
        number=number,
        line_number=lines.astype(np.int32),
        kind_observed=kinds,
        confidence=1.0,
        reason="",
    )


def distance_to_scene(
    scn: Scene, points: np.ndarray, *, objects: list[str] | None = None
) -> np.ndarray:
    """Unsigned distance (mm) of ``(N, 3)`` points to the true surface.

    The analytic surface for the simulator's shapes, else the scene's meshes (open3d
    raycasting; the rendering's ground truth is exact on those very meshes).
    """
    if scn.metadata.get("kind") in ("plane", "sphere", "cylinder", "step") and objects is None:
        from rasterserver.simulator.shapes import surface_distance

        return np.abs(surface_distance(scn, np.asarray(points, dtype=np.float64)))
    rc = o3d.t.geometry.RaycastingScene()
    for obj in scn.objects:
        if objects is None or obj.name in objects:
            rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    query = o3d.core.Tensor(np.asarray(points, dtype=np.float32))
    # float32 queries: ~1e-4 mm at 2 m, far below the tolerances tested
    return rc.compute_distance(query).numpy().astype(np.float64)


def rms(values: np.ndarray) -> float:
    """Root mean square of the finite values."""
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2)))


STATION_NAME = "clinic-1"


def archive_with_frames(settings: Any, frames: dict[str, np.ndarray], *, calibrate: bool = True):
    """A fresh archive with station ``clinic-1`` (calibrated with the default station) and one
    single-frame acquisition of patient ``P1`` per entry of ``frames``.

    Returns
    -------
    archive : Archive
    uids : dict of str to str
        Acquisition uid per key of ``frames``.
    """
    import datetime as dt

    from rasterserver.archive import Archive, FrameSource

    archive = Archive.create(settings)
    archive.add_patient("P1")
    archive.add_station(STATION_NAME)
    if calibrate:
        st = station()
        archive.add_raster("default", st.raster_definition.to_dict())
        # in force before the frames below were taken (they carry past acquisition times)
        archive.add_calibration(
            STATION_NAME, st.to_dict(), raster="default",
            valid_from=dt.datetime(2000, 1, 1, tzinfo=dt.UTC),
        )
    uids = {}
    for k, (name, pixels) in enumerate(frames.items()):
        acq = archive.ingest(
            [FrameSource(pixels, role="raster", name=f"{name}.npy")],
            patient="P1",
            station=STATION_NAME,
            acquired_at=dt.datetime(2025, 3, 1, 10, k, tzinfo=dt.UTC),
        )
        uids[name] = acq.uid
    return archive, uids
