"""Simple analytic surfaces for unit tests: plane, sphere, cylinder and step.

Every scene carries the exact analytic surface in ``metadata`` (``kind`` plus its
parameters), so a test can measure a reconstruction against the true surface with
:func:`surface_distance` instead of against the triangulation. The meshes are fine enough
that the triangulation differs from the analytic surface by less than ``max_error``
(0.005 mm by default) where the camera sees it: planes are exact with two triangles, curved
shapes are sampled so that the chord sagitta ``h**2 / (8 R)`` stays below ``max_error``.

All surfaces face the camera (normals towards −Z) in the world frame of
:mod:`rasterserver.simulator.scene`; curved shapes are meshed only on the side that the
camera and the projector see (polar angles up to 100° from −Z), which keeps them small.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
import open3d as o3d

from rasterserver.errors import InputError
from rasterserver.simulator.scene import Scene, SceneObject

__all__ = ["cylinder", "plane", "sphere", "step", "surface_distance", "tilted_plane"]

_DEFAULT_ALBEDO = 0.8


def _vector(name: str, value: Sequence[float] | np.ndarray, size: int = 3) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be {size} finite numbers, got {value!r}")
    return arr


def _positive(name: str, value: float, *, upper: float = 1e5) -> float:
    value = float(value)
    if not (math.isfinite(value) and 0.0 < value <= upper):
        raise InputError(f"{name} must be a positive number up to {upper:g}, got {value!r}")
    return value


def _albedo(value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise InputError(f"albedo must lie in [0, 1], got {value!r}")
    return value


def _mesh(vertices: np.ndarray, triangles: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Mesh with normals; triangles are flipped if needed so the normals face −Z (camera)."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(triangles, dtype=np.int32)),
    )
    mesh.compute_triangle_normals()
    if np.asarray(mesh.triangle_normals)[:, 2].sum() > 0:
        mesh.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(triangles[:, ::-1]))
    mesh.compute_vertex_normals()
    return mesh


def _grid_triangles(rows: int, cols: int) -> np.ndarray:
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def _rectangle(centre: np.ndarray, u: np.ndarray, v: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Two triangles spanning ``centre ± u ± v``."""
    corners = np.array([centre - u - v, centre + u - v, centre + u + v, centre - u + v])
    return _mesh(corners, np.array([[0, 1, 2], [0, 2, 3]]))


def _chord_spacing(radius: float, max_error: float) -> float:
    # Sagitta of a chord of length h on a circle of radius R is h**2 / (8 R).
    return math.sqrt(8.0 * radius * max_error)


def plane(
    *,
    point: Sequence[float] = (0.0, 0.0, 0.0),
    normal: Sequence[float] | np.ndarray = (0.0, 0.0, -1.0),
    size: tuple[float, float] = (1000.0, 1000.0),
    albedo: float = _DEFAULT_ALBEDO,
) -> Scene:
    """A flat rectangle through ``point`` with unit ``normal``, exact with two triangles.

    Parameters
    ----------
    point : sequence of 3 float
        A point of the plane and the rectangle's centre (mm).
    normal : sequence of 3 float
        Plane normal; it is normalised and turned to face the camera (−Z). Planes seen
        edge-on (``|n_z| < 0.1`` after normalising, tilts beyond ~84°) are refused.
    size : (float, float)
        Extent of the rectangle along its in-plane axes (mm); the first axis is the
        projection of world X into the plane.
    albedo : float
        Diffuse reflectance.

    Returns
    -------
    Scene
        One object ``"plane"``; metadata ``{"kind": "plane", "point", "normal", "size"}``.
    """
    p = _vector("point", point)
    n = _vector("normal", normal)
    norm = float(np.linalg.norm(n))
    if norm == 0.0:
        raise InputError("normal must not be zero")
    n = n / norm
    if n[2] > 0:
        n = -n
    if abs(n[2]) < 0.1:
        raise InputError(f"the plane is seen edge-on (normal {n.round(3).tolist()})")
    w, h = (_positive("size", s) for s in size)
    u = np.array([1.0, 0.0, 0.0]) - n[0] * n
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    if v[1] < 0:
        v = -v
    mesh = _rectangle(p, u * w / 2, v * h / 2)
    return Scene(
        objects=[SceneObject("plane", mesh, _albedo(albedo))],
        landmarks={"point": p.copy()},
        metadata={"kind": "plane", "point": p.tolist(), "normal": n.tolist(), "size": [w, h]},
    )


