"""3-D reconstruction: each numbered peak's camera ray meets its raster line's light surface.

The seed's direct method (Hierholzer and Frobin 1989): instead of forming stereo pairs, the
ray through the camera's projection centre and the peak's image point is intersected with
the light surface of the peak's raster line, i.e. the surface through the projector centre
and the line ``v = const`` on the diapositive. Without projector distortion that surface is a
plane (closed form); with distortion it is cone-like and the intersection is iterated
(:meth:`rasterserver.optics.Projector.light_surface_intersection`, Newton on the ray
parameter). Camera distortion is removed when the ray is formed.

Speed: the camera rays depend only on the pixel position, so the exact rays through every
pixel centre (:meth:`rasterserver.optics.Camera.rays`) are computed once per camera and the
ray of a sub-pixel row is interpolated linearly between the two rows around it, in ideal
normalised coordinates. The interpolation error is bounded by the second derivative of the
lens distortion over half a pixel, ~1e-5 px for real lenses (checked in the tests), three
orders below the peak detector's noise. ``exact_rays=True`` forms every ray exactly instead.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import ClassVar

import numpy as np
from pydantic import Field

from rasterserver.errors import InputError
from rasterserver.optics import Camera, Projector, Station
from rasterserver.raster import Raster
from rasterserver.records_lines import NumberedLines
from rasterserver.records_surface import Points
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["RayPlaneReconstruction", "camera_rays", "line_positions", "reconstruct_points"]

_RAY_TABLES: OrderedDict[str, np.ndarray] = OrderedDict()
_RAY_TABLES_LOCK = threading.Lock()
_RAY_TABLES_MAX = 4  # stations per process; a table is 2 x H x W float64 (5.6 MB at 604x576)


def _ray_table(camera: Camera) -> np.ndarray:
    """Ideal normalised ``x`` and ``y`` of the rays through every pixel centre, ``(2, H, W)``."""
    key = camera.key()
    with _RAY_TABLES_LOCK:
        table = _RAY_TABLES.get(key)
        if table is not None:
            _RAY_TABLES.move_to_end(key)
            return table
    h, w = camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    _, directions = camera.rays(np.column_stack([cols.ravel(), rows.ravel()]))
    device = directions @ camera.R.T  # back to the camera frame: (x, y, 1) / norm
    # planes of x and y, each contiguous: the per-peak gathers then read one array each
    table = np.ascontiguousarray((device[:, :2] / device[:, 2:3]).T.reshape(2, h, w))
    table.flags.writeable = False
    with _RAY_TABLES_LOCK:
        _RAY_TABLES[key] = table
        while len(_RAY_TABLES) > _RAY_TABLES_MAX:
            _RAY_TABLES.popitem(last=False)
    return table


def camera_rays(
    camera: Camera, col: np.ndarray, row: np.ndarray, *, exact: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """World rays through image points on integer columns and sub-pixel rows.

    Parameters
    ----------
    camera : Camera
        The calibrated camera.
    col : numpy.ndarray
        ``(N,)`` integer image columns, within the image.
    row : numpy.ndarray
        ``(N,)`` float image rows (pixel-centre convention), within ``[-0.5, H - 0.5]``.
    exact : bool, optional
        Form every ray with :meth:`Camera.rays` instead of interpolating the per-pixel table.

    Returns
    -------
    origins : numpy.ndarray
        ``(N, 3)`` ray origins (the camera's projection centre), world mm.
    directions : numpy.ndarray
        ``(N, 3)`` world directions (not normalised unless ``exact``).
    """
    col = np.asarray(col)
    row = np.asarray(row, dtype=np.float64)
    if exact or col.size == 0:
        return camera.rays(np.column_stack([col.astype(np.float64), row]))
    # one compiled loop over the points (pixel_rays); the numba import costs ~0.3 s. Rows
    # -0.5..0 and H-1..H-0.5 extrapolate from the edge pair: linear, like inside
    from .pixel_rays import interpolated_rays

    device = interpolated_rays(_ray_table(camera), col, row)
    # R.T @ d per row; the seed's camera defines the world frame (R = I): skip the product
    directions = device if np.array_equal(camera.R, np.eye(3)) else device @ camera.R
    origins = np.broadcast_to(camera.centre, directions.shape)
    return origins, directions


def line_positions(raster: Raster, number: np.ndarray) -> np.ndarray:
    """Diapositive ``v`` of absolute line numbers; NaN for numbers the raster does not have.

    Parameters
    ----------
    raster : Raster
        The diapositive definition.
    number : numpy.ndarray
        ``(N,)`` integer line numbers.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` float64 ``v``.
    """
    positions, k, known = _line_index(raster, number)
    if positions.size == 0:
        return np.full(k.shape, np.nan)
    return np.where(known, positions[k], np.nan)


def _line_index(raster: Raster, number: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The raster's positions in line-number order, the index of each ``number`` in them and
    whether the raster has that number (an index of 0 where it has none, or no lines)."""
    order = np.argsort(raster.numbers, kind="stable")
    numbers = raster.numbers[order]
    number = np.asarray(number, dtype=np.int64)
    if numbers.size == 0:
        none = np.zeros(number.shape, np.intp)
        return raster.positions[order], none, none.astype(bool)
    k = np.clip(np.searchsorted(numbers, number), 0, numbers.size - 1)
    return raster.positions[order], k, numbers[k] == number


def _line_planes(
    projector: Projector, raster: Raster, number: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """:func:`line_positions` of ``number`` and their light planes (``Projector.light_plane``),
    the planes formed for the raster's lines and gathered: the same rows, N / lines fewer.
    Numbers the raster does not have get ``v`` NaN and a NaN plane, as ``light_plane`` of NaN.
    """
    if raster.numbers.size == 0:
        nan = np.full(np.shape(number), np.nan)
        return nan, projector.light_plane(nan)
    order = np.argsort(raster.numbers, kind="stable")
    positions = np.asarray(raster.positions[order], dtype=np.float64)
    normals, offsets = projector.light_plane(positions)
    # each peak's line looked up and its plane gathered in one compiled loop (line_planes;
    # the numba import costs ~0.3 s, hence here)
    from .line_planes import gathered_planes

    v, n_w, off = gathered_planes(
        np.ascontiguousarray(raster.numbers[order]),
        positions,
        np.ascontiguousarray(normals),
        np.ascontiguousarray(offsets),
        np.ascontiguousarray(number, dtype=np.int64),
    )
    return v, (n_w, off)


def reconstruct_points(
    station: Station,
    raster: Raster,
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    *,
    tolerance: float = 1e-7,
    exact_rays: bool = False,
) -> np.ndarray:
    """Intersect the camera rays of image points with their raster lines' light surfaces.

    Parameters
    ----------
    station : Station
        Calibrated camera and projector.
    raster : Raster
        Diapositive definition: line numbers to ``v``.
    col, row : numpy.ndarray
        ``(N,)`` image columns (integer) and rows (sub-pixel).
    number : numpy.ndarray
        ``(N,)`` absolute line numbers.
    tolerance : float, optional
        Newton tolerance on ``v`` (diapositive units; one unit is ~1 mm on the back).
    exact_rays : bool, optional
        See :func:`camera_rays`.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` world points (mm); NaN rows where the number is unknown or the ray misses
        the light surface.
    """
    v = line_positions(raster, number)
    origins, directions = camera_rays(station.camera, col, row, exact=exact_rays)
    return station.projector.light_surface_intersection(origins, directions, v, tol=tolerance)


class RayPlaneReconstruction(Stage[NumberedLines, Points]):
    """Ray / light-surface intersection of every numbered peak (the seed's direct method)."""

    name: ClassVar[str] = "points.ray-plane"
    stage: ClassVar[str] = "points"
    version: ClassVar[str] = "1"
    input_type = NumberedLines
    output_type = Points
    requires: ClassVar[tuple[str, ...]] = ("calibration", "raster")

    class Params(StageParams):
        """Parameters of :class:`RayPlaneReconstruction`."""

        tolerance: float = Field(
            1e-7, gt=0, le=1e-3, description="Newton tolerance on v (diapositive units)."
        )
        exact_rays: bool = Field(
            False, description="Form each camera ray exactly instead of from the pixel table."
        )
        depth_limit: float = Field(
            800.0,
            gt=0,
            description=(
                "Points farther than this from the world origin's plane (|z|, mm) are dropped "
                "and counted in the reason: they come from wrongly numbered lines."
            ),
        )

    def run(self, data: NumberedLines, params: Params, context: StageContext) -> Points:
        """Reconstruct the numbered peaks of ``data`` with the station in ``context``."""
        station = context.calibration
        raster = context.raster
        if not isinstance(station, Station):
            raise InputError(
                f"{self.name} needs a rasterserver.optics.Station as calibration, "
                f"not {type(station).__name__}"
            )
        if not isinstance(raster, Raster):
            raise InputError(
                f"{self.name} needs a rasterserver.raster.Raster, not {type(raster).__name__}"
            )
        shape = tuple(int(s) for s in data.image_shape)
        if shape != station.camera.shape:
            raise InputError(
                f"the frame is {shape[0]}x{shape[1]} (rows x columns) but the calibration's "
                f"camera {station.name!r} is {station.camera.height}x{station.camera.width}: "
                "wrong calibration for this frame"
            )
        notes: list[str] = [data.reason] if data.reason else []
        numbered = np.flatnonzero(data.number >= 0)
        if numbered.size == 0:
            why = "no numbered raster lines" if data.col.size else "no raster line peaks"
            return Points.empty(shape, "; ".join([why, *notes]))
        # half a pixel of slack beyond the frame's edge: a noisy sub-pixel row may stray there
        # and the ray table extrapolates linearly; anything farther is not a peak of this frame
        col, row = data.col[numbered], data.row[numbered]
        in_image = (col >= 0) & (col < shape[1]) & (row >= -1.0) & (row <= shape[0])
        outside = int(np.count_nonzero(~in_image))
        numbered = numbered[in_image]
        col, row, number = col[in_image], row[in_image], data.number[numbered]
        # reconstruct_points inlined: the line positions are looked up once, not twice, and
        # the light planes are formed once per raster line, not once per peak
        v, planes = _line_planes(station.projector, raster, number)
        origins, directions = camera_rays(station.camera, col, row, exact=params.exact_rays)
        xyz = station.projector.light_surface_intersection(
            origins, directions, v, tol=params.tolerance, planes=planes
        )
        # finite and within the measuring depth, in one compiled loop (point_screen; the
        # numba import costs ~0.3 s, hence here)
        from .point_screen import screened_points

        keep, x, y, z, (unknown, missed, beyond) = screened_points(
            np.ascontiguousarray(xyz, dtype=np.float64),
            np.ascontiguousarray(v, dtype=np.float64),
            float(params.depth_limit),
        )
        dropped = {
            "with a line number the raster does not have": unknown,
            "whose ray misses the light surface": missed,
            f"beyond the measuring depth (|z| > {params.depth_limit:g} mm)": beyond,
        }
        dropped["outside the frame"] = outside
        notes += [f"{n} peaks {what} dropped" for what, n in dropped.items() if n]
        if data.col.size > numbered.size:
            notes.append(f"{data.col.size - numbered.size} unnumbered peaks not reconstructed")
        sel = numbered[keep]
        points = Points(
            x=x,
            y=y,
            z=z,
            number=data.number[sel].astype(np.int32),
            col=data.col[sel].astype(np.int32),
            row=data.row[sel].astype(np.float64),
            area=data.area[sel].astype(np.float32),
            image_shape=np.asarray(shape, dtype=np.int64),
            reason="; ".join(notes),
        )
        if len(points) == 0:
            return Points.empty(shape, "; ".join(["no point could be reconstructed", *notes]))
        return points
