"""Comparing two visits of one patient: registration, distance map, asymmetry map.

Pure functions of the records of two analysed acquisitions (a :class:`Visit` each: the
smoothed :class:`~rasterserver.records_surface.Surface`, its
:class:`~rasterserver.records_surface.MeshRecord` and its
:class:`~rasterserver.records_analysis.BackShape`); no archive, no files. Every position is in
the world frame of visit A's calibration (mm); visit B is moved onto it.

:func:`register`
    Visit B onto visit A: first B's body-fixed landmark frame (origin DM, axes from VP, DL,
    DR) mapped onto A's, then point-to-plane ICP (open3d) on the *trunk* of both, the part of
    the back between DM and VP inside the measured outline eroded by :data:`EDGE_MARGIN`
    (arms, head, buttocks and the ragged edges left out). Refused with a reason
    (:class:`ComparisonRefusedError`) when a landmark frame is missing or ICP does not
    converge within :data:`THRESHOLDS`; never a guessed alignment.
:func:`distance_map`
    Signed distance along A's vertex normal from each trunk vertex of A's mesh to B's
    registered mesh: positive where B lies *posterior* of A (towards the camera: a rib hump
    that grew), negative where it lies anterior (flattened). NaN where B has no surface
    within :data:`MAX_DISTANCE` (no overlap).
:func:`asymmetry_map`
    One visit against its own mirror image about the symmetry plane (Komeili et al., Spine J
    15 (2015) 743-751): the back mirrored about the body frame's sagittal plane (through DM,
    normal the transverse axis), fitted onto the back by ICP (the plane of best symmetry),
    then the signed distance as above: positive where this side is more posterior than its
    mirror (the hump side), negative on the other side.
:func:`asymmetry_change`
    B's asymmetry map minus A's, on A's vertices (through the registration).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from rasterserver.errors import InputError
from rasterserver.records_analysis import BackShape, landmark_in
from rasterserver.records_surface import MeshRecord, Surface

__all__ = [
    "EDGE_MARGIN",
    "MAX_DISTANCE",
    "THRESHOLDS",
    "ComparisonRefusedError",
    "DistanceMap",
    "Registration",
    "Thresholds",
    "Visit",
    "asymmetry_change",
    "asymmetry_fit",
    "asymmetry_map",
    "distance_map",
    "landmark_transform",
    "register",
    "trunk_mask",
]

#: How far inside the measured outline the trunk starts (mm): the outermost cells of a
#: reconstructed surface are the least certain (grazing raster lines, smoothing at the rim).
EDGE_MARGIN = 15.0
#: Largest distance a distance map reports (mm); farther, the vertex has no counterpart.
MAX_DISTANCE = 30.0


@dataclass(frozen=True)
class Thresholds:
    """When a registration is accepted; values of :data:`THRESHOLDS` and why.

    Attributes
    ----------
    coarse_distance : float
        Correspondence distance of the first ICP pass (mm): the landmark frames agree to a few
        millimetres and about a degree (7 mm over a 440 mm trunk), so 20 mm catches them.
    fine_distance : float
        Correspondence distance of the second pass and of the reported fitness and rmse (mm).
    min_fitness : float
        Fraction of B's trunk points with a counterpart on A within ``fine_distance``: below
        0.7 the two surfaces do not overlap enough to say they were aligned.
    max_rmse : float
        Inlier rmse (mm); two visits of one back agree to well under 1 mm after
        registration, a progressed scoliosis to 2-3 mm; above 4 mm the alignment is not
        trusted.
    max_shift : float
        Largest distance (mm) ICP may move the trunk's centre away from where the landmark
        frames put it; farther means ICP slid into another minimum.
    max_turn : float
        Largest rotation (degrees) ICP may add to the landmark frames' rotation.
    min_points : int
        Fewest trunk points of either visit.
    robust_scale : float or None
        Scale (mm) of Tukey's biweight in the fine ICP pass: point-to-plane residuals beyond
        it do not pull the alignment (a changed region is left out of the fit). Two renders
        of one back agree to about 0.1 mm along the normal, a change worth mapping is
        millimetres. None: plain least squares.
    voxel : float or None
        Voxel size (mm) the moved visit's trunk is thinned to for ICP (one point per voxel,
        their mean); None: every point.
    mirror_distance : float
        Correspondence distance (mm) of the asymmetry map's mirror fit, both passes.
    """

    coarse_distance: float = 20.0
    fine_distance: float = 5.0
    min_fitness: float = 0.7
    max_rmse: float = 4.0
    max_shift: float = 25.0
    max_turn: float = 8.0
    min_points: int = 500
    robust_scale: float | None = 1.0
    voxel: float | None = 4.0
    mirror_distance: float = 10.0


#: The thresholds :func:`register` uses unless given others.
THRESHOLDS = Thresholds()


class ComparisonRefusedError(InputError):
    """Two visits cannot be compared; the message says why (exit 2, HTTP 422)."""


@dataclass(frozen=True, eq=False)
class BodyFrame:
    """The part of a back-shape analysis a comparison uses: landmarks and body frame.

    Attributes
    ----------
    frame_origin : numpy.ndarray
        ``(3,)`` DM (world mm), NaN without a frame.
    frame_axes : numpy.ndarray
        ``(3, 3)`` rows: transverse, vertical, sagittal unit axes.
    landmarks : numpy.ndarray
        ``(len(LANDMARKS), 3)`` world mm in the order of
        :data:`~rasterserver.records_analysis.LANDMARKS`, NaN when not found.
    reason : str
        Why the analysis found nothing, if it did not.
    reasons : str
        JSON object: what could not be computed, and why.
    """

    frame_origin: np.ndarray
    frame_axes: np.ndarray
    landmarks: np.ndarray
    reason: str = ""
    reasons: str = "{}"

    @classmethod
    def of(cls, shape: BackShape | BodyFrame) -> BodyFrame:
        """The body frame of an analysis."""
        if isinstance(shape, BodyFrame):
            return shape
        return cls(
            np.asarray(shape.frame_origin, dtype=float),
            np.asarray(shape.frame_axes, dtype=float),
            np.asarray(shape.landmarks, dtype=float),
            shape.reason,
            shape.reasons,
        )

    def landmark(self, name: str) -> np.ndarray | None:
        """World position of landmark ``name``, None when not found."""
        return landmark_in(self.landmarks, name)

    def reason_table(self) -> dict[str, str]:
        """What could not be computed, and why."""
        value = json.loads(self.reasons or "{}")
        return value if isinstance(value, dict) else {}


@dataclass(frozen=True)
class Visit:
    """What the comparison needs of one analysed acquisition.

    Attributes
    ----------
    surface : Surface
        The smoothed surface (its measured outline bounds the trunk).
    mesh : MeshRecord
        The mesh of that surface (normals facing the camera).
    shape : BackShape or BodyFrame
        The back-shape analysis (landmarks, body frame).
    label : str
        How messages name the visit (an acquisition uid, a date).
    """

    surface: Surface
    mesh: MeshRecord
    shape: BackShape | BodyFrame
    label: str = ""


@dataclass(frozen=True)
class Registration:
    """Visit B moved onto visit A.

    Attributes
    ----------
    transform : numpy.ndarray
        ``(4, 4)`` rigid transform from B's world frame to A's (``p_a = R p_b + t``).
    start : numpy.ndarray
        ``(4, 4)`` the landmark frames' transform ICP started from.
    fitness : float
        Fraction of B's trunk points with a counterpart on A's trunk within
        ``Thresholds.fine_distance`` (open3d's ``evaluate_registration``).
    rmse : float
        Rms distance of those counterparts (mm).
    points : int
        B's trunk points used.
    """

    transform: np.ndarray
    start: np.ndarray
    fitness: float
    rmse: float
    points: int

    def summary(self) -> dict[str, Any]:
        """JSON-ready: transform, landmark start, fitness, rmse, points, and what ICP added to
        the landmark start (angle and translation of ``transform @ inv(start)``)."""
        extra = self.transform @ np.linalg.inv(self.start)
        return {
            "transform": [[float(v) for v in row] for row in self.transform],
            "landmark_start": [[float(v) for v in row] for row in self.start],
            "fitness": float(self.fitness),
            "rmse_mm": float(self.rmse),
            "points": int(self.points),
            "icp_rotation_deg": _angle(extra[:3, :3]),
            "icp_translation_mm": float(np.linalg.norm(extra[:3, 3])),
        }


@dataclass(frozen=True)
class DistanceMap:
    """A signed scalar per vertex of a (trunk) mesh, in mm.

    Attributes
    ----------
    vertices : numpy.ndarray
        ``(N, 3)`` world mm (visit A's frame).
    triangles : numpy.ndarray
        ``(M, 3)`` int32 vertex indices.
    normals : numpy.ndarray
        ``(N, 3)`` unit vertex normals, facing the camera (posterior).
    distance : numpy.ndarray
        ``(N,)`` float64 signed distance (mm), NaN where there is no counterpart.
    what : str
        What the value is (for file headers and plots).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    distance: np.ndarray
    what: str = "signed distance (mm)"
    area: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "area", vertex_areas(self.vertices, self.triangles))

    def statistics(self) -> dict[str, Any]:
        """rms, largest absolute value (signed, and where), areas beyond ±2 and ±5 mm.

        Returns
        -------
        dict
            ``vertices``, ``measured`` (vertices with a value), ``overlap`` (their area
            fraction), ``rms_mm``, ``mean_mm``, ``max_abs_mm`` (signed), ``max_abs_at``
            (world mm), ``area_mm2`` (measured), ``area_above_2mm_mm2``,
            ``area_below_minus_2mm_mm2``, ``area_above_5mm_mm2``, ``area_below_minus_5mm_mm2``.
            Values are None when nothing was measured.
        """
        d = self.distance
        ok = np.isfinite(d)
        total = float(self.area.sum())
        out: dict[str, Any] = {
            "vertices": int(d.size),
            "measured": int(ok.sum()),
            "overlap": float(self.area[ok].sum() / total) if total > 0 else 0.0,
        }
        if not ok.any():
            return out | dict.fromkeys(
                ("rms_mm", "mean_mm", "max_abs_mm", "max_abs_at", "area_mm2"), None
            )
        w = self.area[ok]
        v = d[ok]
        k = int(np.argmax(np.abs(v)))
        out |= {
            "rms_mm": float(np.sqrt(np.average(v * v, weights=w))) if w.sum() > 0 else None,
            "mean_mm": float(np.average(v, weights=w)) if w.sum() > 0 else None,
            "max_abs_mm": float(v[k]),
            "max_abs_at": [float(c) for c in self.vertices[ok][k]],
            "area_mm2": float(w.sum()),
        }
        for limit in (2, 5):
            out[f"area_above_{limit}mm_mm2"] = float(w[v > limit].sum())
            out[f"area_below_minus_{limit}mm_mm2"] = float(w[v < -limit].sum())
        return out


def _angle(rotation: np.ndarray) -> float:
    """Rotation angle of a 3×3 rotation matrix, degrees."""
    cos = (float(np.trace(rotation)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def vertex_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """A third of the area of every triangle around each vertex (mm²), ``(N,)``."""
    area = np.zeros(len(vertices))
    if len(triangles):
        a, b, c = (vertices[triangles[:, k]] for k in range(3))
        each = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1) / 3.0
        for k in range(3):
            np.add.at(area, triangles[:, k], each)
    return area


def _frame(shape: BackShape | BodyFrame, label: str) -> tuple[np.ndarray, np.ndarray]:
    origin, axes = shape.frame_origin, shape.frame_axes
    if shape.reason or not (np.all(np.isfinite(origin)) and np.all(np.isfinite(axes))):
        missing = [n for n in ("VP", "DL", "DR") if shape.landmark(n) is None]
        why = shape.reason or (
            f"landmark {', '.join(missing)} not found" if missing else "degenerate landmarks"
        )
        details = shape.reason_table()
        extra = "; ".join(f"{n}: {details[n]}" for n in missing if n in details)
        raise ComparisonRefusedError(
            f"visit {label or '?'} has no body-fixed frame ({why}{'; ' + extra if extra else ''})"
        )
    return np.asarray(origin, dtype=float), np.asarray(axes, dtype=float)


def landmark_transform(
    a: BackShape | BodyFrame, b: BackShape | BodyFrame, *, labels: tuple[str, str] = ("A", "B")
) -> np.ndarray:
    """The rigid transform putting B's body-fixed frame onto A's.

    A point with body-frame coordinates ``l`` is ``o + Axesᵀ l`` in each world frame, so
    ``p_a = A_axesᵀ B_axes (p_b − o_b) + o_a``.

    Parameters
    ----------
    a, b : BackShape
        The analyses of visits A and B.
    labels : (str, str), optional
        Names of the visits in messages.

    Returns
    -------
    numpy.ndarray
        ``(4, 4)`` homogeneous transform from B's world frame to A's.

    Raises
    ------
    ComparisonRefusedError
        When either visit has no body frame (VP, DL or DR not found), saying which.
    """
    oa, ra = _frame(a, labels[0])
    ob, rb = _frame(b, labels[1])
    rotation = ra.T @ rb
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = oa - rotation @ ob
    return out


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def trunk_mask(visit: Visit, points: np.ndarray, *, margin: float = EDGE_MARGIN) -> np.ndarray:
    """Which of ``points`` (world mm) lie on the visit's trunk.

    The trunk is the part of the measured surface between DM and VP along the body frame's
    vertical axis (the head and neck above VP, the buttocks below DM left out), at least
    ``margin`` inside the measured outline (the outline eroded), and in the connected piece
    of it that holds the VP–DM line's midpoint (arms measured apart from the trunk left out).

    Parameters
    ----------
    visit : Visit
        The visit (surface and analysis).
    points : numpy.ndarray
        ``(N, 3)`` points in the visit's world frame.
    margin : float, optional
        Erosion of the outline, mm.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool.
    """
    from scipy import ndimage

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    surface = visit.surface
    if surface.z.size == 0 or len(points) == 0:
        return np.zeros(len(points), dtype=bool)
    origin, axes = _frame(visit.shape, visit.label)
    vp = visit.shape.landmark("VP")
    assert vp is not None  # the frame exists, so VP does
    height = float((vp - origin) @ axes[1])
    local = (points - origin) @ axes.T
    inside = (local[:, 1] >= 0.0) & (local[:, 1] <= height)
    steps = max(1, round(margin / surface.spacing))
    eroded = ndimage.binary_erosion(surface.valid, iterations=steps, border_value=0)
    labels, _count = ndimage.label(eroded)
    ny, nx = surface.shape

    def cells(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        j = np.rint((p[:, 0] - surface.x0) / surface.spacing).astype(np.int64)
        i = np.rint((p[:, 1] - surface.y0) / surface.spacing).astype(np.int64)
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        return np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1), ok

    mid = 0.5 * (vp + origin)
    mi, mj, mok = cells(mid[None, :])
    piece = labels[mi[0], mj[0]] if mok[0] else 0
    i, j, ok = cells(points)
    on = ok & (labels[i, j] == piece) if piece else ok & eroded[i, j]
    return inside & on


def _submesh(mesh: MeshRecord, keep: np.ndarray) -> MeshRecord:
    """The vertices ``keep`` and the triangles whose three corners are kept, renumbered."""
    index = np.full(len(mesh.vertices), -1, dtype=np.int64)
    index[keep] = np.arange(int(keep.sum()))
    tri = mesh.triangles[np.all(keep[mesh.triangles], axis=1)]
    return MeshRecord(
        vertices=np.array(mesh.vertices[keep]),
        triangles=index[tri].astype(np.int32),
        normals=np.array(mesh.normals[keep]),
    )


def trunk_mesh(visit: Visit, *, margin: float = EDGE_MARGIN) -> MeshRecord:
    """The part of the visit's mesh on its trunk (:func:`trunk_mask`)."""
    return _submesh(visit.mesh, trunk_mask(visit, visit.mesh.vertices, margin=margin))


def _cloud(points: np.ndarray, normals: np.ndarray | None = None) -> Any:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, dtype=np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.array(normals, dtype=np.float64))
    return cloud


def _icp(
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
    src = _cloud(source.vertices)
    if thresholds.voxel:
        # tens of thousands of trunk points say no more about six degrees of freedom than a
        # few thousand; ICP's cost is in the source's nearest-neighbour searches
        src = src.voxel_down_sample(thresholds.voxel)
    dst = _cloud(target.vertices, target.normals)
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
    start = landmark_transform(a.shape, b.shape, labels=(a.label, b.label))
    target = trunk_mesh(a, margin=margin)
    source = trunk_mesh(b, margin=margin)
    for visit, part in ((a, target), (b, source)):
        if len(part.vertices) < thresholds.min_points:
            raise ComparisonRefusedError(
                f"visit {visit.label or '?'} has too little measured trunk to register "
                f"({len(part.vertices)} points between DM and VP, at least "
                f"{thresholds.min_points} needed)"
            )
    transform, fitness, rmse = _icp(source, target, start, thresholds)
    centre = source.vertices.mean(axis=0)
    shift = float(
        np.linalg.norm(_apply(transform, centre[None])[0] - _apply(start, centre[None])[0])
    )
    turn = _angle(transform[:3, :3] @ start[:3, :3].T)
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
    return Registration(transform, start, fitness, rmse, len(source.vertices))


def _signed_distances(
    vertices: np.ndarray, normals: np.ndarray, mesh: MeshRecord, *, limit: float
) -> np.ndarray:
    """Signed distance along each normal to ``mesh`` (the nearer hit forward or backward)."""
    import open3d as o3d

    out = np.full(len(vertices), np.nan)
    if len(vertices) == 0 or len(mesh.triangles) == 0:
        return out
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
    )
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    rays = np.concatenate([np.hstack([vertices, n]), np.hstack([vertices, -n])]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    ahead, behind = hit[: len(vertices)], hit[len(vertices) :]
    signed = np.where(ahead <= behind, ahead, -behind)
    ok = np.isfinite(signed) & (np.abs(signed) <= limit)
    out[ok] = signed[ok]
    return out


def distance_map(
    a: Visit,
    b: Visit,
    registration: Registration,
    *,
    margin: float = EDGE_MARGIN,
    limit: float = MAX_DISTANCE,
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

    Returns
    -------
    DistanceMap
        On A's trunk mesh; positive where B is posterior of A (along A's normal, which faces
        the camera).
    """
    trunk = trunk_mesh(a, margin=margin)
    moved = MeshRecord(
        vertices=_apply(registration.transform, np.asarray(b.mesh.vertices, dtype=float)),
        triangles=b.mesh.triangles,
        normals=np.asarray(b.mesh.normals) @ registration.transform[:3, :3].T,
    )
    distance = _signed_distances(trunk.vertices, trunk.normals, moved, limit=limit)
    return DistanceMap(trunk.vertices, trunk.triangles, trunk.normals, distance)


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
        As for :func:`register` and :func:`distance_map`.

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
    origin, axes = _frame(visit.shape, visit.label)
    across = axes[0]
    reflect = np.eye(4)
    reflect[:3, :3] -= 2.0 * np.outer(across, across)
    reflect[:3, 3] = 2.0 * (origin @ across) * across
    mesh = visit.mesh
    mirrored = MeshRecord(
        vertices=_apply(reflect, np.asarray(mesh.vertices, dtype=float)),
        triangles=np.ascontiguousarray(mesh.triangles[:, ::-1]),  # a mirror turns the winding
        normals=np.asarray(mesh.normals) @ reflect[:3, :3].T,
    )
    trunk = trunk_mesh(visit, margin=margin)
    if len(trunk.vertices) < thresholds.min_points:
        raise ComparisonRefusedError(
            f"visit {visit.label or '?'} has too little measured trunk for an asymmetry map "
            f"({len(trunk.vertices)} points, at least {thresholds.min_points} needed)"
        )
    mirror_trunk = _submesh(mirrored, trunk_mask(visit, mesh.vertices, margin=margin))
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
    transform, fitness, rmse = _icp(
        mirror_trunk, trunk, np.eye(4), mirror, judge=thresholds.coarse_distance
    )
    turn, shift = _angle(transform[:3, :3]), float(np.linalg.norm(transform[:3, 3]))
    if fitness < thresholds.min_fitness or shift > thresholds.max_shift:
        raise ComparisonRefusedError(
            f"the mirror image of visit {visit.label or '?'} could not be fitted onto it "
            f"(overlap {fitness:.0%}, residual {rmse:.1f} mm, moved {shift:.0f} mm / "
            f"{turn:.1f}°)"
        )
    fitted = MeshRecord(
        vertices=_apply(transform, mirrored.vertices),
        triangles=mirrored.triangles,
        normals=mirrored.normals @ transform[:3, :3].T,
    )
    # the distance runs from the back to its mirror; the back lying out of it is the negative
    distance = -_signed_distances(trunk.vertices, trunk.normals, fitted, limit=limit)
    amap = DistanceMap(
        trunk.vertices, trunk.triangles, trunk.normals, distance, what="asymmetry (mm)"
    )
    return amap, transform, fitness, rmse


def asymmetry_change(
    a_map: DistanceMap, b_map: DistanceMap, registration: Registration, *, reach: float = 3.0
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

    Returns
    -------
    DistanceMap
        On A's trunk; positive where the asymmetry grew towards the posterior.
    """
    from scipy.spatial import cKDTree

    moved = _apply(registration.transform, b_map.vertices)
    change = np.full(len(a_map.vertices), np.nan)
    if len(moved):
        gap, index = cKDTree(moved).query(a_map.vertices, distance_upper_bound=reach)
        near = np.isfinite(gap)
        change[near] = b_map.distance[index[near]] - a_map.distance[near]
    return DistanceMap(
        a_map.vertices, a_map.triangles, a_map.normals, change, what="asymmetry change (mm)"
    )
