"""The renderer against physics: line positions, shadows, noise statistics, determinism.

Every scene here is built inline (planes, boxes, spheres) so these tests do not depend on the
back model. Predictions are analytic (light plane ∩ object plane, projected by the camera
model, which tests/test_optics.py checks against OpenCV), never taken from the renderer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from rasterserver.documents import load_calibration_document
from rasterserver.optics import Station, default_station, rotation_matrix
from rasterserver.simulator.ground_truth import load_ground_truth, save_ground_truth
from rasterserver.simulator.io import write_simulation
from rasterserver.simulator.noise import expected_statistics
from rasterserver.simulator.render import Rendering, RenderSettings, render
from rasterserver.simulator.scene import Scene, SceneObject

NOISE_FREE = RenderSettings(noise=False)


def plane_mesh(
    *, tilt_x: float = 0.0, tilt_y: float = 0.0, z: float = 0.0, size: float = 2000.0, n: int = 21
) -> o3d.geometry.TriangleMesh:
    """A finely triangulated square plane through (0, 0, z), tilted about X then Y (degrees)."""
    s = np.linspace(-size / 2, size / 2, n)
    gx, gy = np.meshgrid(s, s)
    local = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    rot = rotation_matrix(tilt_x, tilt_y, 0.0)
    vertices = local @ rot.T + [0.0, 0.0, z]
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(tris)
    )


def plane_normal(tilt_x: float, tilt_y: float) -> np.ndarray:
    return rotation_matrix(tilt_x, tilt_y, 0.0) @ np.array([0.0, 0.0, 1.0])


def predicted_rows(
    station: Station, normal: np.ndarray, offset: float, columns: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """Row at which line ``v`` crosses pixel column ``c`` on the plane ``normal . X = offset``.

    Valid for a projector without distortion: the light plane meets the object plane in a
    3-D line, which the camera projects; Newton on the line parameter finds ``u = c``.
    """
    cam, proj = station.camera, station.projector
    m, e = proj.light_plane(v)
    direction = np.cross(np.broadcast_to(normal, m.shape), m)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # a point on both planes: least-norm solution of the 2x3 system
    a = np.stack([np.broadcast_to(normal, m.shape), m], axis=1)
    rhs = np.column_stack([np.full(m.shape[0], offset), e])
    x0 = np.einsum("nij,nj->ni", np.linalg.pinv(a), rhs)
    lam = np.zeros(columns.size)
    for _ in range(30):
        p = x0 + lam[:, None] * direction
        uv = cam.project(p)
        duv = (cam.project(p + direction) - cam.project(p - direction)) / 2.0
        step = (uv[:, 0] - columns) / duv[:, 0]
        lam -= step
        if np.max(np.abs(step)) < 1e-12:
            break
    return cam.project(x0 + lam[:, None] * direction)[:, 1]


def centroid_rows(electrons: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """First moment of each peak after subtracting the local background (the seed's method)."""
    h = electrons.shape[0]
    centre = np.rint(rows).astype(int)
    offsets = np.arange(-4, 5)
    rr = centre[:, None] + offsets[None, :]
    window = electrons[np.clip(rr, 0, h - 1), columns[:, None]].astype(np.float64)
    wide = electrons[np.clip(centre[:, None] + np.arange(-5, 6), 0, h - 1), columns[:, None]]
    signal = window - wide.min(axis=1, keepdims=True)
    return (signal * rr).sum(axis=1) / signal.sum(axis=1)


@pytest.fixture(scope="module")
def light_plane_station() -> Station:
    # projector without distortion: light *planes*, as in the closed-form prediction
    return default_station(projector_distortion=(0.0, 0.0, 0.0, 0.0, 0.0))


@pytest.mark.parametrize(("tilt_x", "tilt_y"), [(0.0, 0.0), (25.0, -15.0)])
def test_line_centres_on_plane_match_prediction(
    light_plane_station: Station, tilt_x: float, tilt_y: float
) -> None:
    st = light_plane_station
    scene = Scene([SceneObject("plane", plane_mesh(tilt_x=tilt_x, tilt_y=tilt_y), 0.8)])
    r = render(scene, st, settings=NOISE_FREE, seed=0)
    lr = r.line_rows
    h, w = st.camera.shape
    raster = st.raster_definition
    v = raster.positions[np.searchsorted(raster.numbers, lr.number)]
    normal = plane_normal(tilt_x, tilt_y)
    expected = predicted_rows(st, normal, 0.0, lr.column.astype(float), v)
    # ground truth: every visible line in every column, on the predicted row
    assert len(lr) > 0.9 * w * (h / 10.0) * (0.6 if tilt_x else 1.0)
    assert np.max(np.abs(lr.row - expected)) < 1e-3
    # the rendered image: first-moment peak centres on the predicted row to 0.01 px
    inner = (lr.row > 6) & (lr.row < h - 7)
    measured = centroid_rows(r.electrons, lr.column[inner], lr.row[inner])
    err = measured - expected[inner]
    assert np.max(np.abs(err)) < 0.01, (np.max(np.abs(err)), np.sqrt(np.mean(err**2)))
    # every lit pixel knows its line; lines are numbered along increasing v
    lit = r.line_number >= 0
    assert lit.mean() > 0.9
    j = np.searchsorted(raster.numbers, r.line_number[lit])
    assert np.all(np.abs(r.diapositive[..., 1][lit] - raster.positions[j]) <= 5.0 + 1e-9)
    # ground-truth points lie on the plane
    pts = r.points[r.visible]
    assert np.max(np.abs(pts @ normal)) < 1e-6


def test_line_rows_with_projector_distortion() -> None:
    """With distortion the light surfaces are cones; predict by solving along each column."""
    st = default_station()  # camera and projector distortion
    scene = Scene([SceneObject("plane", plane_mesh(), 0.8)])
    r = render(scene, st, settings=NOISE_FREE, seed=0)
    lr = r.line_rows
    raster = st.raster_definition
    v = raster.positions[np.searchsorted(raster.numbers, lr.number)]

    def v_at(rows: np.ndarray) -> np.ndarray:
        o, d = st.camera.rays(np.column_stack([lr.column.astype(float), rows]))
        p = o + (-o[:, 2] / d[:, 2])[:, None] * d  # the plane Z = 0
        return st.projector.diapositive_coordinates(p)[:, 1]

    rows = np.rint(lr.row)
    for _ in range(20):  # secant-free Newton with a numerical derivative
        dv = (v_at(rows + 1e-3) - v_at(rows - 1e-3)) / 2e-3
        rows = rows - (v_at(rows) - v) / dv
    assert np.max(np.abs(lr.row - rows)) < 1e-3
    h = st.camera.height
    inner = (lr.row > 6) & (lr.row < h - 7)
    measured = centroid_rows(r.electrons, lr.column[inner], lr.row[inner])
    assert np.max(np.abs(measured - rows[inner])) < 0.01


def _box(centre: tuple[float, float, float], size: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate(np.asarray(centre) - np.asarray(size) / 2.0)
    return box


def _segment_hits_box(points: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray):  # type: ignore[no-untyped-def]
    """Slab test: does the segment point → target pass through the axis-aligned box?"""
    d = target[None, :] - points
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo[None, :] - points) / d
        t2 = (hi[None, :] - points) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return (t_near <= t_far) & (t_far > 0) & (t_near < 1)


def test_shadow_behind_occluder() -> None:
    st = default_station()
    centre, size = (0.0, -60.0, -300.0), (120.0, 80.0, 60.0)
    scene = Scene(
        [
            SceneObject("wall", plane_mesh(), 0.8),
            SceneObject("box", _box(centre, size), 0.5),
        ]
    )
    r = render(scene, st, settings=NOISE_FREE, seed=0)
    on_wall = r.object_index == 0
    lo = np.asarray(centre) - np.asarray(size) / 2
    hi = np.asarray(centre) + np.asarray(size) / 2
    expected = _segment_hits_box(r.points[on_wall], st.projector.centre, lo, hi)
    got = r.shadow[on_wall]
    assert expected.sum() > 2000  # a real shadow
    assert np.mean(got == expected) > 0.998
    # the shadow falls below the box (the projector is above the camera), not above it
    shadow_y = r.points[on_wall][got][:, 1]
    assert np.all(shadow_y > hi[1])
    # no raster light in the shadow: only ambient (plus transmission tails below the shadow
    # threshold, < 1e-4 of the projector's light, where no shadow ray is cast), no line there
    amb = 0.8 * NOISE_FREE.ambient_electrons
    core = r.shadow & on_wall
    core_inner = core & np.roll(core, 3, 0) & np.roll(core, -3, 0)
    core_inner &= np.roll(core, 3, 1) & np.roll(core, -3, 1)
    assert core_inner.sum() > 1000
    np.testing.assert_allclose(r.electrons[core_inner], amb, atol=1.0)
    assert np.all(r.line_number[core] == -1)
    in_shadow = r.shadow[np.rint(r.line_rows.row).astype(int), r.line_rows.column]
    assert not np.any(in_shadow & (r.line_rows.object_index == 0))
    # the box itself is seen and lit on its top and front
    assert np.any(r.object_index == 1)


@pytest.mark.parametrize(("bit_depth", "gain", "ambient"), [(16, 0.5, 6000.0), (8, 0.0125, 9000.0)])
def test_noise_statistics(bit_depth: int, gain: float, ambient: float) -> None:
    st = default_station()
    settings = RenderSettings(
        projector_electrons=0.0,  # uniformly lit by ambient light only
        ambient_electrons=ambient,
        camera_blur=0.0,
        supersampling=1,
        bit_depth=bit_depth,
        gain=gain,
        offset=10.0,
        read_noise=15.0,
        line_rows=False,
    )
    r = render(Scene([SceneObject("plane", plane_mesh(), 0.5)]), st, settings=settings, seed=7)
    e = 0.5 * ambient
    np.testing.assert_allclose(r.electrons, e, rtol=1e-5)
    mean, var = expected_statistics(e, gain=gain, offset=10.0, read_noise=15.0)
    img = r.image.astype(np.float64)
    assert img.mean() == pytest.approx(float(mean), rel=0.005)
    assert img.var() == pytest.approx(float(var), rel=0.03)


def test_saturation_and_dtype() -> None:
    st = default_station()
    settings = RenderSettings(projector_electrons=0.0, ambient_electrons=1e6, line_rows=False)
    r = render(Scene([SceneObject("plane", plane_mesh(), 0.5)]), st, settings=settings, seed=1)
    assert r.image.dtype == np.uint8
    assert r.image.max() == min(255, round(settings.gain * settings.full_well + settings.offset))
    assert r.image.min() >= round(settings.gain * settings.full_well + settings.offset) - 6
    r16 = render(
        Scene([SceneObject("plane", plane_mesh(), 0.5)]),
        st,
        settings=settings.replace(bit_depth=12, gain=0.2),
        seed=1,
    )
    assert r16.image.dtype == np.uint16 and r16.image.max() <= 4095


@pytest.fixture(scope="module")
def sphere_scene() -> Scene:
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=150.0, resolution=60)
    sphere.compute_vertex_normals()
    sphere.translate([30.0, 20.0, -100.0])
    return Scene(
        [
            SceneObject("wall", plane_mesh(z=100.0), lambda p: 0.6 + 0.2 * np.cos(p[:, 0] / 50)),
            SceneObject("ball", sphere, 0.7),
        ],
        landmarks={"apex": np.array([30.0, 20.0, -250.0])},
        metadata={"kind": "test", "radius": 150.0},
    )


