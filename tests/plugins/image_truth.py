"""Simulated frames with exact ground truth for the tests of the image-processing stages.

Renderings are cached per process (one takes seconds). ``truth_of_peaks`` matches detected
peaks to the simulator's exact line-centre rows, so every test compares against the ground
truth, never against an earlier output of the stages themselves.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import open3d as o3d

from rasterserver.optics import Station, default_station
from rasterserver.raster import Raster
from rasterserver.simulator.back import make_back, preset
from rasterserver.simulator.ground_truth import LineRows
from rasterserver.simulator.render import Rendering, RenderSettings, render
from rasterserver.simulator.scene import Scene, SceneObject


@lru_cache(maxsize=1)
def station() -> Station:
    """The seed's station (604 x 576 portrait camera, default raster)."""
    return default_station()


@lru_cache(maxsize=8)
def back(name: str, *, supersampling: int = 1, seed: int = 1) -> Rendering:
    """A preset back (``normal``, ``moderate``, ``severe``) at default noise."""
    settings = RenderSettings(supersampling=supersampling)
    return render(make_back(preset(name)), station(), settings=settings, seed=seed)


def plane_scene(z: float = 0.0, *, albedo: float = 0.6) -> Scene:
    """A flat wall facing the camera at depth ``z`` (mm), larger than the field of view."""
    half = 600.0
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    triangles = np.array([[0, 2, 1], [0, 3, 2]])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles)
    )
    mesh.compute_vertex_normals()
    return Scene(objects=[SceneObject("wall", mesh, albedo)])


@lru_cache(maxsize=2)
def wall(*, supersampling: int = 1, seed: int = 3) -> Rendering:
    """The flat wall at default noise."""
    settings = RenderSettings(supersampling=supersampling)
    return render(plane_scene(), station(), settings=settings, seed=seed)


def truth_of_peaks(
    col: np.ndarray,
    row: np.ndarray,
    line_rows: LineRows,
    *,
    tol: float = 1.5,
    resolve: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth line number and row of each peak (-1 / NaN when no line centre is near).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_rows : LineRows
        The simulator's exact line-centre rows.
    tol : float
        Largest distance (px) from a peak to its line centre in the same column.
    resolve : float
        Two line centres closer than this (px) in a column (where a line emerges from
        behind a fold) make a single peak whose line cannot be told: such peaks get -1.
    """
    gc, gr, gn = line_rows.column, line_rows.row, line_rows.number
    order = np.lexsort((gr, gc))
    gc, gr, gn = gc[order].astype(np.int64), gr[order], gn[order]
    span = 1e5
    kg = gc * span + gr
    kp = col.astype(np.int64) * span + row
    if kg.size == 0 or kp.size == 0:
        return np.full(kp.size, -1, np.int64), np.full(kp.size, np.nan)
    last = kg.size - 1
    j = np.clip(np.searchsorted(kg, kp), 1, max(last, 1))
    j0 = np.clip(j - 1, 0, last)
    j1 = np.clip(j, 0, last)
    e0, e1 = np.abs(kg[j0] - kp), np.abs(kg[j1] - kp)
    jj = np.where(e0 < e1, j0, j1)
    near = np.minimum(e0, e1) < tol
    for side in (np.clip(jj - 1, 0, last), np.clip(jj + 1, 0, last)):
        near &= ~((side != jj) & (np.abs(kg[side] - kg[jj]) < resolve))
    return np.where(near, gn[jj], -1), np.where(near, gr[jj], np.nan)


def synthetic_lines(
    shape: tuple[int, int] = (120, 80),
    *,
    spacing: float = 10.0,
    sigma: float = 1.0,
    amplitude: float = 120.0,
    background: float = 10.0,
    tilt: float = 0.05,
    noise: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tilted Gaussian lines integrated over each pixel's area, as an 8-bit image.

    Returns
    -------
    image : numpy.ndarray
        ``(H, W)`` uint8.
    cols, rows : numpy.ndarray
        The exact line centres per column (flattened, sorted by column then row).
    """
    from scipy.special import erf

    h, w = shape
    centres = np.arange(spacing, h - spacing, spacing)
    c = np.arange(w)
    rows_exact = centres[None, :] + tilt * (c[:, None] - w / 2.0) + 0.37
    edges = np.arange(h + 1) - 0.5
    img = np.full((h, w), background, dtype=np.float64)
    for k in range(rows_exact.shape[1]):
        z = (edges[:, None] - rows_exact[None, :, k]) / (np.sqrt(2.0) * sigma)
        cdf = 0.5 * (1.0 + erf(z))
        img += amplitude * np.sqrt(2.0 * np.pi) * sigma * np.diff(cdf, axis=0)
    if noise > 0:
        img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    cols = np.repeat(c, rows_exact.shape[1])
    return image, cols, rows_exact.ravel()


def truth_lines(
    rendering: Rendering, *, shading: float = 0.5, noise: float = 0.02, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact line-centre peaks of a rendering with areas from the raster's line kinds.

    The area of a peak is its line width (1.5 heavy, 1 light) times a smooth shading
    (relative amplitude ``shading``) times log-normal noise, so numbering can be tested on
    known-good lines and kinds.

    Returns
    -------
    col, row, area, number : numpy.ndarray
        Sorted by ``(col, row)``.
    """
    lr = rendering.line_rows
    raster = rendering_raster()
    heavy = dict(zip(raster.numbers.tolist(), raster.code.tolist(), strict=True))
    order = np.lexsort((lr.row, lr.column))
    col, row, number = lr.column[order], lr.row[order], lr.number[order]
    kind = np.array([heavy[int(n)] for n in number])
    shade = 1.0 + shading * np.sin(col / 90.0) * np.cos(row / 130.0)
    rng = np.random.default_rng(seed)
    area = 100.0 * np.where(kind == 1, 1.5, 1.0) * shade * np.exp(rng.normal(0, noise, col.size))
    return col.astype(np.int32), row, area.astype(np.float32), number.astype(np.int64)


def rendering_raster() -> Raster:
    """The raster of :func:`station`."""
    return station().raster_definition
