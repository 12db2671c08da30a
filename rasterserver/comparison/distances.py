"""Signed distances between registered meshes: the distance map, the asymmetry map (a back
against its own mirror image) and the change of asymmetry between visits."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rasterserver.comparison.displaced import displaced_regions
from rasterserver.comparison.geometry import apply_transform, rotation_angle
from rasterserver.comparison.registration import icp
from rasterserver.comparison.thresholds import (
    EDGE_MARGIN,
    MAX_DISTANCE,
    THRESHOLDS,
    ComparisonRefusedError,
    Thresholds,
)
from rasterserver.comparison.trunk import (
    landmark_frame,
    pair_frames,
    submesh,
    trunk_mask,
    trunk_mesh,
)
from rasterserver.comparison.visits import DistanceMap, Registration, Visit
from rasterserver.records_surface import MeshRecord


def signed_distances(
    vertices: np.ndarray,
    normals: np.ndarray,
    mesh: MeshRecord,
    *,
    limit: float,
    through_slack: float | None = None,
) -> np.ndarray:
    """Signed distance along each normal to ``mesh`` (the nearer hit forward or backward).

    Parameters
    ----------
    vertices, normals : numpy.ndarray
        ``(N, 3)`` where from and along which (need not be unit).
    mesh : MeshRecord
        The surface hit.
    limit : float
        Farther hits are NaN (mm).
    through_slack : float or None, optional
        A hit along the normal more than twice as far as the nearest point of ``mesh`` and
        farther than it by more than this (mm) passed through a hole of ``mesh`` (a piece
        not measured) to another part of it: NaN, no counterpart. A real change between two
        surfaces tilted by up to 60° to each other stays within twice the nearest distance.
        None: every hit kept.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` mm, NaN where there is no counterpart.
    """
    import open3d as o3d

    out = np.full(len(vertices), np.nan)
    if len(vertices) == 0 or len(mesh.triangles) == 0:
        return out
    scene = o3d.t.geometry.RaycastingScene()
    # open3d's generated stubs drop the defaults (None) of Tensor's dtype and device
    scene.add_triangles(
        o3d.core.Tensor(  # type: ignore[call-overload]
            np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        ),
        o3d.core.Tensor(  # type: ignore[call-overload]
            np.ascontiguousarray(mesh.triangles, dtype=np.uint32)
        ),
    )
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    rays = np.concatenate([np.hstack([vertices, n]), np.hstack([vertices, -n])]).astype(np.float32)
    rays_t = o3d.core.Tensor(rays)  # type: ignore[call-overload]  # (stubs: see above)
    hit = scene.cast_rays(rays_t)["t_hit"].numpy().astype(np.float64)
    ahead, behind = hit[: len(vertices)], hit[len(vertices) :]
    signed = np.where(ahead <= behind, ahead, -behind)
    ok = np.isfinite(signed) & (np.abs(signed) <= limit)
    if through_slack is not None:
        points = o3d.core.Tensor(vertices.astype(np.float32))  # type: ignore[call-overload]
        nearest = scene.compute_distance(points).numpy().astype(np.float64)
        far = np.abs(signed)
        ok &= ~((far > 2.0 * nearest) & (far > nearest + through_slack))
    out[ok] = signed[ok]
    return out


def distance_map(
    a: Visit,
    b: Visit,
    registration: Registration,
    *,
    margin: float = EDGE_MARGIN,
    limit: float = MAX_DISTANCE,
    thresholds: Thresholds = THRESHOLDS,
) -> DistanceMap:
    """Signed distance from each trunk vertex of A's mesh to B's mesh, after registration.

    Parameters
    ----------
    a, b : Visit
        The two visits.
    registration : Registration
        B onto A (:func:`register`).
    margin : float, optional
        Outline erosion of A's trunk, mm.
    limit : float, optional
        Largest distance reported (mm); beyond, NaN.
    thresholds : Thresholds, optional
        ``axis_window`` (the trunk's rows), ``partial_frame`` (A's trunk frame as
        :func:`register` made it), ``displaced_limit``, ``displaced_slope`` and
        ``displaced_margin`` (regions from the outline inwards that differ by more, arms,
        hands or clothing placed otherwise, are not compared).

    Returns
    -------
    DistanceMap
        On A's trunk mesh; positive where B is posterior of A (along A's normal, which faces
        the camera); NaN and ``displaced`` where not compared.
    """
    # the displaced regions are found on the connected trunk, arms included: an arm's core
    # (differing most) shows where its ramp onto the trunk begins
    frame = pair_frames(
        a, b, partial=thresholds.partial_frame, neither=thresholds.frame_without_vp
    )[0]
    wide = trunk_mesh(a, margin=margin, window=None, frame=frame)
    moved = MeshRecord(
        vertices=apply_transform(registration.transform, np.asarray(b.mesh.vertices, dtype=float)),
        triangles=b.mesh.triangles,
        normals=np.asarray(b.mesh.normals) @ registration.transform[:3, :3].T,
    )
    distance = signed_distances(
        wide.vertices, wide.normals, moved, limit=limit, through_slack=thresholds.through_slack
    )
    displaced = np.zeros(len(distance), dtype=bool)
    if thresholds.displaced_limit is not None:
        displaced = displaced_regions(
            wide.vertices,
            wide.triangles,
            distance,
            limit=thresholds.displaced_limit,
            slope=thresholds.displaced_slope,
            margin=thresholds.displaced_margin,
        )
        distance[displaced] = np.nan
    keep = trunk_mask(a, wide.vertices, margin=margin, window=thresholds.axis_window, frame=frame)
    trunk = submesh(wide, keep)
    return DistanceMap(
        trunk.vertices,
        trunk.triangles,
        trunk.normals,
        distance[keep],
        displaced=displaced[keep] if thresholds.displaced_limit is not None else None,
    )


def asymmetry_map(
    visit: Visit,
    *,
    thresholds: Thresholds = THRESHOLDS,
    margin: float = EDGE_MARGIN,
    limit: float = MAX_DISTANCE,
) -> DistanceMap:
    """The back against its own mirror image (:func:`asymmetry_fit` without the fit)."""
    return asymmetry_fit(visit, thresholds=thresholds, margin=margin, limit=limit)[0]


def asymmetry_fit(
    visit: Visit,
    *,
    thresholds: Thresholds = THRESHOLDS,
    margin: float = EDGE_MARGIN,
    limit: float = MAX_DISTANCE,
) -> tuple[DistanceMap, np.ndarray, float, float]:
    """The back against its own mirror image about its plane of best symmetry.

    The mesh is mirrored about the body frame's sagittal plane (through DM, normal to the
    transverse axis), fitted onto the original trunk by point-to-plane ICP (so the plane is
    the one of best symmetry, not only the landmarks'), and the signed distance along the
    original's normals to the mirror image is taken on the trunk.

    Parameters
    ----------
    visit : Visit
        The visit.
    thresholds, margin, limit
        As for :func:`register` and :func:`distance_map`; ``thresholds.through_slack``
        leaves a vertex whose normal passes through a hole of the mirror image without a
        value (:func:`signed_distances`; asymmetry stage version 3); ``thresholds.mirror_reach``
        fits only the trunk seen alike on both sides (version 4).

    Returns
    -------
    DistanceMap
        Positive where the back is more posterior (towards the camera) than its mirror
        image there: a right rib hump is positive on the right and, mirrored, negative at
        the same place on the left.
    transform : numpy.ndarray
        ``(4, 4)`` the fit of the mirror image onto the back (after the reflection).
    fitness, rmse : float
        The fit's overlap fraction and inlier rms (mm) at ``thresholds.coarse_distance``.

    Raises
    ------
    ComparisonRefusedError
        No body frame, too little trunk, or the mirror image cannot be fitted.
    """
    origin, axes = landmark_frame(visit.shape, visit.label)
    across = axes[0]
    reflect = np.eye(4)
    reflect[:3, :3] -= 2.0 * np.outer(across, across)
    reflect[:3, 3] = 2.0 * (origin @ across) * across
    mesh = visit.mesh
    mirrored = MeshRecord(
        vertices=apply_transform(reflect, np.asarray(mesh.vertices, dtype=float)),
        triangles=np.ascontiguousarray(mesh.triangles[:, ::-1]),  # a mirror turns the winding
        normals=np.asarray(mesh.normals) @ reflect[:3, :3].T,
    )
    trunk = trunk_mesh(visit, margin=margin, window=thresholds.axis_window)
    if len(trunk.vertices) < thresholds.min_points:
        raise ComparisonRefusedError(
            f"visit {visit.label or '?'} has too little measured trunk for an asymmetry map "
            f"({len(trunk.vertices)} points, at least {thresholds.min_points} needed)"
        )
    mirror_trunk = submesh(
        mirrored, trunk_mask(visit, mesh.vertices, margin=margin, window=thresholds.axis_window)
    )
    if thresholds.mirror_reach:
        from scipy.spatial import cKDTree

        # the inliers are fixed where the landmarks put the plane, so that ICP refines the
        # plane without trading them for other parts of an asymmetric scene (version 4)
        gap, _ = cKDTree(trunk.vertices).query(
            mirror_trunk.vertices, distance_upper_bound=thresholds.mirror_reach
        )
        both = np.isfinite(gap)
        seen = int(both.sum())
        if seen < thresholds.min_points:
            raise ComparisonRefusedError(
                f"visit {visit.label or '?'} has too little trunk seen alike on both sides "
                f"for an asymmetry map ({seen} points within "
                f"{thresholds.mirror_reach:g} mm of their mirror image, at least "
                f"{thresholds.min_points} needed)"
            )
        mirror_fit = submesh(mirror_trunk, both)
    else:
        mirror_fit = mirror_trunk
    # The landmark plane is within a few millimetres of the plane of best symmetry, so both
    # passes use mirror_distance, whose cut-off already keeps the most asymmetric parts (a
    # scoliotic back differs from its mirror image by up to a centimetre or two: that is what
    # the map shows) out of the fit; for the same reason the fit is judged at the coarse
    # distance. Least squares, not the robust kernel: with the back's broad asymmetry Tukey's
    # weights keep changing and ICP runs to its iteration limit (4 times slower) for a plane
    # that differs by a few hundredths of a millimetre in the map's median.
    mirror = replace(
        thresholds,
        coarse_distance=thresholds.mirror_distance,
        fine_distance=thresholds.mirror_distance,
        robust_scale=None,
    )
    transform, fitness, rmse = icp(
        mirror_fit, trunk, np.eye(4), mirror, judge=thresholds.coarse_distance
    )
    turn, shift = rotation_angle(transform[:3, :3]), float(np.linalg.norm(transform[:3, 3]))
    if fitness < thresholds.min_fitness or shift > thresholds.max_shift:
        raise ComparisonRefusedError(
            f"the mirror image of visit {visit.label or '?'} could not be fitted onto it "
            f"(overlap {fitness:.0%}, residual {rmse:.1f} mm, moved {shift:.0f} mm / "
            f"{turn:.1f}°)"
        )
    fitted = MeshRecord(
        vertices=apply_transform(transform, mirrored.vertices),
        triangles=mirrored.triangles,
        normals=mirrored.normals @ transform[:3, :3].T,
    )
    # the distance runs from the back to its mirror; the back lying out of it is the negative
    # a normal passing through a hole of the mirror image (a piece not measured on the other
    # side) meets another part of it: no counterpart there, as in the distance map
    distance = -signed_distances(
        trunk.vertices,
        trunk.normals,
        fitted,
        limit=limit,
        through_slack=thresholds.through_slack,
    )
    amap = DistanceMap(
        trunk.vertices, trunk.triangles, trunk.normals, distance, what="asymmetry (mm)"
    )
    return amap, transform, fitness, rmse


def asymmetry_change(
    a_map: DistanceMap,
    b_map: DistanceMap,
    registration: Registration,
    *,
    reach: float = 3.0,
    displaced: np.ndarray | None = None,
) -> DistanceMap:
    """B's asymmetry minus A's, on A's trunk vertices.

    Parameters
    ----------
    a_map, b_map : DistanceMap
        :func:`asymmetry_map` of visits A and B (each in its own world frame).
    registration : Registration
        B onto A.
    reach : float, optional
        Largest distance (mm) from an A vertex to the nearest registered B vertex whose value
        it takes; farther, NaN.
    displaced : numpy.ndarray, optional
        The distance map's ``displaced`` vertices (the same trunk as ``a_map``'s): not
        compared here either.

    Returns
    -------
    DistanceMap
        On A's trunk; positive where the asymmetry grew towards the posterior.
    """
    from scipy.spatial import cKDTree

    moved = apply_transform(registration.transform, b_map.vertices)
    change = np.full(len(a_map.vertices), np.nan)
    if len(moved):
        gap, index = cKDTree(moved).query(a_map.vertices, distance_upper_bound=reach)
        near = np.isfinite(gap)
        change[near] = b_map.distance[np.asarray(index)[near]] - a_map.distance[near]
    if displaced is not None:
        if len(displaced) != len(change):
            raise ValueError("displaced must hold one flag per vertex of A's asymmetry map")
        change[displaced] = np.nan
    return DistanceMap(
        a_map.vertices,
        a_map.triangles,
        a_map.normals,
        change,
        what="asymmetry change (mm)",
        displaced=displaced,
    )