def test_same_seed_same_image(sphere_scene: Scene) -> None:
    st = default_station()
    a = render(sphere_scene, st, seed=11)
    b = render(sphere_scene, st, seed=11)
    c = render(sphere_scene, st, seed=12)
    assert a.image.tobytes() == b.image.tobytes()
    np.testing.assert_array_equal(a.electrons, b.electrons)
    np.testing.assert_array_equal(a.line_rows.row, b.line_rows.row)
    assert a.image.tobytes() != c.image.tobytes()
    np.testing.assert_array_equal(a.electrons, c.electrons)  # only the noise differs


def test_sphere_ground_truth_consistency(sphere_scene: Scene) -> None:
    st = default_station()
    r = render(sphere_scene, st, settings=NOISE_FREE, seed=0)
    assert set(np.unique(r.object_index)) == {0, 1}
    assert r.object_names == ["wall", "ball"]
    lr = r.line_rows
    assert np.all(np.diff(lr.column) >= 0)
    raster = st.raster_definition
    # re-trace every ground-truth crossing independently of the renderer's samples
    o, d = st.camera.rays(np.column_stack([lr.column.astype(float), lr.row]))
    rc = o3d.t.geometry.RaycastingScene()
    for obj in sphere_scene.objects:
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))
    t = rc.cast_rays(o3d.core.Tensor(np.hstack([o, d]).astype(np.float32)))["t_hit"].numpy()
    p = o + t[:, None] * d
    v = st.projector.diapositive_coordinates(p)[:, 1]
    v_line = raster.positions[np.searchsorted(raster.numbers, lr.number)]
    assert np.percentile(np.abs(v - v_line), 99) < 1e-2  # float32 ray casting here
    # shading: the ball darkens towards its rim as the surface turns from the projector
    ball = (r.object_index == 1) & ~r.shadow
    n = r.normals[ball]
    to_proj = st.projector.centre - r.points[ball]
    cos = np.einsum("ij,ij->i", n, to_proj / np.linalg.norm(to_proj, axis=1, keepdims=True))
    assert cos.min() < 0.3 and cos.max() > 0.95
    # both sides of the sphere's projector shadow on the wall: a shadow exists
    assert np.any(r.shadow & (r.object_index == 0))


