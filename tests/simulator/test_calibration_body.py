"""The control-point calibration body: layout, visibility in every configuration, files."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from rasterserver.errors import InputError
from rasterserver.optics import default_station
from rasterserver.simulator.calibration_body import (
    CONFIGURATIONS,
    CONTROL_POINTS_FORMAT,
    HOLE_LAYOUT,
    control_points,
    make_calibration_body,
    plate_placements,
    write_control_points,
)


def test_seven_holes_per_plate_two_plates_per_configuration() -> None:
    points = control_points()
    assert len(points) == 3 * 2 * 7
    assert len({p.id for p in points}) == len(points)
    for k in range(3):
        for plate in ("high", "low"):
            mine = [p for p in points if p.configuration == k and p.plate == plate]
            assert [p.index for p in mine] == list(range(7))
            assert len({p.z for p in mine}) == 1
    assert {p.z for p in points if p.plate == "high"} == {-100.0}
    assert {p.z for p in points if p.plate == "low"} == {100.0}


def test_every_lateral_place_carries_a_high_and_a_low_plate() -> None:
    used = {(p.plate, p.lateral) for k in range(3) for p in plate_placements(k)}
    assert used == {(h, lat) for h in ("high", "low") for lat in ("left", "centre", "right")}
    assert len(CONFIGURATIONS) == 3


def test_hole_pattern_identifies_points_and_orientation() -> None:
    layout = HOLE_LAYOUT - HOLE_LAYOUT.mean(0)
    # No rotation by 90°, 180° or 270° and no mirror maps the pattern onto itself.
    for transform in (
        np.array([[-1, 0], [0, -1]]),
        np.array([[0, -1], [1, 0]]),
        np.array([[0, 1], [-1, 0]]),
        np.array([[-1, 0], [0, 1]]),
        np.array([[1, 0], [0, -1]]),
    ):
        moved = layout @ transform.T
        d = np.linalg.norm(moved[:, None] - layout[None], axis=2).min(1)
        assert d.max() > 5.0
    # The marker is the only point with no neighbour in the grid pitch.
    pairwise = np.linalg.norm(HOLE_LAYOUT[:, None] - HOLE_LAYOUT[None], axis=2)
    assert pairwise[pairwise > 0].min() > 30.0  # holes far apart compared with their size


@pytest.mark.parametrize("configuration", [0, 1, 2])
def test_control_points_are_in_view_and_not_occluded(configuration: int) -> None:
    scene = make_calibration_body(configuration)
    station = default_station()
    pts = scene.landmarks["control_points"]
    uv = station.camera.project(pts)
    margin = 15.0
    assert (uv[:, 0] > margin).all() and (uv[:, 0] < station.camera.width - 1 - margin).all()
    assert (uv[:, 1] > margin).all() and (uv[:, 1] < station.camera.height - 1 - margin).all()
    rs = o3d.t.geometry.RaycastingScene()
    names = {}
    for obj in scene.objects:
        names[rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))] = obj.name
    for origin in (station.camera.centre, station.projector.centre):
        d = pts - origin
        dist = np.linalg.norm(d, axis=1)
        rays = np.hstack([np.broadcast_to(origin, d.shape), d / dist[:, None]])
        ans = rs.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        np.testing.assert_allclose(ans["t_hit"].numpy(), dist, atol=0.01)
        hit = [names[int(g)] for g in ans["geometry_ids"].numpy()]
        assert hit == ["plate-high"] * 7 + ["plate-low"] * 7
    # The whole hole disc, not just the centre, lies on its plate.
    for placement in plate_placements(configuration):
        w, h = placement.size
        local = placement.holes()[:, :2] - np.asarray(placement.centre[:2])
        assert (np.abs(local[:, 0]) + 4.5 < w / 2).all() and (
            np.abs(local[:, 1]) + 4.5 < h / 2
        ).all()


def test_holes_image_dark() -> None:
    scene = make_calibration_body(1, hole_radius=5.0)
    plate = scene.objects[0]
    assert plate.name == "plate-high"
    centres = scene.landmarks["control_points"][:7]
    assert np.allclose(plate.albedo(centres), 0.02)
    ring = centres + np.array([5.5, 0.0, 0.0])
    assert np.allclose(plate.albedo(ring), 0.7)
    inside = centres + np.array([0.0, 4.9, 0.0])
    assert np.allclose(plate.albedo(inside), 0.02)
    assert scene.metadata["hole_radius_mm"] == 5.0
    json.dumps(scene.metadata)
    for p in control_points(1):
        np.testing.assert_allclose(scene.landmarks[f"cp/{p.id}"], [p.x, p.y, p.z])


def test_write_control_points(tmp_path: Path) -> None:
    points = control_points()
    doc = json.loads(write_control_points(tmp_path / "cp.json", points).read_text())
    assert doc["format"] == CONTROL_POINTS_FORMAT and doc["units"] == "mm"
    assert len(doc["points"]) == 42
    first = doc["points"][0]
    assert set(first) >= {"id", "plate", "configuration", "x", "y", "z"}
    assert first["id"] == "c0-high-0"
    write_control_points(tmp_path / "cp.csv", points)
    with (tmp_path / "cp.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 42 and float(rows[5]["x"]) == pytest.approx(points[5].x)


def test_without_base() -> None:
    names = [o.name for o in make_calibration_body(0, base=False).objects]
    assert names == ["plate-high", "plate-low"]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"configuration": 3},
        {"configuration": -1},
        {"configuration": 1.5},
        {"configuration": 0, "hole_radius": 0.0},
        {"configuration": 0, "hole_radius": float("nan")},
        {"configuration": 0, "hole_albedo": 0.9},
        {"configuration": 0, "plate_albedo": 2.0},
    ],
)
def test_bad_calibration_body_input(kwargs: dict) -> None:
    with pytest.raises(InputError):
        make_calibration_body(**kwargs)


# --- the body as a clinic's camera sees it (issue 13) --------------------------------------


def test_real_body_has_a_bright_base_columns_mounting_holes_and_uneven_light() -> None:
    from rasterserver.simulator.calibration_body import REAL_BODY, UnevenLight, real_body

    scene = real_body(0)
    names = [o.name for o in scene.objects]
    assert names == ["plate-high", "column-high-0", "column-high-1", "plate-low",
                     "column-low-0", "column-low-1", "base"]
    base = scene.objects[-1]
    assert REAL_BODY["base_albedo"] >= 0.7
    # mounting holes at the columns of the other configurations are dark
    other = plate_placements(1)[0].columns()[0]
    assert base.albedo(np.array([[*other, 300.0]]))[0] < 0.05
    light = UnevenLight()
    grid = np.stack(np.meshgrid(np.linspace(-300, 300, 7), np.linspace(-300, 300, 7),
                                [-100.0, 300.0]), -1).reshape(-1, 3)
    factor = light(grid)
    assert (factor > 0).all() and (factor <= 1).all() and factor.max() / factor.min() > 1.5
    assert scene.metadata["columns"] and scene.metadata["mount_holes"]
    json.dumps(scene.metadata)


@pytest.mark.parametrize("configuration", [0, 1, 2])
def test_real_body_control_points_are_seen_and_columns_show(configuration: int) -> None:
    """Columns never cover a hole, and they show beyond the plates' outline."""
    from rasterserver.simulator.calibration_body import random_hole_layout, real_body

    layout = random_hole_layout(np.random.default_rng(configuration))
    scene = real_body(configuration, layout=layout)
    station = default_station()
    pts = scene.landmarks["control_points"]
    rs = o3d.t.geometry.RaycastingScene()
    names = {}
    for obj in scene.objects:
        names[rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(obj.mesh))] = obj.name
    origin = station.camera.centre
    d = pts - origin
    rays = np.hstack([np.broadcast_to(origin, d.shape), d / np.linalg.norm(d, axis=1)[:, None]])
    ans = rs.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    hit = [names[int(g)] for g in ans["geometry_ids"].numpy()]
    assert hit == ["plate-high"] * 7 + ["plate-low"] * 7
    # a ray just above each plate's top edge meets the column, not the base
    for placement in plate_placements(configuration):
        x, y, z = placement.centre
        top = np.array([x, y - placement.size[1] / 2 - 5.0, z])
        ray = np.hstack([origin, (top - origin) / np.linalg.norm(top - origin)])
        g = rs.cast_rays(o3d.core.Tensor(ray[None].astype(np.float32)))["geometry_ids"]
        assert names[int(g.numpy()[0])].startswith(f"column-{placement.plate}")