def tilted_plane(
    z0: float = 0.0,
    *,
    tilt_x: float = 0.0,
    tilt_y: float = 0.0,
    size: tuple[float, float] = (1000.0, 1000.0),
    albedo: float = _DEFAULT_ALBEDO,
) -> Scene:
    """A plane through ``(0, 0, z0)`` tilted by angles about the world X and Y axes.

    Parameters
    ----------
    z0 : float
        Depth of the plane on the optical axis (mm).
    tilt_x : float
        Rotation about the X axis, degrees; positive turns the upper part (−Y) away from the
        camera (+Z), so the plane faces upwards, towards the projector.
    tilt_y : float
        Rotation about the Y axis, degrees; positive turns the right part (+X) away from the
        camera.
    size : (float, float)
        Extent of the rectangle (mm).
    albedo : float
        Diffuse reflectance.

    Returns
    -------
    Scene
        As :func:`plane`; the metadata also holds ``tilt_x`` and ``tilt_y``.
    """
    ax, ay = math.radians(float(tilt_x)), math.radians(float(tilt_y))
    if not (abs(tilt_x) < 80.0 and abs(tilt_y) < 80.0):
        raise InputError(f"tilts must be below 80°, got {tilt_x}, {tilt_y}")
    # Depth grows along the tilted directions: z = z0 + x tan(ay) - y tan(ax).
    n = np.array([-math.tan(ay), math.tan(ax), 1.0])
    scene = plane(point=(0.0, 0.0, float(z0)), normal=-n, size=size, albedo=albedo)
    meta = dict(scene.metadata) | {"tilt_x": float(tilt_x), "tilt_y": float(tilt_y)}
    return Scene(scene.objects, scene.landmarks, meta)


def sphere(
    *,
    centre: Sequence[float] = (0.0, 0.0, 150.0),
    radius: float = 150.0,
    albedo: float = _DEFAULT_ALBEDO,
    max_error: float = 0.005,
) -> Scene:
    """The camera-facing part of a sphere (polar angles up to 100° from −Z).

    Parameters
    ----------
    centre : sequence of 3 float
        Centre (mm); the default puts the front pole at the origin.
    radius : float
        Radius (mm).
    albedo : float
        Diffuse reflectance.
    max_error : float
        Largest distance between the mesh and the sphere (mm), in (0, 1].

    Returns
    -------
    Scene
        One object ``"sphere"``; landmark ``"pole"`` (the point nearest the camera);
        metadata ``{"kind": "sphere", "centre", "radius", "max_error"}``.
    """
    c = _vector("centre", centre)
    r = _positive("radius", radius)
    err = _positive("max_error", max_error, upper=1.0)
    # A quad cell split in two has triangles of circumradius h / sqrt(2), which sag by
    # h**2 / (4 R) at most: half the spacing of a single chord's budget.
    h = _chord_spacing(r, err / 2.0)
    polar_max = math.radians(100.0)
    n_polar = max(math.ceil(r * polar_max / h), 8)
    n_azimuth = max(math.ceil(2 * math.pi * r / h), 16)
    # Rings of constant polar angle around the −Z axis, densest sampling h along both
    # directions at the rim; the pole is one vertex.
    polar = np.linspace(0.0, polar_max, n_polar + 1)[1:]
    azimuth = np.linspace(0.0, 2 * np.pi, n_azimuth, endpoint=False)
    pp, aa = np.meshgrid(polar, azimuth, indexing="ij")
    direction = np.stack([np.sin(pp) * np.cos(aa), np.sin(pp) * np.sin(aa), -np.cos(pp)], -1)
    pole = c + np.array([0.0, 0.0, -r])
    verts = np.concatenate([pole[None], (c + r * direction).reshape(-1, 3)])
    ring = np.arange(n_polar * n_azimuth).reshape(n_polar, n_azimuth) + 1
    nxt = np.roll(ring, -1, axis=1)
    tris = [
        np.stack([np.zeros(n_azimuth, int), ring[0], nxt[0]], 1),
        np.stack([ring[:-1].ravel(), ring[1:].ravel(), nxt[:-1].ravel()], 1),
        np.stack([nxt[:-1].ravel(), ring[1:].ravel(), nxt[1:].ravel()], 1),
    ]
    triangles = np.concatenate(tris)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(triangles.astype(np.int32))
    )
    # Outward normals: flip the winding if the first triangle's normal points inwards.
    mesh.compute_triangle_normals()
    centroid = verts[triangles].mean(1)
    if (np.asarray(mesh.triangle_normals) * (centroid - c)).sum() < 0:
        mesh.triangles = o3d.utility.Vector3iVector(triangles[:, ::-1].astype(np.int32))
    mesh.compute_vertex_normals()
    return Scene(
        objects=[SceneObject("sphere", mesh, _albedo(albedo))],
        landmarks={"pole": pole, "centre": c.copy()},
        metadata={"kind": "sphere", "centre": c.tolist(), "radius": r, "max_error": err},
    )


