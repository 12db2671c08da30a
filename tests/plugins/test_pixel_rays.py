"""The compiled ray interpolation against the whole-array passes it replaced: the same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.pixel_rays import interpolated_rays


def _passes(table: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """The interpolation of reconstruction.camera_rays of rasterserver 0.x."""
    h, w = table.shape[1:]
    r0 = np.clip(np.floor(row).astype(np.intp), 0, max(h - 2, 0))
    f = row - r0
    flat = r0 * w + col.astype(np.intp)
    below = flat + (w if h > 1 else 0)
    tx, ty = table[0].reshape(-1), table[1].reshape(-1)
    device = np.empty((col.size, 3))
    x0, y0 = tx[flat], ty[flat]
    device[:, 0] = x0 + f * (tx[below] - x0)
    device[:, 1] = y0 + f * (ty[below] - y0)
    device[:, 2] = 1.0
    return device


def _table(h: int, w: int, seed: int) -> np.ndarray:
    """Normalised coordinates of a distorted pinhole camera, as the ray table holds them."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (cols - w / 2) / 800.0, (rows - h / 2) / 800.0
    k = 1.0 + rng.uniform(-0.2, 0.2) * (x * x + y * y)
    return np.ascontiguousarray(np.stack([x * k, y * k]))


@pytest.mark.parametrize("seed", range(3))
def test_same_rays(seed: int) -> None:
    h, w = 120, 160
    table = _table(h, w, seed)
    rng = np.random.default_rng(seed)
    n = 20000
    col = rng.integers(0, w, n).astype(np.int32)
    row = rng.uniform(-0.5, h - 0.5, n)
    row[:200] = np.round(row[:200])  # whole rows
    row[200:210] = [-0.5, -0.25, 0.0, h - 1.0, h - 0.75, h - 0.5, 1e-12, h - 2.0, 0.5, 1.0]
    got = interpolated_rays(table, col, row)
    assert got.tobytes() == _passes(table, col, row).tobytes()
    col64 = col.astype(np.int64)
    assert interpolated_rays(table, col64, row).tobytes() == _passes(table, col64, row).tobytes()


def test_one_row_one_point_none() -> None:
    table = _table(1, 50, 0)
    col, row = np.array([3, 49]), np.array([-0.5, 0.4])
    assert interpolated_rays(table, col, row).tobytes() == _passes(table, col, row).tobytes()
    table = _table(40, 50, 1)
    col, row = np.array([7]), np.array([12.3])
    assert interpolated_rays(table, col, row).tobytes() == _passes(table, col, row).tobytes()
    none = interpolated_rays(table, np.zeros(0, np.int64), np.zeros(0))
    assert none.shape == (0, 3)