def test_ground_truth_files_round_trip(sphere_scene: Scene, tmp_path) -> None:  # type: ignore[no-untyped-def]
    st = default_station()
    r: Rendering = render(sphere_scene, st, seed=3)
    for name in ("truth.npz", "truth.h5"):
        path = save_ground_truth(tmp_path / name, r, sphere_scene, st)
        gt = load_ground_truth(path)
        np.testing.assert_array_equal(gt["image"], r.image)
        np.testing.assert_array_equal(gt["points"], r.points)
        np.testing.assert_array_equal(gt["line_number"], r.line_number)
        np.testing.assert_array_equal(gt["line_rows"].row, r.line_rows.row)
        np.testing.assert_array_equal(gt["landmarks"]["apex"], [30.0, 20.0, -250.0])
        assert gt["scene_metadata"] == {"kind": "test", "radius": 150.0}
        assert gt["station"].to_json() == st.to_json()
        assert gt["raster"].n_lines == st.raster_definition.n_lines
        assert gt["object_names"] == ["wall", "ball"]
        assert gt["seed"] == 3 and gt["settings"]["supersampling"] == 3
    paths = write_simulation(tmp_path / "out", r, sphere_scene, st, stem="ball")
    assert set(paths) == {"image_png", "image_npy", "ground_truth", "calibration", "raster"}
    assert all(p.exists() for p in paths.values())
    assert load_calibration_document(Path(paths["calibration"])).to_json() == st.to_json()
    np.testing.assert_array_equal(np.load(paths["image_npy"]), r.image)


