"""Comparison of two visits against the simulator's truth: registration, distance and
asymmetry maps, refusals, and the files (PLY read back by pymeshlab, PNG)."""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
import pytest

from rasterserver.comparison import (
    THRESHOLDS,
    TOP_MARGIN,
    ComparisonRefusedError,
    Thresholds,
    Visit,
    asymmetry_change,
    asymmetry_fit,
    asymmetry_map,
    distance_map,
    landmark_frame,
    landmark_transform,
    measured_height,
    pair_frames,
    register,
    submesh,
    trunk_mask,
)
from rasterserver.comparison.geometry import rotation_angle
from rasterserver.comparison_files import colour_limit, write_distance_ply, write_distance_png
from rasterserver.records_analysis import BackShape
from rasterserver.records_surface import MeshRecord, Surface
from rasterserver.simulated_visits import progressed
from rasterserver.simulator.back import BackParameters, make_back, posture_sway, preset

BASE = preset("moderate")  # main curve: apex t = 0.35, 15 mm to the right, rotated 8°


@lru_cache(maxsize=4)
def visit(params: BackParameters, seed: int, label: str) -> Visit:
    """Render, reconstruct and analyse a back (a few seconds; once per test process)."""
    from rasterserver.optics import default_station
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.render import RenderSettings, render
    from rasterserver.stage import StageContext

    station = default_station()
    image = render(make_back(params), station, settings=RenderSettings(supersampling=1), seed=seed)
    context = StageContext(calibration=station, raster=station.raster_definition)
    records = run_chain(image.image, context=context, until="analysis")
    surface, shape = records["surface"], records["analysis"]
    mesh = run_chain(surface, context=context, until="mesh")["mesh"]
    assert isinstance(surface, Surface) and isinstance(shape, BackShape)
    assert isinstance(mesh, MeshRecord) and not shape.reason
    return Visit(surface, mesh, shape, label=label)


def first() -> Visit:
    return visit(BASE, 1, "first")


def apex_band(v: Visit, vertices: np.ndarray, half: float = 40.0) -> np.ndarray:
    vp, dm = v.shape.landmark("VP"), v.shape.landmark("DM")
    assert vp is not None and dm is not None
    apex_y = vp[1] + BASE.curves[0].apex * (dm[1] - vp[1])
    return np.abs(vertices[:, 1] - apex_y) < half