def cylinder(
    *,
    axis: Literal["vertical", "horizontal"] = "vertical",
    centre: Sequence[float] = (0.0, 0.0, 150.0),
    radius: float = 150.0,
    length: float = 800.0,
    albedo: float = _DEFAULT_ALBEDO,
    max_error: float = 0.005,
) -> Scene:
    """The camera-facing half (±100° from −Z) of a circular cylinder.

    Parameters
    ----------
    axis : {"vertical", "horizontal"}
        Axis along world Y (vertical) or X (horizontal).
    centre : sequence of 3 float
        A point on the axis, the middle of the cylinder's length (mm).
    radius : float
        Radius (mm).
    length : float
        Length along the axis (mm).
    albedo : float
        Diffuse reflectance.
    max_error : float
        Largest distance between mesh and cylinder (mm); the generators are straight, so only
        the angular sampling contributes.

    Returns
    -------
    Scene
        One object ``"cylinder"``; metadata ``{"kind": "cylinder", "axis_direction",
        "centre", "radius", "length", "max_error"}``.
    """
    if axis not in ("vertical", "horizontal"):
        raise InputError(f"axis must be 'vertical' or 'horizontal', got {axis!r}")
    c = _vector("centre", centre)
    r = _positive("radius", radius)
    ln = _positive("length", length)
    err = _positive("max_error", max_error, upper=1.0)
    h = _chord_spacing(r, err)
    span = math.radians(100.0)
    n_angle = max(math.ceil(2 * span * r / h), 8) + 1
    n_along = max(math.ceil(ln / 25.0), 1) + 1
    ang = np.linspace(-span, span, n_angle)
    along = np.linspace(-ln / 2, ln / 2, n_along)
    aa, ll = np.meshgrid(ang, along, indexing="ij")
    across = r * np.sin(aa)
    depth = -r * np.cos(aa)
    if axis == "vertical":
        direction = np.array([0.0, 1.0, 0.0])
        pts = np.stack([across, ll, depth], -1)
    else:
        direction = np.array([1.0, 0.0, 0.0])
        pts = np.stack([ll, across, depth], -1)
    mesh = _mesh((pts + c).reshape(-1, 3), _grid_triangles(n_angle, n_along))
    return Scene(
        objects=[SceneObject("cylinder", mesh, _albedo(albedo))],
        landmarks={"centre": c.copy()},
        metadata={
            "kind": "cylinder",
            "axis_direction": direction.tolist(),
            "centre": c.tolist(),
            "radius": r,
            "length": ln,
            "max_error": err,
        },
    )