def test_even_supersampling_and_large_sensor_path() -> None:
    st = default_station(160, 200)
    scene = Scene([SceneObject("plane", plane_mesh(), 0.8)])
    r2 = render(scene, st, settings=NOISE_FREE.replace(supersampling=2), seed=0)
    r3 = render(scene, st, settings=NOISE_FREE, seed=0)
    np.testing.assert_array_equal(r2.line_number, r3.line_number)
    # the same crossings, to the ground truth's accuracy
    key2 = {
        (c, n): row
        for c, n, row in zip(
            r2.line_rows.column, r2.line_rows.number, r2.line_rows.row, strict=True
        )
    }
    diffs = [
        abs(key2[(c, n)] - row)
        for c, n, row in zip(
            r3.line_rows.column, r3.line_rows.number, r3.line_rows.row, strict=True
        )
        if (c, n) in key2
    ]
    assert len(diffs) > 0.95 * len(r3.line_rows) and max(diffs) < 1e-4
    # supersampling converges: 3 x 3 is within ~1 % of a 7 x 7 reference, 4 x 4 closer
    ref = render(scene, st, settings=NOISE_FREE.replace(supersampling=7), seed=0).electrons
    r4 = render(scene, st, settings=NOISE_FREE.replace(supersampling=4), seed=0).electrons
    err3 = np.abs(r3.electrons - ref).max() / ref.max()
    err4 = np.abs(r4 - ref).max() / ref.max()
    assert err3 < 0.02 and err4 < err3


def test_empty_scene_is_dark() -> None:
    st = default_station(64, 80)
    plane_far = Scene([SceneObject("plane", plane_mesh(z=5000.0, size=10.0, n=2), 0.8)])
    r = render(plane_far, st, settings=NOISE_FREE, seed=0)
    assert not r.visible.any() and len(r.line_rows) == 0
    assert np.all(r.image == round(NOISE_FREE.offset))
    assert np.all(np.isnan(r.points)) and np.all(r.line_number == -1)
    nothing = render(Scene([]), st, settings=NOISE_FREE, seed=0)
    assert np.array_equal(nothing.image, r.image) and nothing.object_names == []


def test_projector_off_has_no_lines() -> None:
    st = default_station(96, 120)
    settings = NOISE_FREE.replace(projector_electrons=0.0, ambient_electrons=5000.0)
    r = render(Scene([SceneObject("plane", plane_mesh(), 0.5)]), st, settings=settings, seed=0)
    assert len(r.line_rows) == 0 and np.all(r.line_number == -1)
    np.testing.assert_array_equal(r.shadow, r.visible)
    np.testing.assert_allclose(r.electrons, 2500.0, rtol=1e-5)