def test_landmark_transform_maps_frames_onto_each_other() -> None:
    a = first().shape
    angle = np.radians(4.0)
    turn = np.array(
        [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    )
    shift = np.array([12.0, -7.0, 30.0])
    b = dataclasses.replace(
        a, frame_origin=turn @ a.frame_origin + shift, frame_axes=a.frame_axes @ turn.T
    )
    t = landmark_transform(a, b)
    np.testing.assert_allclose(t[:3, :3], turn.T, atol=1e-9)
    np.testing.assert_allclose(t[:3, :3] @ b.frame_origin + t[:3, 3], a.frame_origin, atol=1e-9)
    np.testing.assert_allclose(landmark_transform(a, a), np.eye(4), atol=1e-12)


def test_posture_change_registers_to_no_change() -> None:
    a = first()
    b = visit(posture_sway(BASE, 3, translation=5.0, rotation=1.0), 2, "swayed")
    reg = register(a, b)
    assert reg.fitness > 0.95 and reg.rmse < 2.0
    stats = distance_map(a, b, reg).statistics()
    assert stats["rms_mm"] < 0.5
    assert abs(stats["mean_mm"]) < 0.2
    assert stats["overlap"] > 0.98
    assert stats["area_above_2mm_mm2"] == 0.0 and stats["area_below_minus_2mm_mm2"] == 0.0


def test_progression_shows_at_the_apex_with_the_right_sign() -> None:
    a = first()
    b = visit(progressed(BASE, 1, 0.5), 3, "progressed")  # rotation 8° -> 12°, hump right
    dmap = distance_map(a, b, register(a, b))
    stats = dmap.statistics()
    assert stats["max_abs_mm"] is not None and abs(stats["max_abs_mm"]) > 4.0
    at = np.array(stats["max_abs_at"])
    assert apex_band(a, at[None, :], half=60.0)[0]
    # the right (+X) side turned further back (+), the left side forward (-)
    assert np.sign(at[0]) == np.sign(stats["max_abs_mm"])
    band = apex_band(a, dmap.vertices) & np.isfinite(dmap.distance)
    right = band & (dmap.vertices[:, 0] > 40)
    left = band & (dmap.vertices[:, 0] < -40)
    assert np.mean(dmap.distance[right]) > 1.5
    assert np.mean(dmap.distance[left]) < -1.5


def test_asymmetry_map_shows_the_hump_side_and_its_growth() -> None:
    a, b = first(), visit(progressed(BASE, 1, 0.5), 3, "progressed")
    sym_a, sym_b = asymmetry_map(a), asymmetry_map(b)
    band = apex_band(a, sym_a.vertices) & np.isfinite(sym_a.distance)
    right = band & (sym_a.vertices[:, 0] > 40)
    left = band & (sym_a.vertices[:, 0] < -40)
    assert np.mean(sym_a.distance[right]) > 3.0  # the rib hump on the right
    assert np.mean(sym_a.distance[left]) < -3.0
    change = asymmetry_change(sym_a, sym_b, register(a, b))
    grown = right & np.isfinite(change.distance)
    assert grown.sum() > 100
    assert np.mean(change.distance[grown]) > 1.0


def test_trunk_leaves_out_head_buttocks_and_edges() -> None:
    a = first()
    keep = trunk_mask(a, a.mesh.vertices)
    vp, dm = a.shape.landmark("VP"), a.shape.landmark("DM")
    assert 0 < keep.sum() < len(keep)
    y = a.mesh.vertices[keep, 1]
    assert y.min() >= vp[1] - 5.0 and y.max() <= dm[1] + 5.0
    assert not trunk_mask(a, np.array([[0.0, vp[1] - 60.0, 0.0]]))[0]  # the neck


def without_vp(v: Visit, label: str) -> Visit:
    shape = dataclasses.replace(
        v.shape,
        landmarks=np.vstack([np.full(3, np.nan), v.shape.landmarks[1:]]),
        frame_origin=np.full(3, np.nan),
        frame_axes=np.full((3, 3), np.nan),
        reasons='{"VP": "no neck in view"}',
    )
    return dataclasses.replace(v, shape=shape, label=label)


def test_missing_landmarks_are_refused_with_the_reason() -> None:
    a = first()
    b = without_vp(a, "cropped")
    version_1 = dataclasses.replace(THRESHOLDS, partial_frame=False)
    with pytest.raises(ComparisonRefusedError, match=r"cropped has no body-fixed frame.*VP"):
        register(a, b, thresholds=version_1)
    version_2 = dataclasses.replace(THRESHOLDS, frame_without_vp=False)
    with pytest.raises(ComparisonRefusedError, match=r"cropped has no body-fixed frame.*VP"):
        register(b, without_vp(a, "also"), thresholds=version_2)  # neither visit has VP
    dimples = np.isin(np.arange(len(a.shape.landmarks)), [1, 2])  # DL, DR
    shape = dataclasses.replace(
        b.shape, landmarks=np.where(dimples[:, None], np.nan, b.shape.landmarks)
    )
    with pytest.raises(ComparisonRefusedError, match="no body-fixed frame"):
        register(a, dataclasses.replace(b, shape=shape))  # no dimples: no frame at all
    with pytest.raises(ComparisonRefusedError, match="no neck in view"):
        asymmetry_map(b)


def test_a_visit_without_vp_is_registered_from_the_dimples_and_the_vertical() -> None:
    a = first()
    b = visit(posture_sway(BASE, 3, translation=5.0, rotation=1.0), 2, "swayed")
    full = register(a, b)
    for x, y in ((a, without_vp(b, "cropped")), (without_vp(a, "cropped"), b)):
        reg = register(x, y)
        assert reg.start_from is not None and "VP of visit cropped not found" in reg.start_from
        assert "VP, DL and DR" in full.summary()["landmark_start_from"]
        assert reg.summary()["landmark_start_from"] == reg.start_from
        # the same alignment as with both body frames, and no change on the trunk
        err = reg.transform @ np.linalg.inv(full.transform)
        assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 0.05
        assert np.linalg.norm(err[:3, 3]) < 0.5
        stats = distance_map(x, y, reg).statistics()
        assert stats["rms_mm"] < 0.3 and stats["vertices"] > 0.8 * len(
            distance_map(a, b, full).vertices
        )
    # as the stage runs it: the gravity travels with the visits, the record keeps the note
    from rasterserver.pair_comparison import compare_pair, pack, registration_of

    record = compare_pair(pack(a, without_vp(b, "cropped")))
    assert not record.refused and record.start_from is not None
    assert registration_of(record).start_from == record.start_from
    shape = dataclasses.replace(b.shape, level_axes=None)  # an analysis without gravity
    with pytest.raises(ComparisonRefusedError, match="no body-fixed frame"):
        register(a, without_vp(dataclasses.replace(b, shape=shape), "cropped"))


def test_two_visits_without_vp_are_registered_below_the_measured_top() -> None:
    a = first()
    b = visit(posture_sway(BASE, 3, translation=5.0, rotation=1.0), 2, "swayed")
    full = register(a, b)
    x, y = without_vp(a, "first"), without_vp(b, "second")
    reg = register(x, y)
    assert reg.start_from is not None and "VP of neither visit found" in reg.start_from
    err = reg.transform @ np.linalg.inv(full.transform)
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 0.05
    assert np.linalg.norm(err[:3, 3]) < 0.5
    stats = distance_map(x, y, reg).statistics()
    assert stats["rms_mm"] < 0.3
    # the trunk compared ends below VP: the measured top (or the neck) less the margin
    fa, fb, _note = pair_frames(x, y)
    vp = a.shape.landmark("VP")
    lower = min(
        measured_height(x, fa.origin, fa.axes[1]), measured_height(y, fb.origin, fb.axes[1])
    )
    assert fa.height == pytest.approx(lower - TOP_MARGIN) == fb.height
    assert 250.0 <= fa.height < float((vp - fa.origin) @ fa.axes[1])
    keep = trunk_mask(x, x.mesh.vertices, frame=fa)
    assert keep.sum() > 0.6 * trunk_mask(a, a.mesh.vertices).sum()
    assert ((x.mesh.vertices[keep] - fa.origin) @ fa.axes[1]).max() <= fa.height + 1e-9
    # the stage record keeps the note
    from rasterserver.pair_comparison import compare_pair, pack

    record = compare_pair(pack(x, y))
    assert not record.refused and record.start_from == reg.start_from


def test_two_visits_without_vp_and_too_little_trunk_are_refused() -> None:
    a = first()
    dm = a.shape.landmark("DM")
    # the surface measured only up to 200 mm above DM (hair down to the shoulder blades)
    lost = a.surface.coordinates()[1][:, None] < dm[1] - 200.0
    z = np.where(lost, np.nan, a.surface.z)
    cut = dataclasses.replace(a, surface=dataclasses.replace(a.surface, z=z))
    reason = r"neither visit's VP was found.*less than 250 mm.*no body-fixed frame"
    with pytest.raises(ComparisonRefusedError, match=reason):
        register(without_vp(a, "first"), without_vp(cut, "second"))


def test_measured_height_stops_at_the_neck_and_at_gaps() -> None:
    a = first()
    origin, axes = landmark_frame(a.shape, "a")
    vp = a.shape.landmark("VP")
    height = measured_height(a, origin, axes[1])
    assert height > 300.0
    dm = a.shape.landmark("DM")
    ys = a.surface.coordinates()[1][:, None]
    gap = (ys < dm[1] - 150.0) & (ys > dm[1] - 170.0)  # a band lost across the back
    holed = dataclasses.replace(
        a, surface=dataclasses.replace(a.surface, z=np.where(gap, np.nan, a.surface.z))
    )
    assert measured_height(holed, origin, axes[1]) < 155.0
    empty = dataclasses.replace(a, surface=Surface.empty("nothing"))
    assert measured_height(empty, origin, axes[1]) == 0.0
    assert float((vp - origin) @ axes[1]) > 0.0


def test_empty_surface_is_refused() -> None:
    a = first()
    b = Visit(Surface.empty("no raster lines"), MeshRecord.empty("no surface"), a.shape, "empty")
    with pytest.raises(ComparisonRefusedError, match="too little measured trunk"):
        register(a, b)


def test_surfaces_that_do_not_overlap_are_refused() -> None:
    a = first()
    away = np.array([0.0, 0.0, -80.0])  # the surface 80 mm off where the landmarks say
    mesh = dataclasses.replace(a.mesh, vertices=a.mesh.vertices + away)
    b = dataclasses.replace(a, mesh=mesh, label="elsewhere")
    with pytest.raises(ComparisonRefusedError, match=r"could not be registered.*overlaps"):
        register(a, b)


def test_files_load_in_meshlab_with_the_values(tmp_path) -> None:
    pymeshlab = pytest.importorskip("pymeshlab")
    a = first()
    b = visit(progressed(BASE, 1, 0.5), 3, "progressed")
    dmap = distance_map(a, b, register(a, b))
    path = write_distance_ply(dmap, tmp_path / "map.ply", comments=["visits first -> progressed"])
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    mesh = ms.current_mesh()
    values = dmap.distance[np.isfinite(dmap.distance)]
    assert mesh.vertex_number() == values.size
    assert mesh.face_number() > 0
    np.testing.assert_allclose(mesh.vertex_scalar_array(), values, atol=1e-5)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "property float scalar_distance" in header and "comment unit mm" in header
    png = write_distance_png(dmap, tmp_path / "map.png", title="first -> progressed")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {p.name for p in tmp_path.iterdir()} == {"map.ply", "map.png"}  # no temporary left


def test_colour_limit_is_symmetric_whole_and_has_a_floor() -> None:
    assert colour_limit(np.array([np.nan, 0.1, -0.2])) == 2.0
    assert colour_limit(np.linspace(-7.2, 3.0, 1000)) == 8.0
    assert colour_limit(np.array([])) == 2.0


def _scene_mesh(params: BackParameters) -> MeshRecord:
    """The simulator's true surface (trunk and arms) as one mesh."""
    scene = make_back(params)
    vertices, triangles, n = [], [], 0
    for o in scene.objects:
        vertices.append(np.asarray(o.mesh.vertices, dtype=float))
        triangles.append(np.asarray(o.mesh.triangles) + n)
        n += len(vertices[-1])
    v = np.vstack(vertices)
    return MeshRecord(vertices=v, triangles=np.vstack(triangles).astype(np.int32), normals=0 * v)


def test_a_local_change_is_mapped_within_half_a_millimetre_of_the_truth() -> None:
    from rasterserver.comparison import signed_distances

    a = first()
    main = BASE.curves[0]
    hump = BASE.with_primary_curve(rotation=main.rotation + 3.0)  # the rib hump rises
    c = visit(hump, 4, "hump")
    dmap = distance_map(a, c, register(a, c))
    # the true change along A's normals: distance to C's true surface minus to A's
    to_c = signed_distances(dmap.vertices, dmap.normals, _scene_mesh(hump), limit=60.0)
    to_a = signed_distances(dmap.vertices, dmap.normals, _scene_mesh(BASE), limit=60.0)
    truth = to_c - to_a
    ok = np.isfinite(truth) & np.isfinite(dmap.distance)
    assert ok.sum() > 0.9 * len(truth)
    assert np.percentile(np.abs(truth[ok]), 99) > 2.0  # there is a change to find
    error = dmap.distance[ok] - truth[ok]
    assert float(np.sqrt(np.mean(error**2))) <= 0.5


def test_trend_flags_against_the_simulated_truth() -> None:
    from rasterserver.trends import TrendVisit, trends

    a = first()
    again = visit(BASE, 5, "again")  # the same back, other sensor noise
    wider = BASE.with_primary_curve(lateral_deviation=BASE.curves[0].lateral_deviation + 5.0)
    grown = visit(wider, 6, "grown")

    def flagged(x: Visit, y: Visit) -> set[str]:
        table = trends([TrendVisit(v.label, None, v.shape.parameter_table()) for v in (x, y)])
        return {row["parameter"] for row in table if row["first_to_last"]["flagged"]}

    assert flagged(a, again) == set()  # noise only: nothing flagged
    assert "lateral_deviation_max_mm" in flagged(a, grown)  # +5 mm: flagged


def _holed_with_a_part_behind(v: Visit, point: np.ndarray, radius: float, depth: float) -> Visit:
    """``v`` with a hole of ``radius`` mm in its mesh at ``point`` and a 40 mm square of
    surface ``depth`` mm behind it (a fold's other side, an arm seen through a gap)."""
    mesh = v.mesh
    centres = mesh.vertices[mesh.triangles].mean(axis=1)
    kept = mesh.triangles[np.linalg.norm(centres - point, axis=1) > radius]
    normal = mesh.normals[np.argmin(np.linalg.norm(mesh.vertices - point, axis=1))]
    normal = normal / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    steps = np.linspace(-20.0, 20.0, 21)
    gu, gw = np.meshgrid(steps, steps)
    sheet = point - depth * normal + gu.reshape(-1, 1) * u + gw.reshape(-1, 1) * w
    n = len(steps)
    tri = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            tri += [(a, b, d), (a, d, c)]
    off = len(mesh.vertices)
    holed = MeshRecord(
        vertices=np.vstack([mesh.vertices, sheet]),
        triangles=np.vstack([kept, np.asarray(tri, dtype=kept.dtype) + off]),
        normals=np.vstack([mesh.normals, np.tile(normal, (len(sheet), 1))]),
    )
    return dataclasses.replace(v, mesh=holed)


def test_the_asymmetry_map_takes_no_value_through_a_hole_of_the_mirror_image() -> None:
    # A hole on the left of the back, with another part of the surface 25 mm behind it: the
    # mirror image has the hole on the right, and normals there pass through it.
    a = first()
    origin, axes = landmark_frame(a.shape, a.label)
    vp, dm = a.shape.landmark("VP"), a.shape.landmark("DM")
    assert vp is not None and dm is not None
    lower = np.abs(a.mesh.vertices[:, 1] - (vp[1] + 0.8 * (dm[1] - vp[1]))) < 10.0
    side = (a.mesh.vertices - origin) @ axes[0]
    left = np.flatnonzero(lower & (np.abs(side + 50.0) < 5.0))
    assert left.size
    holed = _holed_with_a_part_behind(a, a.mesh.vertices[left[0]], radius=8.0, depth=25.0)
    version_2 = dataclasses.replace(THRESHOLDS, through_slack=None)
    plain = asymmetry_map(a, thresholds=version_2)
    kept = asymmetry_map(holed, thresholds=version_2)
    checked = asymmetry_map(holed)
    n = len(plain.vertices)  # the trunk's own vertices come first, the part behind after
    np.testing.assert_array_equal(kept.vertices[:n], plain.vertices)
    # version 2 maps the part behind the hole where the back has its counterpart
    through = np.abs(kept.distance[:n] - plain.distance) > 10.0
    assert through.sum() >= 3
    assert np.isnan(checked.distance[:n][through]).all()
    # elsewhere version 3 maps the holed back as it maps the back itself (whose own few
    # through-hole hits, at the outline, it leaves out too)
    own = asymmetry_map(a).distance
    np.testing.assert_allclose(checked.distance[:n][~through], own[~through], atol=0.05)


def _plane(v: Visit, thresholds: Thresholds, across: np.ndarray) -> tuple[float, float]:
    """Where the mirror fit puts the trunk's centre across the body (mm) and its turn (°)."""
    amap, transform, _, _ = asymmetry_fit(v, thresholds=thresholds)
    centre = amap.vertices.mean(axis=0)
    moved = transform[:3, :3] @ centre + transform[:3, 3] - centre
    return float(moved @ across), rotation_angle(transform[:3, :3])


def test_the_mirror_fit_does_not_slide_onto_an_arm_held_before_one_flank() -> None:
    # The right flank, from 60 mm out, pushed 15 mm towards the camera (an arm held close
    # before it): fitted on every trunk point (version 3) the mirror plane slides sideways
    # onto it; fitted on the trunk seen alike on both sides (version 4) it stays where the
    # back alone puts it.
    a = first()
    origin, axes = landmark_frame(a.shape, a.label)
    side = (a.mesh.vertices - origin) @ axes[0]
    push = 15.0 * np.clip((side - 60.0) / 20.0, 0.0, 1.0)
    armed = dataclasses.replace(
        a,
        mesh=MeshRecord(
            vertices=a.mesh.vertices + push[:, None] * axes[2],
            triangles=a.mesh.triangles,
            normals=a.mesh.normals,
        ),
    )
    version_3 = dataclasses.replace(THRESHOLDS, mirror_reach=None)
    alone = _plane(a, THRESHOLDS, axes[0])
    fitted = _plane(armed, THRESHOLDS, axes[0])
    slid = _plane(armed, version_3, axes[0])
    assert abs(fitted[0] - alone[0]) < 3.0 and abs(fitted[1] - alone[1]) < 1.0
    assert abs(slid[0] - _plane(a, version_3, axes[0])[0]) > 8.0


def test_too_little_trunk_seen_on_both_sides_refuses_the_asymmetry_map() -> None:
    a = first()
    origin, axes = landmark_frame(a.shape, a.label)
    # the left of the back not measured (a whole flank in shadow or behind an arm)
    keep = (a.mesh.vertices - origin) @ axes[0] > 20.0
    half = dataclasses.replace(a, mesh=submesh(a.mesh, keep))
    with pytest.raises(ComparisonRefusedError, match="seen alike on both sides"):
        asymmetry_fit(half)


def _clinic_visit(role: str, params: dict[str, dict[str, object]] | None = None) -> Visit:
    """Clinic tuning person 44's acquisition ``role`` (kept frame, chain run here with the
    stage parameters ``params``)."""
    from kept_visits import kept_visit

    return kept_visit(f"person-44-{role}", f"44:{role}", params)[0]


def test_an_unchanged_clinic_back_keeps_its_asymmetry_map_between_acquisitions() -> None:
    # Clinic tuning person 44 (arms away, hair over the nape), acquired twice unchanged in
    # one dress (benchmarks/clinic_comparison.py's A and D): on the surfaces of peaks version
    # 4 version 3's mirror fit slid at D (its plane turned 5.7°), an 8 mm rms asymmetry
    # change; version 4 keeps it under 1 mm. (Peaks version 5's surfaces, a few more
    # crossings under the hair, do not make version 3 slide: both keep it there.)
    from scipy.spatial import cKDTree

    # numbering version 25 with them, as the case was found (version 29's line-end steps
    # move the change to 1.01 mm there; with the installed peaks it is 0.14 mm either way)
    numbers_25 = {"meet_tolerance": 0.0, "outer_gap": 0.0, "one_sided_peaks": 5}
    peaks_4 = {"peaks": {"flank_tolerance": 0.0}, "numbers": numbers_25}
    a, d = _clinic_visit("A", peaks_4), _clinic_visit("D", peaks_4)

    def change(thresholds: Thresholds) -> float:
        ma, md = asymmetry_map(a, thresholds=thresholds), asymmetry_map(d, thresholds=thresholds)
        gap, index = cKDTree(md.vertices).query(ma.vertices)
        ok = (gap < 3.0) & np.isfinite(ma.distance) & np.isfinite(md.distance[index])
        assert ok.sum() > 5000
        return float(np.sqrt(np.mean((md.distance[index] - ma.distance)[ok] ** 2)))

    assert change(THRESHOLDS) < 1.0
    assert change(dataclasses.replace(THRESHOLDS, mirror_reach=None)) > 5.0
    a, d = _clinic_visit("A"), _clinic_visit("D")  # the installed peaks
    assert change(THRESHOLDS) < 1.0
