"""The ``analysis.back-shape`` stage: found as a plugin, run by the pipeline, refusals, gravity."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from back_surfaces import GRAVITY, back, with_z
from image_truth import station
from rasterserver_plugins.back_shape import NO_VERTICAL, BackShapeAnalysis, analyse_back
from rasterserver_plugins.peak_detection import VERSION_5

from rasterserver.pipeline import run_chain
from rasterserver.records_analysis import LANDMARKS, BackShape
from rasterserver.records_surface import Surface
from rasterserver.registry import Registry
from rasterserver.stage import StageContext, run_stage

#: Peaks version 5 in version 6 (extrema on ``[1, 2, 1]``-smoothed columns): the clinic
#: scenes below were found with them.
PEAKS_5 = {"peaks": VERSION_5}
#: Numbering version 25 in version 29 (its line-end steps off): scene 24's case was found
#: with it on peaks version 5.
NUMBERS_25 = {"numbers": {"meet_tolerance": 0.0, "outer_gap": 0.0, "one_sided_peaks": 5}}


def test_found_through_the_entry_point() -> None:
    stage = Registry().discover().get("analysis.back-shape")
    assert isinstance(stage, BackShapeAnalysis)
    assert stage.stage == "analysis" and stage.requires == ("calibration",)


def test_the_pipeline_runs_it_after_the_surface() -> None:
    surface, truth = back("normal")
    st = station()
    records = run_chain(surface, context=StageContext(calibration=st), until="analysis")
    shape = records["analysis"]
    assert isinstance(shape, BackShape) and shape.reason == ""
    summary = shape.summary()
    assert set(summary["landmarks"]) == set(LANDMARKS)
    vp = summary["landmarks"]["VP"]
    assert np.linalg.norm(np.array(vp) - truth["landmarks"]["VP"]) < 2.0
    entry = summary["parameters"]["trunk_length"]
    assert set(entry) == {"value", "unit", "spread"} and entry["unit"] == "mm"
    assert entry["spread"] is None
    # the body frame: origin DM, right-handed unit axes
    np.testing.assert_allclose(shape.frame_origin, shape.landmark("DM"))
    np.testing.assert_allclose(shape.frame_axes @ shape.frame_axes.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(shape.frame_axes) > 0.999
    m = shape.symmetry_line.shape[0]
    assert m > 100 and shape.midline.shape == (m, 3) and shape.surface_rotation.shape == (m,)
    assert shape.mean_curvature.dtype == np.float32
    assert (
        shape.max_curvature is not None and shape.max_curvature.shape == shape.mean_curvature.shape
    )


def test_a_calibration_without_vertical_is_refused() -> None:
    surface, _ = back("normal")
    no_gravity = dataclasses.replace(station(), gravity=None)
    shape = run_stage(BackShapeAnalysis, surface, context=StageContext(calibration=no_gravity))
    assert shape.reason == NO_VERTICAL and "gravity" in shape.reason
    assert np.isnan(shape.landmarks).all() and shape.parameter_table() == {}


@pytest.mark.parametrize(
    "z",
    [np.zeros((0, 0)), np.full((50, 60), np.nan)],
    ids=["empty", "all-NaN"],
)
def test_no_surface(z: np.ndarray) -> None:
    shape = analyse_back(Surface(x0=0.0, y0=0.0, spacing=3.0, z=z, reason="x"), GRAVITY)
    assert shape.reason.startswith("no surface to analyse")


def test_flat_wall_is_no_back() -> None:
    rng = np.random.default_rng(2)
    z = 900.0 + rng.normal(0.0, 0.3, (200, 190))
    shape = analyse_back(Surface(x0=-285.0, y0=-300.0, spacing=3.0, z=z), GRAVITY)
    assert "no back recognised" in shape.reason
    assert {"VP", "DL", "DR"} <= set(shape.reason_table())
    assert np.isnan(shape.landmarks).all()


def test_half_a_back_is_refused() -> None:
    surface, truth = back("severe")
    xs, _ = surface.coordinates()
    half = np.where(xs[None, :] <= truth["landmarks"]["VP"][0] + 2.0, surface.z, np.nan)
    shape = analyse_back(with_z(surface, half), GRAVITY)
    assert "straight vertical edge" in shape.reason and "right" in shape.reason
    assert np.isnan(shape.landmarks).all()


def test_missing_dimples_leave_what_needs_them_out() -> None:
    surface, truth = back("moderate")
    _, ys = surface.coordinates()
    cropped = np.where(ys[:, None] < truth["landmarks"]["DL"][1] - 3.0, surface.z, np.nan)
    shape = analyse_back(with_z(surface, cropped), GRAVITY)
    assert shape.reason == "" and shape.landmark("VP") is not None
    reasons = shape.reason_table()
    for key in ("DL", "DR", "DM", "SP", "symmetry_line", "pelvic_tilt_mm", "trunk_length"):
        assert key in reasons
    assert shape.parameter_table() == {} and shape.symmetry_line.shape == (0, 3)
    assert np.isnan(shape.frame_axes).all()


def _rolled(surface: Surface, angle: float) -> tuple[Surface, np.ndarray]:
    """The surface seen by a camera rolled by ``angle`` (rad) about its optical axis."""
    from scipy.interpolate import griddata
    from scipy.spatial import cKDTree

    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    points = surface.grid_points() @ rot.T
    step = surface.spacing
    x0 = math.floor(points[:, 0].min() / step) * step
    y0 = math.floor(points[:, 1].min() / step) * step
    gx = np.arange(x0, points[:, 0].max(), step)
    gy = np.arange(y0, points[:, 1].max(), step)
    mx, my = np.meshgrid(gx, gy)
    z = griddata(points[:, :2], points[:, 2], (mx, my), method="linear")
    far = cKDTree(points[:, :2]).query(np.column_stack([mx.ravel(), my.ravel()]))[0]
    z[far.reshape(z.shape) > step] = np.nan
    return Surface(x0=x0, y0=y0, spacing=step, z=z), rot


def test_gravity_defines_the_vertical() -> None:
    # The camera rolled by 4°: the same back, gravity no longer along the world's Y.
    surface, _ = back("moderate")
    plain = analyse_back(surface, GRAVITY)
    rolled, rot = _rolled(surface, math.radians(4.0))
    shape = analyse_back(rolled, rot @ GRAVITY)
    assert shape.reason == "" and shape.level_axes is not None
    np.testing.assert_allclose(shape.level_axes, rot.T, atol=1e-9)
    for name in ("VP", "DL", "DR"):
        expected = rot @ plain.landmark(name)
        assert np.linalg.norm(shape.landmark(name) - expected) < 1.5, name
    p, q = plain.parameter_table(), shape.parameter_table()
    for key, tol in (
        ("trunk_length", 1.5),
        ("trunk_imbalance_mm", 1.5),
        ("pelvic_tilt_deg", 0.5),
        ("surface_rotation_max_deg", 0.5),
        ("lateral_deviation_max_mm", 1.0),
    ):
        assert q[key]["value"] == pytest.approx(p[key]["value"], abs=tol), key
    # wrongly believing the camera level shows up as an imbalance of the trunk
    naive = analyse_back(rolled, GRAVITY).parameter_table()
    assert abs(naive["trunk_imbalance_mm"]["value"] - p["trunk_imbalance_mm"]["value"]) > 20.0


def test_the_checks_of_versions_4_to_9_are_parameters_that_switch_them_off() -> None:
    from rasterserver_plugins.back_shape import BackShapeAnalysis

    default = BackShapeAnalysis.Params()
    assert default.vp_axis_offset == 15.0 and default.row_concavities == 3
    assert default.dimple_pit_ratio == 0.15 and default.vp_top_drop == 0.9
    assert default.vp_max_imbalance == 50.0 and default.vp_region_below == 0.45
    old = BackShapeAnalysis.Params(
        vp_axis_offset=0.0,
        row_concavities=0,
        dimple_pit_ratio=None,
        vp_top_drop=None,
        vp_max_imbalance=None,
        vp_region_below=0.7,
    )
    assert old.vp_max_imbalance is None and old.vp_region_below == 0.7
    assert old.vp_axis_offset == 0.0 and old.row_concavities == 0  # version 3
    assert old.dimple_pit_ratio is None and old.vp_top_drop is None
    bads = (
        {"vp_axis_offset": -1.0},
        {"row_concavities": -1},
        {"dimple_pit_ratio": -0.1},
        {"dimple_pit_ratio": 1.5},
        {"vp_top_drop": 0.0},
        {"vp_top_drop": 1.0},
        {"vp_max_imbalance": 0.0},
        {"vp_region_below": 0.0},
        {"vp_region_below": 2.0},
    )
    for bad in bads:
        with pytest.raises(ValueError):
            BackShapeAnalysis.Params(**bad)


def test_a_waistband_groove_no_longer_hides_the_dimples_of_a_clinic_scene() -> None:
    # Clinic tuning scene 119 (benchmarks/clinic_analysis.py; hands away, a waistband): the
    # waistband's edge is a groove across the lower back whose points rival the dimples, so
    # version 5 refused them as ambiguous; the grooves are no pits (version 6).
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body
    from rasterserver.simulator.render import RenderSettings, render

    body = random_body(119)
    assert body.waistband is not None
    st = clinic_station(119)
    context = StageContext(calibration=st, raster=st.raster_definition)
    scene = make_body(body)
    settings = RenderSettings(supersampling=1, threads=1)
    image = render(scene, st, settings=settings, seed=119).image
    surface = run_chain(image, context=context, until="surface")["surface"]
    true = truth(scene)["landmarks"]
    old = run_chain(
        surface, context=context, until="analysis", params={"analysis": {"dimple_pit_ratio": None}}
    )["analysis"]
    assert old.landmark("DL") is None
    assert "two similar pairs" in old.reason_table()["DL"]
    new = run_chain(surface, context=context, until="analysis")["analysis"]
    for name in ("DL", "DR", "DM"):
        point = new.landmark(name)
        assert point is not None, new.reason_table().get(name)
        assert np.linalg.norm(point - true[name]) < 5.0


def test_vp_just_below_the_hair_of_a_clinic_scene_is_found() -> None:
    # Clinic tuning scene 24 (kept frame; hair down to just above C7): the measured surface
    # ends a few millimetres above VP, whose convex maximum is seen on both sides; version 6
    # refused every candidate that close to the top, version 7 keeps it. (Scene 144 showed
    # it on the AMD EPYC this test was written on, not on an Intel Xeon: the renderer's
    # frames differ in their last bits between processors, so the frame is kept.) Judged on
    # peaks version 5, on which the case was found; with version 6's the surface ends a
    # little lower under the hair and VP is refused there: no answer, not a wrong one.
    # (Numbering version 25 with them: with 29's, a few line ends fewer, version 6 finds a
    # VP there too.)
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body

    kept = np.load(Path(__file__).parents[1] / "data" / "scenes" / "body-24.npz")
    st = clinic_station(24, str(kept["code"]))
    context = StageContext(calibration=st, raster=st.raster_definition)
    installed = run_chain(kept["image"], context=context, until="analysis")["analysis"]
    assert installed.landmark("VP") is None
    assert "top of the measured surface" in installed.reason_table()["VP"]
    on_25 = {**PEAKS_5, **NUMBERS_25}
    surface = run_chain(kept["image"], context=context, until="surface", params=on_25)["surface"]
    version6 = {"vp_top_drop": None, "vp_region_below": 0.7}
    old = run_chain(surface, context=context, until="analysis", params={"analysis": version6})[
        "analysis"
    ]
    assert old.landmark("VP") is None
    assert "top of the measured surface" in old.reason_table()["VP"]
    new = run_chain(surface, context=context, until="analysis")["analysis"]
    point = new.landmark("VP")
    assert point is not None, new.reason_table().get("VP")
    assert np.linalg.norm(point - truth(make_body(random_body(24)))["landmarks"]["VP"]) < 3.0


def test_a_scapulas_point_far_beside_dm_is_no_vp() -> None:
    # Held-out clinic scene 41394 as benchmarks/clinic_analysis.py renders it (the w8-1to2
    # code, its light and noise): arms away, hair over the whole nape. The strongest convex
    # point near the neck's base is the right scapula's, 76 mm beside and 61 mm below C7;
    # the symmetry axis just below it follows the trunk's pulled centre line (version 4
    # keeps it), but it lies 60 mm beside DM: no trunk imbalance (version 8).
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body
    from rasterserver.simulator.render import render

    seed = 41394
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "numbering_backs.py"
    spec = importlib.util.spec_from_file_location("numbering_backs_settings", path)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    settings = bench._settings(seed).replace(threads=1)
    st = clinic_station(seed, "w8-1to2")
    context = StageContext(calibration=st, raster=st.raster_definition)
    scene = make_body(random_body(seed))
    image = render(scene, st, settings=settings, seed=seed).image
    # the surface of peaks version 4, on which the case was found
    peaks_4 = {"peaks": {"flank_tolerance": 0.0, **PEAKS_5["peaks"]}}
    surface = run_chain(image, context=context, until="surface", params=peaks_4)["surface"]
    old = run_chain(
        surface,
        context=context,
        until="analysis",
        params={"analysis": {"vp_max_imbalance": None, "vp_region_below": 0.7}},
    )["analysis"]
    wrong = old.landmark("VP")
    assert wrong is not None
    assert np.linalg.norm(wrong - truth(scene)["landmarks"]["VP"]) > 80.0
    eight = run_chain(
        surface, context=context, until="analysis", params={"analysis": {"vp_region_below": 0.7}}
    )["analysis"]
    assert eight.landmark("VP") is None
    assert "beside DM" in eight.reason_table()["VP"]
    # version 9's region (0.45 W below the neck line) may leave another candidate, which
    # another check refuses (frames differ by processor): no wrong VP either way
    new = run_chain(surface, context=context, until="analysis")["analysis"]
    assert new.landmark("VP") is None
    assert new.landmark("DM") is not None  # the rest of the analysis stands


def test_dimples_across_a_hole_are_refused_and_dm_is_never_placed_in_one() -> None:
    # Fresh held-out clinic scene 42596 (benchmarks/clinic_analysis.py, kept frame; hands on
    # the hips, a waistband): two pits of the buttocks, 10 cm below the dimples, outscored
    # them with the skin midway between them unmeasured; DM there had no depth and version 8
    # failed on it. Version 9 refuses such a pair with its reason, and keeps the rest.
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body

    kept = np.load(Path(__file__).parents[1] / "data" / "scenes" / "body-42596.npz")
    st = clinic_station(42596, str(kept["code"]))
    context = StageContext(calibration=st, raster=st.raster_definition)
    shape = run_chain(kept["image"], context=context, until="analysis")["analysis"]
    assert isinstance(shape, BackShape) and shape.reason == ""
    reasons = shape.reason_table()
    for name in ("DL", "DR", "DM"):
        assert shape.landmark(name) is None and name in reasons
    # version 10 counts the grooves beside the pair too: the buttocks' row of concavities
    # refuses it first; without that check the pair is refused for the skin between them
    assert "row of" in reasons["DL"]
    assert reasons["frame"] == "needs VP, DL, DR and DM"
    point = shape.landmark("VP")
    assert point is not None
    assert np.linalg.norm(point - truth(make_body(random_body(42596)))["landmarks"]["VP"]) < 3
    unchecked = run_chain(
        kept["image"],
        context=context,
        until="analysis",
        params={"analysis": {"row_concavities": 0}},
    )["analysis"]
    for name in ("DL", "DR", "DM"):
        assert unchecked.landmark(name) is None
    assert "midway between the pair" in unchecked.reason_table()["DL"]


def test_a_carried_vp_leaves_the_stored_parameters_hash_alone() -> None:
    # the archive's stored analyses were hashed without the field: unset, it must not show
    from rasterserver_plugins.back_shape import BackShapeAnalysis

    from rasterserver.stage import params_hash

    plain = BackShapeAnalysis.Params()
    assert "vp_carried" not in plain.model_dump(mode="json")
    carried = BackShapeAnalysis.Params(vp_carried=(1.0, -200.0, 30.0))
    assert carried.model_dump(mode="json")["vp_carried"] == [1.0, -200.0, 30.0]
    assert params_hash(carried) != params_hash(plain)
    with pytest.raises(ValueError):
        BackShapeAnalysis.Params(vp_carried=(1.0, 2.0))


def test_a_symmetry_line_along_the_trunks_edge_is_refused() -> None:
    # Held-out clinic scene 43762 (benchmarks/clinic_analysis.py, kept frame; arms close, a
    # 54 mm lateral deviation): the left arm cuts the measured trunk near the curve's apex,
    # and the symmetry line ran along that edge, 85 mm off the spine; the midline's answer
    # was a deviation of -27 mm against the truth's +54 mm. Version 10 refuses the line.
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body

    kept = np.load(Path(__file__).parents[1] / "data" / "scenes" / "body-43762.npz")
    st = clinic_station(43762, str(kept["code"]))
    context = StageContext(calibration=st, raster=st.raster_definition)
    unchecked = run_chain(
        kept["image"], context=context, until="analysis", params={"analysis": {"line_edge_room": 0}}
    )["analysis"]
    tr = truth(make_body(random_body(43762)))
    true_max = tr["parameters"]["lateral_deviation_max_mm"]["value"]
    wrong = unchecked.parameter_table()["lateral_deviation_neg_max_mm"]["value"]
    assert true_max > 50.0 and wrong < -20.0  # the sign and size of the curve were wrong
    shape = run_chain(kept["image"], context=context, until="analysis")["analysis"]
    reasons = shape.reason_table()
    assert "trunk's edge" in reasons["symmetry_line"]
    assert len(shape.midline) == 0
    table = shape.parameter_table()
    for name in ("lateral_deviation_max_mm", "scoliosis_angle_deg", "kyphotic_angle_deg"):
        assert name not in table and name in reasons
    # the landmarks stand
    for name in ("VP", "DL", "DR", "DM"):
        point = shape.landmark(name)
        assert point is not None
        assert np.linalg.norm(point - tr["landmarks"][name]) < 3.0


def test_a_weak_convex_point_taken_for_vp_is_refused_by_version_12() -> None:
    # Clinic scene 60850 (benchmarks/clinic_analysis.py, kept frame; the w8-1to2 code, arms
    # away, a waistband): version 11 takes a weak convex point on the upper back for VP, 88 mm
    # from C7, with confidence 0.27 (the other 355 VPs of bodies 60800-60999 and their backs
    # had 0.70 or more, within 5.1 mm). Version 12 refuses a VP below confidence 0.5.
    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import clinic_station, make_body, random_body

    kept = np.load(Path(__file__).parents[1] / "data" / "scenes" / "body-60850.npz")
    st = clinic_station(60850, str(kept["code"]))
    context = StageContext(calibration=st, raster=st.raster_definition)
    v11 = run_chain(
        kept["image"], context=context, until="analysis",
        params={"analysis": {"vp_min_confidence": 0.0}},
    )["analysis"]  # fmt: skip
    true_vp = np.asarray(truth(make_body(random_body(60850)))["landmarks"]["VP"], dtype=float)
    found = v11.landmark("VP")
    assert found is not None and np.linalg.norm(found - true_vp) > 50.0
    assert v11.landmark_confidence[0] < 0.3
    shape = run_chain(kept["image"], context=context, until="analysis")["analysis"]
    assert BackShapeAnalysis.Params().vp_min_confidence == 0.5
    assert shape.landmark("VP") is None
    assert "confidence 0.27" in json.loads(shape.reasons)["VP"]
    # the dimples are found as before (their search starts at the candidate's height)
    for name in ("DL", "DR"):
        assert np.allclose(shape.landmark(name), v11.landmark(name))
