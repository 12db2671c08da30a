"""Visit B onto visit A: landmark frames first, then point-to-plane ICP (open3d) on the
trunks; refused with a reason, never a guessed alignment."""

from __future__ import annotations

from typing import Any

import numpy as np

from rasterserver.comparison.geometry import apply_transform, rotation_angle
from rasterserver.comparison.thresholds import (
    EDGE_MARGIN,
    THRESHOLDS,
    ComparisonRefusedError,
    Thresholds,
)
from rasterserver.comparison.trunk import frame_transform, pair_frames, trunk_mesh
from rasterserver.comparison.visits import Registration, Visit
from rasterserver.records_surface import MeshRecord


def point_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> Any:
    """An open3d point cloud of ``points`` (with ``normals`` if given)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, dtype=np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.array(normals, dtype=np.float64))
    return cloud


def icp(
    source: MeshRecord,
    target: MeshRecord,
    start: np.ndarray,
    thresholds: Thresholds,
    judge: float | None = None,
) -> tuple[np.ndarray, float, float]:
    """Point-to-plane ICP of ``source`` onto ``target`` from ``start``, coarse then fine;
    returns the transform, fitness and inlier rmse at ``judge`` (default
    ``thresholds.fine_distance``)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = point_cloud(source.vertices)
    if thresholds.voxel:
        # tens of thousands of trunk points say no more about six degrees of freedom than a
        # few thousand; ICP's cost is in the source's nearest-neighbour searches
        src = src.voxel_down_sample(thresholds.voxel)
    dst = point_cloud(target.vertices, target.normals)
    transform = np.array(start, dtype=np.float64)
    for distance, kernel in (
        (thresholds.coarse_distance, None),
        (thresholds.fine_distance, thresholds.robust_scale),
    ):
        # The fine pass weighs residuals with Tukey's biweight: a local change between visits
        # (a rib hump grown by millimetres) is what the map must show, so it must not pull the
        # alignment; plain least squares spreads it over the whole trunk.
        method = (
            reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=kernel))
            if kernel
            else reg.TransformationEstimationPointToPlane()
        )
        criteria = reg.ICPConvergenceCriteria(
            relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=60
        )
        result = reg.registration_icp(src, dst, distance, transform, method, criteria)
        transform = np.array(result.transformation)
    final = reg.evaluate_registration(src, dst, judge or thresholds.fine_distance, transform)
    return transform, float(final.fitness), float(final.inlier_rmse)


def register(
    a: Visit, b: Visit, *, thresholds: Thresholds = THRESHOLDS, margin: float = EDGE_MARGIN
) -> Registration:
    """Register visit B onto visit A: landmark frames, then point-to-plane ICP on the trunk.

    Parameters
    ----------
    a, b : Visit
        The two visits; B is moved onto A.
    thresholds : Thresholds, optional
        When the result is accepted (:data:`THRESHOLDS`).
    margin : float, optional
        Erosion of the outline for the trunk (:func:`trunk_mask`), mm.

    Returns
    -------
    Registration

    Raises
    ------
    ComparisonRefusedError
        A visit without a body frame, without a measured trunk (too few points), ICP that
        ends with too low a fitness or too high an rmse, or that moved far from the landmark
        start; the message names the figure and its limit.
    """
    fa, fb, start_from = pair_frames(
        a, b, partial=thresholds.partial_frame, neither=thresholds.frame_without_vp
    )
    start = frame_transform(fa, fb)
    # B's trunk is moved onto A's connected trunk, arms included, so that B's points at the
    # edge of its rows (the armpits) keep their counterparts in the overlap and the fitness
    target = trunk_mesh(a, margin=margin, window=None, frame=fa)
    source = trunk_mesh(b, margin=margin, window=thresholds.axis_window, frame=fb)
    for visit, part in ((a, target), (b, source)):
        if len(part.vertices) < thresholds.min_points:
            raise ComparisonRefusedError(
                f"visit {visit.label or '?'} has too little measured trunk to register "
                f"({len(part.vertices)} points between DM and VP, at least "
                f"{thresholds.min_points} needed)"
            )
    transform, fitness, rmse = icp(source, target, start, thresholds)
    centre = source.vertices.mean(axis=0)
    shift = float(
        np.linalg.norm(
            apply_transform(transform, centre[None])[0] - apply_transform(start, centre[None])[0]
        )
    )
    turn = rotation_angle(transform[:3, :3] @ start[:3, :3].T)
    problems = []
    if fitness < thresholds.min_fitness:
        problems.append(
            f"only {fitness:.0%} of the trunk overlaps within {thresholds.fine_distance:g} mm "
            f"(at least {thresholds.min_fitness:.0%} needed)"
        )
    if fitness > 0 and rmse > thresholds.max_rmse:
        problems.append(f"residual {rmse:.1f} mm rms (at most {thresholds.max_rmse:g} mm)")
    if shift > thresholds.max_shift or turn > thresholds.max_turn:
        problems.append(
            f"ICP moved {shift:.0f} mm / {turn:.1f}° away from the landmark frames' alignment "
            f"(at most {thresholds.max_shift:g} mm / {thresholds.max_turn:g}°)"
        )
    if problems:
        raise ComparisonRefusedError(
            f"visits {a.label or 'A'} and {b.label or 'B'} could not be registered: "
            + "; ".join(problems)
        )
    return Registration(transform, start, fitness, rmse, len(source.vertices), start_from)
