"""The compiled cell triangles against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.mesh import grid_triangles


def _passes(valid: np.ndarray, z: np.ndarray | None) -> np.ndarray:
    """mesh.grid_triangles of rasterserver 0.x."""
    ny, nx = valid.shape
    if ny < 2 or nx < 2:
        return np.zeros((0, 3), dtype=np.int64)
    cell = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    i, j = np.nonzero(cell)
    v00 = i * nx + j
    v01 = v00 + 1
    v10 = v00 + nx
    v11 = v10 + 1
    if z is None:
        main = np.zeros(i.size, dtype=bool)
    else:
        main = np.abs(z[i, j] - z[i + 1, j + 1]) < np.abs(z[i, j + 1] - z[i + 1, j])
    t1 = np.where(main[:, None], np.column_stack([v00, v10, v11]), np.column_stack([v00, v10, v01]))
    t2 = np.where(main[:, None], np.column_stack([v00, v11, v01]), np.column_stack([v01, v10, v11]))
    return np.concatenate([t1, t2])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_depth", [True, False])
def test_same_triangles_as_the_passes(seed: int, with_depth: bool) -> None:
    rng = np.random.default_rng(seed)
    valid = rng.random((60, 80)) < 0.85
    z = rng.normal(0, 5, valid.shape)
    z[rng.random(valid.shape) < 0.05] = np.nan  # NaN depths compare false either way
    depth = z if with_depth else None
    got = grid_triangles(valid, depth)
    np.testing.assert_array_equal(got, _passes(valid, depth))
    assert got.dtype == np.int64 and got.shape[0] > 1000


@pytest.mark.parametrize("shape", [(1, 5), (5, 1), (2, 2), (0, 0)])
def test_degenerate_grids(shape: tuple[int, int]) -> None:
    valid = np.ones(shape, dtype=bool)
    got = grid_triangles(valid, np.zeros(shape))
    np.testing.assert_array_equal(got, _passes(valid, np.zeros(shape)))
    assert got.shape == ((2, 3) if shape == (2, 2) else (0, 3))


def test_used_vertices_as_the_passes() -> None:
    from rasterserver_plugins.grid_cells import used_vertices

    rng = np.random.default_rng(4)
    valid = rng.random((30, 40)) < 0.7
    triangles = grid_triangles(valid, rng.normal(0, 1, valid.shape))
    flat, tri = used_vertices(triangles, valid.size)
    used = np.zeros(valid.size, dtype=bool)
    used[triangles.ravel()] = True
    np.testing.assert_array_equal(flat, np.flatnonzero(used))
    np.testing.assert_array_equal(tri, (np.cumsum(used) - 1)[triangles].astype(np.int32))
    assert tri.dtype == np.int32
    none = used_vertices(np.zeros((0, 3), dtype=np.int64), 12)
    assert none[0].size == 0 and none[1].shape == (0, 3)
