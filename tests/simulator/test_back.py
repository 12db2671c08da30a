"""The parametric back: anatomy, scoliosis, arms, landmarks, parameters (fixed seeds)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import open3d as o3d
import pytest

from rasterserver.errors import InputError
from rasterserver.simulator.back import (
    PRESETS,
    BackParameters,
    ScoliosisCurve,
    SkinAlbedo,
    make_back,
    preset,
    random_back,
)
from rasterserver.simulator.scene import Scene

CAMERA = np.array([0.0, 0.0, -2000.0])


def _raycaster(scene: Scene, names: tuple[str, ...] | None = None):
    rs = o3d.t.geometry.RaycastingScene()
    ids = {}
    for obj in scene.objects:
        if names is None or obj.name in names:
            ids[rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))] = obj.name
    return rs, ids


def _depth_orthographic(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Z of the trunk seen along +Z at (x, y) (NaN where missed)."""
    rs, _ = _raycaster(scene, ("trunk",))
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    rays = np.zeros((x.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = x.ravel(), y.ravel(), -1000.0, 1.0
    t = rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return (t - 1000.0).reshape(x.shape)


def _camera_hits(scene: Scene, points: np.ndarray) -> list[str | None]:
    """Name of the object each camera ray through ``points`` hits first."""
    rs, ids = _raycaster(scene)
    d = points - CAMERA
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.hstack([np.broadcast_to(CAMERA, d.shape), d]).astype(np.float32)
    ans = rs.cast_rays(o3d.core.Tensor(rays))
    gid = ans["geometry_ids"].numpy()
    hit = np.isfinite(ans["t_hit"].numpy())
    return [ids[int(g)] if h else None for g, h in zip(gid, hit, strict=True)]


@pytest.fixture(scope="module")
def normal() -> Scene:
    return make_back(dataclasses.replace(preset("normal"), inclination=0.0))


@pytest.fixture(scope="module")
def moderate() -> Scene:
    return make_back(preset("moderate"))


def _mid_height(scene: Scene) -> float:
    return float((scene.landmarks["vertebra_prominens"][1] + scene.landmarks["sacrum"][1]) / 2)


def test_objects_and_mesh_budget(normal: Scene) -> None:
    assert [o.name for o in normal.objects] == ["trunk", "left-arm", "right-arm"]
    trunk = normal.objects[0].mesh
    assert len(trunk.triangles) <= 350_000
    # The back faces the camera: normals at the spinal line point towards -Z.
    v = np.asarray(trunk.vertices)
    n = np.asarray(trunk.vertex_normals)
    near_mid = np.linalg.norm(v[:, :2] - [0.0, _mid_height(normal)], axis=1) < 5.0
    assert near_mid.any() and (n[near_mid, 2] < -0.9).all()
    # The arms' normals point away from their axes (outwards): the posterior side faces -Z.
    for arm in normal.objects[1:]:
        av, an = np.asarray(arm.mesh.vertices), np.asarray(arm.mesh.vertex_normals)
        back = av[:, 2] < np.percentile(av[:, 2], 2)
        assert (an[back, 2] < 0).mean() > 0.95


def test_back_lies_around_the_nominal_plane(normal: Scene) -> None:
    mid = normal.landmarks["spinal_midline"]
    assert abs(mid[:, 2].mean()) < 2.0
    y = np.linspace(mid[0, 1], mid[-1, 1], 40)
    x = np.linspace(-120, 120, 49)
    z = _depth_orthographic(normal, x[None, :], y[:, None])
    assert np.isfinite(z).all()
    assert -40.0 < np.nanmin(z) < -5.0  # the most posterior points (shoulder blades, kyphosis)
    # Flanks curve away from the camera.
    assert (_depth_orthographic(normal, 150.0, y[10:30]) > 30.0).all()


def test_midline_furrow_is_a_local_minimum_of_posteriority(normal: Scene) -> None:
    y = _mid_height(normal) + np.array([-60.0, 0.0, 60.0, 120.0])
    x = np.linspace(-40.0, 40.0, 81)
    z = _depth_orthographic(normal, x[None, :], y[:, None])
    centre = np.argmin(np.abs(x))
    for row in z:
        # posterior-ness is -z: the furrow bottom (x = 0) is deeper than its surroundings
        assert row[centre] == pytest.approx(row[np.abs(x) <= 6].max(), abs=0.05)
        assert row[centre] > row[np.abs(x - 25.0) < 1].max() + 1.0
        assert row[centre] > row[np.abs(x + 25.0) < 1].max() + 1.0


def test_normal_back_is_symmetric(normal: Scene) -> None:
    y = np.linspace(-200.0, 250.0, 31)
    x = np.linspace(5.0, 140.0, 28)
    right = _depth_orthographic(normal, x[None, :], y[:, None])
    left = _depth_orthographic(normal, -x[None, :], y[:, None])
    both = np.isfinite(right) & np.isfinite(left)
    diff = np.abs(right[both] - left[both])
    # Exact up to the triangulation (diagonals of the grid cells are not mirrored).
    assert both.mean() > 0.9
    assert diff.max() < 0.3 and np.percentile(diff, 99) < 0.05
    lm = normal.landmarks
    assert lm["dimple_left"][0] == pytest.approx(-lm["dimple_right"][0], abs=1e-6)
    assert np.abs(lm["spinal_midline"][:, 0]).max() < 1e-9


@pytest.mark.parametrize("deviation", [25.0, -12.0])
def test_midline_deviation_matches_the_parameter(deviation: float) -> None:
    params = BackParameters(
        inclination=0.0, curves=(ScoliosisCurve(apex=0.4, lateral_deviation=deviation),)
    )
    scene = make_back(params)
    mid = scene.landmarks["spinal_midline"]
    i = np.argmax(np.abs(mid[:, 0]))
    assert mid[i, 0] == pytest.approx(deviation, abs=0.05)
    t = np.asarray(scene.metadata["spine"]["t"])
    assert t[i] == pytest.approx(0.4, abs=0.01)
    np.testing.assert_allclose(
        mid[:, 0], scene.metadata["spine"]["lateral_deviation_mm"], atol=1e-9
    )
    # The surface itself: the furrow bottom follows the deviated midline.
    y_apex = mid[i, 1]
    x = mid[i, 0] + np.linspace(-8.0, 8.0, 33)
    z = _depth_orthographic(scene, x, np.full_like(x, y_apex))
    assert abs(x[np.argmax(z)] - mid[i, 0]) <= 1.0


def test_moderate_preset_deviation(moderate: Scene) -> None:
    mid = moderate.landmarks["spinal_midline"]
    main = PRESETS["moderate"].curves[0]
    assert np.abs(mid[:, 0]).max() == pytest.approx(abs(main.lateral_deviation), abs=0.3)
    rotation = np.asarray(moderate.metadata["spine"]["axial_rotation_deg"])
    assert rotation.max() == pytest.approx(main.rotation, abs=0.1)


@pytest.mark.parametrize("rotation", [10.0, -10.0])
def test_axial_rotation_makes_a_rib_hump_on_the_expected_side(rotation: float) -> None:
    params = BackParameters(
        inclination=0.0,
        scapula_prominence=0.0,
        curves=(ScoliosisCurve(apex=0.45, extent=0.3, rotation=rotation),),
    )
    scene = make_back(params)
    mid = scene.landmarks["spinal_midline"]
    t = np.asarray(scene.metadata["spine"]["t"])
    y = mid[np.argmin(np.abs(t - 0.45)), 1]
    z_right = _depth_orthographic(scene, 80.0, y)
    z_left = _depth_orthographic(scene, -80.0, y)
    hump = z_left - z_right  # > 0: the right side is more posterior (nearer the camera)
    expected = 2 * 80.0 * np.sin(np.radians(rotation))
    assert np.sign(hump) == np.sign(rotation)
    assert hump == pytest.approx(expected, rel=0.35)
    # Far from the curve the back is symmetric again.
    y_far = mid[np.argmin(np.abs(t - 0.95)), 1]
    assert (
        abs(_depth_orthographic(scene, 80.0, y_far) - _depth_orthographic(scene, -80.0, y_far))
        < 0.1
    )


def test_arms_are_separate_with_a_gap(moderate: Scene) -> None:
    params = PRESETS["moderate"]
    gaps = moderate.metadata["arm_gap_mm"]
    assert min(gaps["left"], gaps["right"]) >= params.arm_gap
    arms = {o.name: np.asarray(o.mesh.vertices) for o in moderate.objects[1:]}
    assert arms["left-arm"][:, 0].mean() < -150 and arms["right-arm"][:, 0].mean() > 150
    # Camera rays across the waist: trunk, then nothing, then an arm, on both sides.
    mid = moderate.landmarks["spinal_midline"]
    y = mid[np.argmin(np.abs(np.asarray(moderate.metadata["spine"]["t"]) - 0.7)), 1]
    x = np.linspace(-285.0, 285.0, 1141)
    hits = _camera_hits(moderate, np.column_stack([x, np.full_like(x, y), np.zeros_like(x)]))
    runs = [hits[0]]
    for h in hits[1:]:
        if h != runs[-1]:
            runs.append(h)
    assert runs[runs.index("trunk") - 2 : runs.index("trunk") + 3] == [
        "left-arm",
        None,
        "trunk",
        None,
        "right-arm",
    ]


def test_landmarks_lie_on_the_skin_and_in_view(moderate: Scene) -> None:
    rs, _ = _raycaster(moderate, ("trunk",))
    lm = moderate.landmarks
    points = np.vstack(
        [lm["vertebra_prominens"], lm["dimple_left"], lm["dimple_right"], lm["spinal_midline"]]
    )
    dist = rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    assert dist.max() < 0.1
    assert lm["vertebra_prominens"][1] < lm["dimple_left"][1]  # C7 above the dimples (Y down)
    assert lm["dimple_left"][0] < 0 < lm["dimple_right"][0]
    np.testing.assert_allclose(lm["spinal_midline"][0], lm["vertebra_prominens"])
    np.testing.assert_allclose(lm["spinal_midline"][-1], lm["sacrum"])
    # Every landmark is visible to the camera (the first hit is the trunk at the point).
    assert set(_camera_hits(moderate, points)) == {"trunk"}
    assert (np.abs(points[:, 0]) < 288).all() and (np.abs(points[:, 1]) < 302).all()
    json.dumps(moderate.metadata)


def test_trunk_length_is_c7_to_dm() -> None:
    params = BackParameters(trunk_length=500.0, inclination=0.0)
    lm = make_back(params).landmarks
    assert lm["sacrum"][1] - lm["vertebra_prominens"][1] == pytest.approx(500.0, abs=1e-6)
    tilted = make_back(dataclasses.replace(params, inclination=10.0)).landmarks
    # Leaning forwards moves C7 away from the camera relative to DM.
    dz = tilted["vertebra_prominens"][2] - tilted["sacrum"][2]
    dz0 = lm["vertebra_prominens"][2] - lm["sacrum"][2]
    assert dz - dz0 == pytest.approx(500.0 * np.sin(np.radians(10.0)), rel=0.1)


def test_deterministic_and_seeded_albedo() -> None:
    a = make_back(PRESETS["severe"], spacing=3.0)
    b = make_back(PRESETS["severe"], spacing=3.0)
    for oa, ob in zip(a.objects, b.objects, strict=True):
        np.testing.assert_array_equal(np.asarray(oa.mesh.vertices), np.asarray(ob.mesh.vertices))
    pts = np.random.default_rng(0).uniform(-200, 200, (1000, 3))
    skin = a.objects[0].albedo
    assert callable(skin)
    values = skin(pts)
    np.testing.assert_array_equal(values, b.objects[0].albedo(pts))
    assert values.min() >= 0.0 and values.max() <= 1.0
    assert 0.01 < values.std() < 0.2
    other = SkinAlbedo(seed=99)(pts)
    assert not np.allclose(other, SkinAlbedo(seed=98)(pts))


def test_random_backs_vary_reproducibly() -> None:
    backs = [random_back(seed) for seed in range(40)]
    assert random_back(7) == backs[7]
    assert len({b.trunk_length for b in backs}) == 40
    assert any(not b.curves for b in backs) and any(len(b.curves) == 2 for b in backs)
    for b in backs:
        assert BackParameters.from_dict(json.loads(json.dumps(b.to_dict()))) == b
    scene = make_back(backs[3], spacing=3.0)
    assert scene.metadata["parameters"] == backs[3].to_dict()


def test_presets_differ_in_severity() -> None:
    dev = {
        k: max((abs(c.lateral_deviation) for c in p.curves), default=0.0)
        for k, p in PRESETS.items()
    }
    assert dev["normal"] == 0.0 < dev["moderate"] < dev["severe"]
    with pytest.raises(InputError):
        preset("mild")


def test_with_primary_curve_overrides() -> None:
    p = PRESETS["normal"].with_primary_curve(lateral_deviation=10.0)
    assert p.curves[0].lateral_deviation == 10.0 and p.curves[0].rotation == 0.0
    q = PRESETS["severe"].with_primary_curve(rotation=-5.0)
    assert q.curves[0].rotation == -5.0 and q.curves[1] == PRESETS["severe"].curves[1]


@pytest.mark.parametrize(
    "changes",
    [
        {"trunk_length": -440.0},
        {"trunk_length": 0.0},
        {"shoulder_width": 100.0},
        {"inclination": 40.0},
        {"kyphosis": -1.0},
        {"arm_gap": -5.0},
        {"albedo": 0.0},
        {"albedo": float("nan")},
        {"trunk_length": "tall"},
        {"albedo_seed": -1},
        {"naevi": 1.5},
        {"curves": (ScoliosisCurve(),) * 4},
    ],
)
def test_degenerate_parameters_are_refused(changes: dict) -> None:
    with pytest.raises(InputError):
        BackParameters(**changes)


@pytest.mark.parametrize(
    "changes",
    [
        {"rotation": 61.0},
        {"rotation": -75.0},
        {"lateral_deviation": 200.0},
        {"apex": 1.5},
        {"extent": 0.0},
        {"extent": float("inf")},
    ],
)
def test_degenerate_curves_are_refused(changes: dict) -> None:
    with pytest.raises(InputError):
        ScoliosisCurve(**changes)


def test_bad_mesh_options_are_refused() -> None:
    with pytest.raises(InputError):
        make_back(BackParameters(), spacing=0.1)
    with pytest.raises(InputError):
        make_back(BackParameters(), y_range=(0.0, 10.0))
    with pytest.raises(InputError):
        BackParameters.from_dict({"height": 3})


@pytest.mark.parametrize("seed", [3, 17, 404, 1111])
def test_random_backs_keep_the_arm_gap(seed: int) -> None:
    params = random_back(seed)
    gaps = make_back(params, spacing=3.0).metadata["arm_gap_mm"]
    assert min(gaps.values()) >= params.arm_gap
