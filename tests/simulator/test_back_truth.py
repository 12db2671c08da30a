"""The simulated back's truth for the back-shape analysis (fixed parameters, no rendering)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import open3d as o3d
import pytest

from rasterserver.errors import InputError
from rasterserver.simulator.back import (
    PRESETS,
    BackParameters,
    ScoliosisCurve,
    make_back,
    posture_sway,
    random_back,
)
from rasterserver.simulator.back_truth import (
    PARAMETER_UNITS,
    body_depth,
    cobb_angle,
    inclination,
    sagittal_points,
    signed_extremes,
    truth,
    turning_points,
)
from rasterserver.simulator.scene import Scene
from rasterserver.simulator.shapes import plane

#: One curve that vanishes at VP and DM, so the VP–DM line is the vertical through offset_x.
CURVE = ScoliosisCurve(apex=0.45, extent=0.3, lateral_deviation=20.0, rotation=12.0)


def _scene(params: BackParameters, spacing: float = 5.0) -> Scene:
    return make_back(params, spacing=spacing)


def _trunk_depth(scene: Scene, x: np.ndarray, y: float) -> np.ndarray:
    """Z of the trunk seen along +Z at (x, y)."""
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.objects[0].mesh))
    rays = np.zeros((x.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = x, y, -1000.0, 1.0
    return rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() - 1000.0


@pytest.fixture(scope="module")
def scoliotic() -> tuple[BackParameters, Scene]:
    params = BackParameters(inclination=0.0, offset_x=7.0, curves=(CURVE,))
    return params, _scene(params, spacing=1.5)


def test_truth_has_every_landmark_and_parameter(scoliotic) -> None:
    _, scene = scoliotic
    tr = truth(scene)
    assert set(tr["landmarks"]) == {"VP", "DL", "DR", "DM", "SP", "ICT", "KA", "ITL", "LA", "ILS"}
    assert all(p.shape == (3,) and np.isfinite(p).all() for p in tr["landmarks"].values())
    assert set(tr["parameters"]) == set(PARAMETER_UNITS)
    for name, entry in tr["parameters"].items():
        assert entry["unit"] == PARAMETER_UNITS[name] and math.isfinite(entry["value"])
    m = len(tr["spine"]["t"])
    assert tr["spine"]["skin"].shape == tr["spine"]["body"].shape == (m, 3)
    lm = scene.landmarks
    np.testing.assert_array_equal(lm["dimple_midpoint"], lm["sacrum"])
    np.testing.assert_array_equal(tr["landmarks"]["DM"], lm["spinal_midline"][-1])


def test_sacrum_point_is_below_dm_at_the_bottom_of_the_cleft(scoliotic) -> None:
    params, scene = scoliotic
    lm = truth(scene)["landmarks"]
    sp, dm = lm["SP"], lm["DM"]
    # Below DM (Y down), on the midline (the curve has vanished there), ~0.135 L lower.
    assert sp[1] - dm[1] == pytest.approx(0.135 * params.trunk_length, rel=0.05)
    assert sp[0] == pytest.approx(params.offset_x, abs=1e-9)
    # On the rendered skin, at the bottom of a furrow (the cleft) across the back.
    x = sp[0] + np.linspace(-10.0, 10.0, 41)
    z = _trunk_depth(scene, x, sp[1])
    assert z[20] == pytest.approx(sp[2], abs=0.1)
    assert abs(x[np.argmax(z)] - sp[0]) <= 0.5
    assert z[20] > z[0] + 0.4 and z[20] > z[-1] + 0.4
    # Two thirds of a cleft ramp higher up there is no cleft yet: the skin is convex there.
    y_above = sp[1] - 0.035 * params.trunk_length
    z_above = _trunk_depth(scene, x, y_above)
    assert z_above[20] - z_above[[0, -1]].mean() < z[20] - z[[0, -1]].mean()


def test_sagittal_points_are_ordered_and_on_the_spinal_line() -> None:
    for params in [*PRESETS.values(), *(random_back(s) for s in range(8))]:
        scene = _scene(params)
        lm, sag = truth(scene)["landmarks"], scene.metadata["truth"]["sagittal"]
        ts = [sag[name]["t"] for name in ("ICT", "KA", "ITL", "LA", "ILS")]
        assert 0.0 <= ts[0] < ts[2] < ts[4] <= 1.0
        assert ts == sorted(ts)
        heights = [lm[name][1] for name in ("ICT", "KA", "ITL", "LA", "ILS")]
        assert heights == sorted(heights)
        assert lm["VP"][1] <= heights[0] and heights[-1] <= lm["DM"][1] + 1e-9
        # The points lie on the skin's spinal line (2 mm samples: within a sample).
        midline = scene.landmarks["spinal_midline"]
        for name in ("ICT", "KA", "ITL", "LA", "ILS"):
            assert np.linalg.norm(midline - lm[name], axis=1).min() < 1.5


def test_sagittal_angles_follow_the_profile_tangents() -> None:
    params = dataclasses.replace(PRESETS["normal"], inclination=0.0)
    tr = truth(_scene(params))
    p, sag = tr["parameters"], _scene(params).metadata["truth"]["sagittal"]
    skin = tr["spine"]["skin"]
    # Tangent inclinations recomputed from the 2 mm midline agree with the stored ones.
    alpha = inclination(skin[:, 1], skin[:, 2])
    t = tr["spine"]["t"]
    for name in ("ITL",):
        assert np.interp(sag[name]["t"], t, alpha) == pytest.approx(
            sag[name]["inclination_deg"], abs=0.3
        )
    # ITL is the steepest anterior run; apices are where the tangent is vertical.
    assert sag["ITL"]["inclination_deg"] == pytest.approx(
        alpha[(t > 0.15) & (t < 0.95)].max(), abs=0.3
    )
    assert abs(np.interp(sag["KA"]["t"], t, alpha)) < 1.0
    assert abs(np.interp(sag["LA"]["t"], t, alpha)) < 1.0
    assert p["kyphotic_angle_deg"]["value"] > 20.0 and p["lordotic_angle_deg"]["value"] > 20.0
    # Leaning forwards turns the whole profile: the angles between tangents stay.
    leaning = truth(_scene(dataclasses.replace(params, inclination=6.0)))["parameters"]
    for name in ("kyphotic_angle_deg", "lordotic_angle_deg"):
        assert leaning[name]["value"] == pytest.approx(p[name]["value"], abs=1.0)
    assert leaning["trunk_inclination_deg"]["value"] - p["trunk_inclination_deg"][
        "value"
    ] == pytest.approx(6.0, abs=0.2)
    # More kyphosis, a larger kyphotic angle and flèche cervicale.
    deeper = truth(_scene(dataclasses.replace(params, kyphosis=45.0)))["parameters"]
    assert deeper["kyphotic_angle_deg"]["value"] > p["kyphotic_angle_deg"]["value"] + 5.0
    assert deeper["fleche_cervicale_mm"]["value"] > p["fleche_cervicale_mm"]["value"] + 5.0


def test_body_centres_follow_deviation_and_rotation(scoliotic) -> None:
    params, scene = scoliotic
    tr = truth(scene)
    spine, meta = tr["spine"], scene.metadata["spine"]
    dev = np.asarray(meta["lateral_deviation_mm"])
    phi = np.radians(spine["axial_rotation_deg"])
    depth = spine["body_depth_mm"]
    np.testing.assert_allclose(depth, body_depth(spine["t"], params.trunk_length))
    assert depth[0] == pytest.approx(45.0) and depth[-1] == pytest.approx(70.0)
    # Frontal deviation of the body centres = applied deviation + depth * sin(rotation).
    np.testing.assert_allclose(spine["lateral_deviation_mm"], dev + depth * np.sin(phi), atol=1e-9)
    np.testing.assert_allclose(spine["body"][:, 0] - params.offset_x, dev + depth * np.sin(phi))
    np.testing.assert_allclose(np.linalg.norm(spine["body"] - spine["skin"], axis=1), depth)
    assert (spine["body"][:, 2] > spine["skin"][:, 2]).all()  # anterior of the skin
    # The vertebral bodies swing further to the convex side than the spinous processes.
    apex = np.argmax(dev)
    assert spine["lateral_deviation_mm"][apex] > dev[apex] + 10.0
    p = tr["parameters"]
    assert p["lateral_deviation_max_mm"]["value"] == pytest.approx(
        spine["lateral_deviation_mm"].max()
    )
    assert p["surface_rotation_max_deg"]["value"] == pytest.approx(CURVE.rotation, abs=1e-6)
    assert p["trunk_imbalance_mm"]["value"] == pytest.approx(0.0, abs=1e-9)
    assert 10.0 < p["scoliosis_angle_deg"]["value"] < 60.0


def test_body_depth_scales_with_the_trunk() -> None:
    assert body_depth(np.array([0.0, 1.0]), 550.0) == pytest.approx([56.25, 87.5])


def test_surface_rotation_is_the_normal_of_the_rendered_skin(scoliotic) -> None:
    _, scene = scoliotic
    tr = truth(scene)
    skin, rotation = tr["spine"]["skin"], tr["spine"]["surface_rotation_deg"]
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.objects[0].mesh))
    pick = np.arange(20, len(skin) - 20, 15)
    rays = np.zeros((pick.size, 6), np.float32)
    rays[:, :3] = skin[pick] - [0.0, 0.0, 50.0]
    rays[:, 5] = 1.0
    normals = rs.cast_rays(o3d.core.Tensor(rays))["primitive_normals"].numpy()
    normals *= np.where(normals[:, 2:] > 0, -1.0, 1.0)
    measured = np.degrees(np.arctan2(-normals[:, 0], -normals[:, 2]))
    assert np.abs(measured - rotation[pick]).max() < 1.0
    assert rotation.max() == pytest.approx(CURVE.rotation, abs=1e-6)


def test_symmetric_back_has_zero_asymmetry_truth() -> None:
    params = dataclasses.replace(PRESETS["normal"], inclination=5.0, offset_x=12.0)
    tr = truth(_scene(params))
    p = {k: v["value"] for k, v in tr["parameters"].items()}
    for name in (
        "trunk_imbalance_mm",
        "trunk_imbalance_deg",
        "pelvic_tilt_mm",
        "pelvic_tilt_deg",
        "pelvic_torsion_deg",
        "pelvic_rotation_deg",
        "surface_rotation_rms_deg",
        "surface_rotation_max_deg",
        "lateral_deviation_rms_mm",
        "lateral_deviation_max_mm",
        "scoliosis_angle_deg",
    ):
        assert p[name] == pytest.approx(0.0, abs=1e-9), name
    assert np.abs(tr["spine"]["lateral_deviation_mm"]).max() < 1e-9
    assert p["trunk_length"] == pytest.approx(params.trunk_length)


def test_mirrored_back_flips_the_signs() -> None:
    params = dataclasses.replace(PRESETS["severe"], offset_x=9.0, lateral_lean=1.5, turn=-2.0)
    mirror = dataclasses.replace(
        params,
        offset_x=-params.offset_x,
        lateral_lean=-params.lateral_lean,
        turn=-params.turn,
        curves=tuple(
            dataclasses.replace(c, lateral_deviation=-c.lateral_deviation, rotation=-c.rotation)
            for c in params.curves
        ),
    )
    a, b = truth(_scene(params)), truth(_scene(mirror))
    flip = np.array([-1.0, 1.0, 1.0])
    for name, point in a["landmarks"].items():
        other = {"DL": "DR", "DR": "DL"}.get(name, name)
        np.testing.assert_allclose(b["landmarks"][other], point * flip, atol=1e-9)
    np.testing.assert_allclose(b["spine"]["body"], a["spine"]["body"] * flip, atol=1e-9)
    odd = {
        "trunk_imbalance_mm",
        "trunk_imbalance_deg",
        "pelvic_tilt_mm",
        "pelvic_tilt_deg",
        "pelvic_torsion_deg",
        "pelvic_rotation_deg",
        "surface_rotation_max_deg",
        "lateral_deviation_max_mm",
    }
    pa, pb = a["parameters"], b["parameters"]
    assert abs(pa["lateral_deviation_max_mm"]["value"]) > 20.0
    assert abs(pa["surface_rotation_max_deg"]["value"]) > 10.0
    for name in PARAMETER_UNITS:
        sign = -1.0 if name in odd else 1.0
        if name.endswith("pos_max_deg") or name.endswith("pos_max_mm"):
            other = name.replace("pos_max", "neg_max")
            assert pb[other]["value"] == pytest.approx(-pa[name]["value"], abs=1e-6), name
            continue
        if "neg_max" in name:
            continue
        assert pb[name]["value"] == pytest.approx(sign * pa[name]["value"], abs=1e-6), name


def test_lean_and_turn_show_in_imbalance_and_rotation() -> None:
    base = BackParameters(inclination=0.0)
    lean = truth(_scene(dataclasses.replace(base, lateral_lean=3.0)))["parameters"]
    assert lean["trunk_imbalance_deg"]["value"] == pytest.approx(3.0, abs=1e-6)
    turned = truth(_scene(dataclasses.replace(base, turn=4.0)))
    np.testing.assert_allclose(turned["spine"]["surface_rotation_deg"], 4.0, atol=1e-6)
    assert turned["parameters"]["pelvic_rotation_deg"]["value"] == pytest.approx(4.0, abs=1e-6)
    # A turned or leaning back is a rigid motion of the same body: the mesh moves with it.
    upright = _scene(base)
    moved = _scene(dataclasses.replace(base, turn=4.0, lateral_lean=3.0))
    va = np.asarray(upright.objects[0].mesh.vertices)
    vb = np.asarray(moved.objects[0].mesh.vertices)
    da = np.linalg.norm(va[0] - va[-1])
    assert np.linalg.norm(vb[0] - vb[-1]) == pytest.approx(da)
    with pytest.raises(InputError):
        BackParameters(turn=31.0)
    with pytest.raises(InputError):
        BackParameters(lateral_lean=-16.0)


def test_posture_sway_is_small_seeded_and_keeps_the_shape() -> None:
    params = PRESETS["moderate"]
    a, b = posture_sway(params, 3), posture_sway(params, 3)
    assert a == b and a != posture_sway(params, 4)
    for name in ("offset_x", "offset_y", "offset_z"):
        assert 0.0 < abs(getattr(a, name) - getattr(params, name)) <= 5.0
    for name in ("inclination", "lateral_lean", "turn"):
        assert 0.0 < abs(getattr(a, name) - getattr(params, name)) <= 1.0
    keep = {"offset_x", "offset_y", "offset_z", "inclination", "lateral_lean", "turn"}
    for f in dataclasses.fields(params):
        if f.name not in keep:
            assert getattr(a, f.name) == getattr(params, f.name)
    # The shape parameters stay, so does the truth that does not depend on the posture.
    ta, tp = truth(_scene(a))["parameters"], truth(_scene(params))["parameters"]
    assert ta["trunk_length"]["value"] == pytest.approx(tp["trunk_length"]["value"], abs=1e-6)
    assert posture_sway(params, 3, translation=0.0, rotation=0.0) == params
    with pytest.raises(InputError):
        posture_sway(params, 1, translation=-1.0)
    # Clipped at the limits.
    leaning = dataclasses.replace(params, inclination=25.0, offset_x=150.0)
    swayed = [posture_sway(leaning, s) for s in range(10)]
    assert max(s.inclination for s in swayed) <= 25.0 and max(s.offset_x for s in swayed) <= 150


def test_turning_points_and_cobb_angle() -> None:
    np.testing.assert_array_equal(turning_points([0, 1, 2, 3, 2, 1, 0, 1, 5]), [0, 3, 6, 8])
    np.testing.assert_array_equal(turning_points([1.0, 1.0 + 1e-9, 1.0]), [0])
    assert turning_points([]).size == 0
    y = np.linspace(0.0, 400.0, 401)
    assert cobb_angle(y, np.full_like(y, 5.0)) == 0.0
    assert cobb_angle(y, 0.1 * y) == 0.0  # a straight oblique line has no curve
    # x = A sin(2 pi y / 400): tangents +-atan(2 pi A / 400) at the ends and the middle.
    amplitude = 20.0
    x = amplitude * np.sin(2.0 * np.pi * y / 400.0)
    expected = 2.0 * math.degrees(math.atan(2.0 * np.pi * amplitude / 400.0))
    assert cobb_angle(y, x) == pytest.approx(expected, rel=1e-3)
    assert cobb_angle(y, -x) == pytest.approx(expected, rel=1e-3)


def test_signed_extremes() -> None:
    assert signed_extremes(np.array([1.0, -3.0, 2.0])) == pytest.approx(
        (math.sqrt(14.0 / 3.0), -3.0, 2.0, -3.0)
    )
    assert signed_extremes(np.array([1.0, 2.0]))[3] == 0.0
    assert all(math.isnan(v) for v in signed_extremes(np.zeros(0)))


def test_degenerate_inputs_are_refused() -> None:
    with pytest.raises(InputError):
        truth(plane())
    with pytest.raises(InputError):
        inclination(np.zeros(3), np.zeros(4))
    t = np.linspace(0.0, 0.1, 20)
    with pytest.raises(InputError):
        sagittal_points(t, t * 400.0, np.zeros_like(t))


def test_a_clinic_scene_has_its_backs_truth() -> None:
    # make_body builds the trunk with make_back (over a taller range, for the neck): the
    # landmarks, spine and parameters are the back's, whatever head, arms and cloth add
    from rasterserver.simulator.body import make_body, random_body

    params = random_body(3)
    body = truth(make_body(params, spacing=5.0))
    back = truth(make_back(params.back, spacing=5.0))
    for name, point in back["landmarks"].items():
        np.testing.assert_allclose(body["landmarks"][name], point, atol=1e-9)
    np.testing.assert_allclose(
        body["spine"]["lateral_deviation_mm"], back["spine"]["lateral_deviation_mm"], atol=1e-9
    )
    assert body["parameters"] == back["parameters"]