def step(
    *,
    z_near: float = -50.0,
    z_far: float = 50.0,
    edge: float = 0.0,
    orientation: Literal["horizontal", "vertical"] = "horizontal",
    size: tuple[float, float] = (1000.0, 1000.0),
    albedo: float = _DEFAULT_ALBEDO,
) -> Scene:
    """Two fronto-parallel planes at different depths meeting at a sharp edge.

    With a horizontal edge the upper part (``y < edge``) lies at ``z_near`` and the lower
    part at ``z_far``, joined by a riser in the plane ``y = edge``: with ``z_near < z_far``
    the projector, which sits above the camera, casts the riser's shadow onto the lower
    part. With a vertical edge the left part (``x < edge``) is near and the right part far.

    Parameters
    ----------
    z_near, z_far : float
        Depths of the two parts (mm); they must differ.
    edge : float
        Position of the edge (Y for horizontal, X for vertical), mm.
    orientation : {"horizontal", "vertical"}
        Direction of the edge line.
    size : (float, float)
        Total extent along X and Y (mm), centred on the optical axis.
    albedo : float
        Diffuse reflectance.

    Returns
    -------
    Scene
        Objects ``"near"``, ``"far"`` and ``"riser"``; metadata ``{"kind": "step", ...}``.
    """
    if orientation not in ("horizontal", "vertical"):
        raise InputError(f"orientation must be 'horizontal' or 'vertical', got {orientation!r}")
    zn, zf, e = (float(v) for v in (z_near, z_far, edge))
    if not all(math.isfinite(v) for v in (zn, zf, e)) or zn == zf:
        raise InputError(f"z_near and z_far must be finite and differ, got {zn}, {zf}")
    w, h = (_positive("size", s) for s in size)
    a = _albedo(albedo)
    k = 1 if orientation == "horizontal" else 0  # the coordinate the edge cuts
    half = (w / 2, h / 2)[k]
    if not -half < e < half:
        raise InputError(f"edge {e} lies outside the step's extent ±{half}")
    lo, hi = -half, half
    other = (h / 2, w / 2)[k]

    def part(start: float, stop: float, z: float) -> o3d.geometry.TriangleMesh:
        centre = np.zeros(3)
        centre[k], centre[2] = (start + stop) / 2, z
        u, v = np.zeros(3), np.zeros(3)
        u[1 - k], v[k] = other, (stop - start) / 2
        return _rectangle(centre, u, v)

    riser_verts = np.zeros((4, 3))
    riser_verts[:, k] = e
    riser_verts[:, 1 - k] = [-other, other, other, -other]
    riser_verts[:, 2] = [zn, zn, zf, zf]
    riser = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(riser_verts),
        o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)),
    )
    riser.compute_vertex_normals()
    return Scene(
        objects=[
            SceneObject("near", part(lo, e, zn), a),
            SceneObject("far", part(e, hi, zf), a),
            SceneObject("riser", riser, a),
        ],
        metadata={
            "kind": "step",
            "orientation": orientation,
            "edge": e,
            "z_near": zn,
            "z_far": zf,
            "size": [w, h],
        },
    )


def surface_distance(metadata: Mapping[str, Any] | Scene, points: np.ndarray) -> np.ndarray:
    """Signed distance (mm) from points to the exact analytic surface of a shape scene.

    Positive means in front of the surface (on the camera's side) for planes and steps,
    outside for spheres and cylinders (the cylinder as an infinite one).

    Parameters
    ----------
    metadata : Mapping or Scene
        A shape scene or its metadata, as made by this module.
    points : numpy.ndarray
        ``(N, 3)`` world points (mm).

    Returns
    -------
    numpy.ndarray
        ``(N,)`` distances.
    """
    meta = metadata.metadata if isinstance(metadata, Scene) else metadata
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    kind = meta.get("kind")
    if kind == "plane":
        n = np.asarray(meta["normal"])
        return (pts - np.asarray(meta["point"])) @ n
    if kind == "sphere":
        return np.linalg.norm(pts - np.asarray(meta["centre"]), axis=1) - meta["radius"]
    if kind == "cylinder":
        d = pts - np.asarray(meta["centre"])
        axis = np.asarray(meta["axis_direction"])
        radial = d - np.outer(d @ axis, axis)
        return np.linalg.norm(radial, axis=1) - meta["radius"]
    if kind == "step":
        k = 1 if meta["orientation"] == "horizontal" else 0
        z = np.where(pts[:, k] < meta["edge"], meta["z_near"], meta["z_far"])
        return z - pts[:, 2]
    raise InputError(f"no analytic surface for scene kind {kind!r}")
