"""Analytic test shapes: exact surfaces, fine meshes, camera-facing normals, bad input."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from rasterserver.errors import InputError
from rasterserver.simulator import shapes
from rasterserver.simulator.scene import Scene

CAMERA = np.array([0.0, 0.0, -2000.0])


def _camera_hits(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """World points where camera rays towards (x, y, 0) first hit the scene (NaN: miss)."""
    rs = o3d.t.geometry.RaycastingScene()
    for obj in scene.objects:
        rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    target = np.column_stack([xy, np.zeros(len(xy))])
    d = target - CAMERA
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.hstack([np.broadcast_to(CAMERA, d.shape), d])
    t = rs.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    return CAMERA + d * t[:, None]


def _grid(extent: float, n: int = 41) -> np.ndarray:
    g = np.linspace(-extent, extent, n)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def _triangle_sag(scene: Scene) -> float:
    """Largest distance of triangle centroids and edge midpoints from the analytic surface."""
    mesh = scene.objects[0].mesh
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    probes = np.vstack([v[t].mean(1), (v[t[:, 0]] + v[t[:, 1]]) / 2, (v[t[:, 1]] + v[t[:, 2]]) / 2])
    return float(np.abs(shapes.surface_distance(scene, probes)).max())


def test_plane_is_exact_with_two_triangles() -> None:
    scene = shapes.plane(point=(10.0, -5.0, 30.0), normal=(0.2, -0.1, 1.0))
    mesh = scene.objects[0].mesh
    assert len(mesh.triangles) == 2
    n = np.asarray(scene.metadata["normal"])
    assert n[2] < 0 and np.linalg.norm(n) == pytest.approx(1.0)
    assert np.abs(shapes.surface_distance(scene, np.asarray(mesh.vertices))).max() < 1e-9
    assert (np.asarray(mesh.vertex_normals)[:, 2] < 0).all()
    hits = _camera_hits(scene, _grid(250.0))
    assert np.abs(shapes.surface_distance(scene, hits)).max() < 1e-3
    json.dumps(scene.metadata)


def test_tilted_plane_depth() -> None:
    scene = shapes.tilted_plane(20.0, tilt_x=15.0, tilt_y=-10.0)
    hits = _camera_hits(scene, _grid(250.0))
    expected = 20.0 + hits[:, 0] * np.tan(np.radians(-10.0)) - hits[:, 1] * np.tan(np.radians(15))
    np.testing.assert_allclose(hits[:, 2], expected, atol=1e-3)
    # positive tilt_x turns the upper part away from the camera
    upper = (hits[:, 1] < -100) & (np.abs(hits[:, 0]) < 20)
    assert upper.any() and hits[upper, 2].min() > 20.0


def test_sphere_triangulation_error_is_small() -> None:
    scene = shapes.sphere(centre=(0.0, 0.0, 100.0), radius=120.0)
    assert _triangle_sag(scene) < 0.01
    hits = _camera_hits(scene, _grid(100.0))
    ok = np.isfinite(hits[:, 2])
    assert ok.sum() > 800
    assert np.abs(shapes.surface_distance(scene, hits[ok])).max() < 0.01
    np.testing.assert_allclose(scene.landmarks["pole"], [0.0, 0.0, -20.0])
    v = np.asarray(scene.objects[0].mesh.vertices)
    n = np.asarray(scene.objects[0].mesh.vertex_normals)
    assert ((n * (v - [0.0, 0.0, 100.0])).sum(1) > 0).all()  # outwards


@pytest.mark.parametrize("axis", ["vertical", "horizontal"])
def test_cylinder(axis: str) -> None:
    scene = shapes.cylinder(axis=axis, centre=(0.0, 0.0, 80.0), radius=80.0, length=500.0)
    assert _triangle_sag(scene) < 0.01
    hits = _camera_hits(scene, _grid(70.0))
    assert np.isfinite(hits).all()
    assert np.abs(shapes.surface_distance(scene, hits)).max() < 0.01
    across = hits[:, 0] if axis == "vertical" else hits[:, 1]
    # the depth varies across the axis only
    np.testing.assert_allclose(hits[:, 2], 80.0 - np.sqrt(80.0**2 - across**2), atol=0.05)


@pytest.mark.parametrize("orientation", ["horizontal", "vertical"])
def test_step(orientation: str) -> None:
    scene = shapes.step(z_near=-40.0, z_far=60.0, edge=10.0, orientation=orientation)
    assert [o.name for o in scene.objects] == ["near", "far", "riser"]
    hits = _camera_hits(scene, _grid(200.0))
    k = 1 if orientation == "horizontal" else 0
    clear = np.abs(hits[:, k] - 10.0) > 15.0  # away from the edge and its riser
    assert np.abs(shapes.surface_distance(scene, hits[clear])).max() < 1e-3
    assert set(np.round(hits[clear, 2]).tolist()) == {-40.0, 60.0}


def test_surface_distance_sign() -> None:
    scene = shapes.sphere(radius=50.0, centre=(0.0, 0.0, 50.0))
    assert shapes.surface_distance(scene, np.array([[0.0, 0.0, -10.0]]))[0] == pytest.approx(10.0)
    plane = shapes.plane()
    assert shapes.surface_distance(plane, np.array([[0.0, 0.0, -3.0]]))[0] == pytest.approx(3.0)
    with pytest.raises(InputError):
        shapes.surface_distance({"kind": "torus"}, np.zeros((1, 3)))


@pytest.mark.parametrize(
    "make",
    [
        lambda: shapes.plane(normal=(1.0, 0.0, 0.0)),
        lambda: shapes.plane(normal=(0.0, 0.0, 0.0)),
        lambda: shapes.plane(point=(0.0, 0.0)),
        lambda: shapes.plane(size=(-1.0, 10.0)),
        lambda: shapes.plane(albedo=1.5),
        lambda: shapes.tilted_plane(tilt_x=85.0),
        lambda: shapes.sphere(radius=-3.0),
        lambda: shapes.sphere(radius=float("nan")),
        lambda: shapes.sphere(max_error=0.0),
        lambda: shapes.cylinder(axis="diagonal"),
        lambda: shapes.cylinder(length=0.0),
        lambda: shapes.step(z_near=5.0, z_far=5.0),
        lambda: shapes.step(edge=900.0),
        lambda: shapes.step(orientation="oblique"),
    ],
)
def test_bad_shapes_are_refused(make) -> None:
    with pytest.raises(InputError):
        make()