def test_any_seven_hole_layout_is_used_and_written(tmp_path: Path) -> None:
    from rasterserver.simulator.calibration_body import random_hole_layout

    layout = random_hole_layout(np.random.default_rng(4))
    points = control_points(2, layout=layout)
    high = np.array([[p.x, p.y] for p in points if p.plate == "high"])
    np.testing.assert_allclose(high - high.mean(0), layout - layout.mean(0))
    doc = json.loads(write_control_points(tmp_path / "cp.json", points, layout=layout)
                     .read_text())
    np.testing.assert_allclose(doc["hole_layout"]["plate_coordinates_mm"], layout)
    scene = make_calibration_body(2, layout=layout)
    assert scene.metadata["hole_layout_mm"] == layout.tolist()
    gaps = np.linalg.norm(layout[:, None] - layout[None], axis=2)
    assert gaps[gaps > 0].min() >= 45.0


@pytest.mark.parametrize(
    ("layout", "message"),
    [
        (np.zeros((6, 2)), "7 finite points"),
        (np.array([[0.0, float("nan")]] * 7), "7 finite points"),
        (HOLE_LAYOUT + np.array([0.0, 80.0]), "off the"),
        (np.array([[0.0, 10.0 * i] for i in range(7)]), "closer than four radii"),
    ],
)
def test_bad_layout_is_refused(layout: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        make_calibration_body(0, layout=layout)
