"""Camera and projector geometry: projection, rays, light-surface intersection, calibration JSON."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from rasterserver.documents import calibration_from_document, load_calibration_document
from rasterserver.errors import InputError
from rasterserver.optics import (
    CALIBRATION_FORMAT,
    Camera,
    Projector,
    Station,
    default_station,
    distort_normalized,
    rotation_matrix,
    undistort_normalized,
)
from rasterserver.raster import default_raster


def _random_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(-280, 280, n), rng.uniform(-290, 290, n), rng.uniform(-250, 250, n)]
    )


def _tilted_camera(skew: float = 0.5) -> Camera:
    rot = rotation_matrix(2.0, -3.0, 1.0)
    centre = np.array([15.0, -20.0, -1990.0])
    return Camera(
        K=np.array([[2010.0, skew, 290.0], [0.0, 1995.0, 300.0], [0.0, 0.0, 1.0]]),
        dist=np.array([-0.08, 0.05, 0.001, -0.0015, 0.01]),
        R=rot,
        t=-rot @ centre,
        width=576,
        height=604,
    )


def test_default_station_geometry() -> None:
    st = default_station()
    cam, proj = st.camera, st.projector
    np.testing.assert_allclose(cam.centre, [0, 0, -2000])
    np.testing.assert_allclose(proj.centre, [0, -800, -2000])
    assert cam.K[0, 0] == pytest.approx(2000.0)
    assert cam.shape == (604, 576)
    assert st.base == pytest.approx(800.0)
    # one diapositive unit is ~1 mm at Z = 0; world origin near the diapositive centre
    uv = proj.diapositive_coordinates(np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]]))
    assert abs(uv[0, 1] - 499.5) < 5
    assert uv[1, 1] - uv[0, 1] == pytest.approx(10.0, rel=0.02)
    # the field of view is covered by the raster at the back's depth range
    big = default_station(2048, 2448)
    assert big.camera.K[0, 0] == pytest.approx(2000 * 2048 / 576)


def test_project_matches_opencv() -> None:
    cam = _tilted_camera(skew=0.0)  # cv2.projectPoints ignores skew
    pts = _random_points(2000)
    ours = cam.project(pts)
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-7)


def test_points_behind_are_nan() -> None:
    cam = default_station().camera
    uv = cam.project(np.array([[0.0, 0.0, -2500.0], [0.0, 0.0, 0.0]]))
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


@pytest.mark.parametrize("tilted", [False, True])
def test_project_rays_round_trip(tilted: bool) -> None:
    cam = _tilted_camera() if tilted else default_station().camera
    rng = np.random.default_rng(1)
    px = np.column_stack([rng.uniform(-0.5, 575.5, 5000), rng.uniform(-0.5, 603.5, 5000)])
    o, d = cam.rays(px)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(o, np.broadcast_to(cam.centre, o.shape))
    back = cam.project(o + 1234.5 * d)
    assert np.max(np.abs(back - px)) < 1e-6


def test_undistort_inverts_distort() -> None:
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.3, 0.3, (2, 1000))
    dist = np.array([-0.1, 0.05, 0.002, -0.001, 0.02])
    xd, yd = distort_normalized(x, y, dist)
    xu, yu = undistort_normalized(xd, yd, dist)
    assert np.max(np.abs(xu - x)) < 1e-12 and np.max(np.abs(yu - y)) < 1e-12


@pytest.mark.parametrize("distortion", [(0.0, 0, 0, 0, 0), (-0.02, 0.01, 0.001, -0.0005, 0.0)])
def test_light_surface_intersection(distortion: tuple[float, ...]) -> None:
    st = default_station(projector_distortion=distortion)
    cam, proj = st.camera, st.projector
    rng = np.random.default_rng(3)
    n = 4000
    px = np.column_stack([rng.uniform(0, 575, n), rng.uniform(0, 603, n)])
    o, d = cam.rays(px)
    v = rng.uniform(100, 900, n)
    p = proj.light_surface_intersection(o, d, v)
    ok = np.all(np.isfinite(p), axis=1)
    assert ok.mean() > 0.99
    # on the requested light surface ...
    assert np.max(np.abs(proj.diapositive_coordinates(p[ok])[:, 1] - v[ok])) < 1e-6
    # ... and on the ray
    w = p[ok] - o[ok]
    cross = np.cross(w, d[ok])
    assert np.max(np.linalg.norm(cross, axis=1)) < 1e-8 * np.max(np.linalg.norm(w, axis=1))
    assert np.all(np.einsum("ij,ij->i", w, d[ok]) > 0)


def test_light_surface_scalar_v_and_parallel_ray() -> None:
    proj = default_station(projector_distortion=(0, 0, 0, 0, 0)).projector
    o = np.array([[0.0, 0.0, -2000.0], [0.0, -800.0, -2000.0]])
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # second: inside the plane's direction
    p = proj.light_surface_intersection(o, d, 499.5)
    assert p[0, 2] == pytest.approx(0.0, abs=1e-9)
    assert np.all(np.isnan(p[1]))


def test_calibration_json_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    st = Station(
        camera=_tilted_camera(),
        projector=default_station().projector,
        raster=default_raster(),
        name="lab-1",
    )
    text = st.to_json()
    data = json.loads(text)
    assert data["format"] == CALIBRATION_FORMAT
    back = load_calibration_document(text)
    for a, b in [(st.camera, back.camera), (st.projector, back.projector)]:
        for attr in ("K", "dist", "R", "t"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
        assert (a.width, a.height) == (b.width, b.height)
    assert isinstance(back.camera, Camera) and isinstance(back.projector, Projector)
    assert back.name == "lab-1"
    np.testing.assert_array_equal(back.raster_definition.positions, default_raster().positions)
    # by name
    named = load_calibration_document(Path(default_station().save(tmp_path / "calibration.json")))
    assert named.raster == "default"
    assert named.raster_definition.n_lines == default_raster().n_lines


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="rotation"):
        Camera(K=np.eye(3), R=np.diag([1.0, 1.0, -1.0]), width=10, height=10)
    with pytest.raises(InputError, match="format"):
        calibration_from_document({"format": "something/9"})
    with pytest.raises(ValueError, match="shape"):
        default_station().camera.project(np.zeros((4, 2)))


def test_triangulate_recovers_surface_points() -> None:
    st = default_station()
    rng = np.random.default_rng(5)
    pts = np.column_stack(
        [rng.uniform(-250, 250, 500), rng.uniform(-280, 280, 500), rng.uniform(-150, 150, 500)]
    )
    pixels = st.camera.project(pts)
    v = st.projector.diapositive_coordinates(pts)[:, 1]
    back = st.triangulate(pixels, v)
    assert np.max(np.linalg.norm(back - pts, axis=1)) < 1e-6
