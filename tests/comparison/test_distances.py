"""Signed distances along the normals: hits through a hole of the other surface."""

from __future__ import annotations

import numpy as np
import pytest

from rasterserver.comparison import signed_distances
from rasterserver.records_surface import MeshRecord


def _sheet(z: float, *, half: float = 40.0, step: float = 2.0, hole: float = 0.0) -> MeshRecord:
    """A square grid at depth ``z``, the squares within ``hole`` mm of the axis left out."""
    n = round(2 * half / step) + 1
    xs = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(xs, xs)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    triangles = []
    for i in range(n - 1):
        for j in range(n - 1):
            cx, cy = 0.5 * (xs[j] + xs[j + 1]), 0.5 * (xs[i] + xs[i + 1])
            if hole and np.hypot(cx, cy) < hole:
                continue
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            triangles += [(a, b, d), (a, d, c)]
    normals = np.tile([0.0, 0.0, -1.0], (len(vertices), 1))
    return MeshRecord(
        vertices=vertices, triangles=np.asarray(triangles, dtype=np.int32), normals=normals
    )


def _two_sheets(hole: float) -> MeshRecord:
    """The surface at depth 0 with a hole, and another part of it 20 mm behind."""
    front, back = _sheet(0.0, hole=hole), _sheet(20.0)
    return MeshRecord(
        vertices=np.vstack([front.vertices, back.vertices]),
        triangles=np.vstack([front.triangles, back.triangles + len(front.vertices)]),
        normals=np.vstack([front.normals, back.normals]),
    )


def test_a_hit_through_a_hole_is_no_counterpart() -> None:
    mesh = _two_sheets(hole=5.0)
    points = np.array([[0.0, 0.0, 0.5], [20.0, 20.0, 0.5], [0.0, 0.0, 0.5]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    kept = signed_distances(points, normals, mesh, limit=30.0)
    assert kept[0] == pytest.approx(19.5, abs=1e-4)  # version 3: the part behind the hole
    checked = signed_distances(points, normals, mesh, limit=30.0, through_slack=3.0)
    assert np.isnan(checked[0])
    assert checked[1] == pytest.approx(-0.5, abs=1e-4)  # beside the hole: the surface itself


def test_a_real_change_is_kept() -> None:
    # a tilted surface 8 mm away (30° to the normal): 9.2 mm along the normal, 8 mm nearest
    sheet = _sheet(0.0)
    angle = np.radians(30.0)
    turn = np.array(
        [[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]
    )
    tilted = MeshRecord(
        vertices=sheet.vertices @ turn.T + [0.0, 0.0, 8.0 / np.cos(angle)],
        triangles=sheet.triangles,
        normals=sheet.normals @ turn.T,
    )
    got = signed_distances(
        np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), tilted, limit=30.0, through_slack=3.0
    )
    assert got[0] == pytest.approx(8.0 / np.cos(angle), abs=1e-3)


def test_no_points_and_no_triangles() -> None:
    mesh = _sheet(0.0)
    assert signed_distances(np.zeros((0, 3)), np.zeros((0, 3)), mesh, limit=30.0).size == 0
    empty = MeshRecord.empty("nothing")
    got = signed_distances(np.zeros((2, 3)), np.ones((2, 3)), empty, limit=30.0, through_slack=3.0)
    assert np.isnan(got).all()
