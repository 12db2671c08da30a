"""Stage 7, ``mesh.grid``: triangulation by index, normals, holes, empty input."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest
from rasterserver_plugins.mesh import GridMesh, grid_triangles

from rasterserver.errors import InputError
from rasterserver.records_surface import MeshRecord, Surface
from rasterserver.registry import Registry
from rasterserver.stage import StageContext, run_stage


def _surface(z: np.ndarray, *, spacing: float = 2.0) -> Surface:
    return Surface(x0=-10.0, y0=4.0, spacing=spacing, z=np.asarray(z, dtype=np.float64))


def _mesh(surface: Surface, **params) -> MeshRecord:
    return run_stage(GridMesh, surface, params, StageContext())


def test_found_through_the_entry_point() -> None:
    assert isinstance(Registry().discover().get("mesh.grid"), GridMesh)


def test_full_grid_two_triangles_per_cell_facing_the_camera() -> None:
    mesh = _mesh(_surface(np.zeros((3, 4))))
    assert mesh.vertices.shape == (12, 3) and mesh.triangles.shape == (12, 3)
    np.testing.assert_allclose(mesh.normals, np.tile([0.0, 0.0, -1.0], (12, 1)), atol=1e-12)
    np.testing.assert_allclose(mesh.vertices[0], [-10.0, 4.0, 0.0])
    np.testing.assert_allclose(mesh.vertices[-1], [-4.0, 8.0, 0.0])
    o3d_mesh = mesh.to_open3d()
    o3d_mesh.compute_triangle_normals()
    assert np.all(np.asarray(o3d_mesh.triangle_normals)[:, 2] < -0.999)
    assert o3d_mesh.is_edge_manifold() and o3d_mesh.is_vertex_manifold()


def test_cells_with_a_missing_corner_are_left_out() -> None:
    z = np.zeros((3, 3))
    z[0, 0] = np.nan  # one corner: its cell goes, the other three stay
    mesh = _mesh(_surface(z))
    assert mesh.triangles.shape == (6, 3)
    assert mesh.vertices.shape == (8, 3)
    z[1, 1] = np.nan  # the centre touches every cell
    assert _mesh(_surface(z)).triangles.shape == (0, 3)


def test_isolated_vertices_are_dropped() -> None:
    z = np.full((4, 4), np.nan)
    z[:2, :2] = 1.0
    z[3, 3] = 5.0  # a lone measured cell corner with no complete cell
    mesh = _mesh(_surface(z))
    assert mesh.vertices.shape == (4, 3)
    assert not np.any(mesh.vertices[:, 2] == 5.0)


def test_cells_split_along_the_shorter_diagonal() -> None:
    z = np.array([[0.0, 0.0], [0.0, 3.0]])  # a fold along 01-10 is shorter than along 00-11
    tri = grid_triangles(np.isfinite(z), z)
    edges = {tuple(sorted(e)) for t in tri for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
    assert (1, 2) in edges and (0, 3) not in edges
    tri = grid_triangles(np.isfinite(z), -z)
    edges = {tuple(sorted(e)) for t in tri for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}
    assert (1, 2) in edges
    z = np.array([[3.0, 0.0], [0.0, 0.0]])
    fixed = _mesh(_surface(z), shorter_diagonal=False)
    assert len(fixed.triangles) == 2


def test_normals_of_a_curved_surface_match_the_analytic_ones() -> None:
    radius = 300.0
    xs = np.arange(-60.0, 61.0, 3.0)
    gx, gy = np.meshgrid(xs, xs)
    z = -np.sqrt(radius**2 - gx**2 - gy**2) + radius  # sphere cap facing the camera
    surface = Surface(x0=-60.0, y0=-60.0, spacing=3.0, z=z)
    mesh = _mesh(surface)
    centre = np.array([0.0, 0.0, radius])
    expected = mesh.vertices - centre
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", mesh.normals, expected)
    inner = np.all(np.abs(mesh.vertices[:, :2]) < 57.0, axis=1)
    assert np.degrees(np.arccos(np.clip(cos[inner], -1, 1))).max() < 0.5
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-9)


def test_empty_surface_gives_an_empty_mesh_with_the_reason() -> None:
    mesh = _mesh(Surface.empty("no points; no numbered raster lines"))
    assert mesh.vertices.shape == (0, 3) and mesh.triangles.shape == (0, 3)
    assert "four measured corners" in mesh.reason
    assert "no numbered raster lines" in mesh.reason
    single_row = _mesh(_surface(np.zeros((1, 5))))
    assert single_row.triangles.shape == (0, 3)


def test_mesh_record_validation_and_round_trip() -> None:
    mesh = _mesh(_surface(np.arange(12.0).reshape(3, 4)))
    assert MeshRecord.from_arrays(mesh.to_arrays()) == mesh
    with pytest.raises(InputError, match="vertices that do not exist"):
        dataclasses.replace(mesh, triangles=mesh.triangles + 100)
    with pytest.raises(InputError, match="int32"):
        dataclasses.replace(mesh, triangles=mesh.triangles.astype(np.int64))
    with pytest.raises(InputError, match="normals"):
        dataclasses.replace(mesh, normals=mesh.normals[:-1])


def test_written_and_read_by_open3d(tmp_path) -> None:
    mesh = _mesh(_surface(np.random.default_rng(0).normal(size=(6, 7))))
    path = tmp_path / "m.ply"
    assert o3d.io.write_triangle_mesh(str(path), mesh.to_open3d())
    back = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_allclose(np.asarray(back.vertices), mesh.vertices, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(back.triangles), mesh.triangles)
