"""The level frame: world axes turned so that one of them is plumb, and the surface in it.

Clinical "vertical" and "horizontal" refer to gravity, not to the camera. The station's
calibration gives the direction of gravity in the world frame (``Station.gravity``, a unit
vector pointing down; ``[0, 1, 0]`` when the world's Y axis is plumb, as for the default
station and a calibration on the control-point body). The analysis works in the **level
frame**:

* ``y'`` along gravity (down);
* ``z'`` the camera's optical axis (world Z) made horizontal: the station's sagittal
  direction, anterior (the patient stands with his back to the camera);
* ``x'`` = ``y' × z'``, horizontal, to the patient's right (world X when the camera is not
  rolled).

Rows of the level grid are then horizontal profiles (sections perpendicular to gravity) and
its columns plumb lines. When gravity is the world's Y axis the level frame *is* the world
frame and the surface is used as it is; otherwise it is resampled onto a level grid of the
same spacing: each level cell ``(x', y')`` is the point of the surface on the horizontal line
``x' ex + y' ey + w ez``, found by a few fixed-point steps on the bilinear interpolation of the
world grid (the surface is a height field along ``z'`` as long as the camera looks roughly
horizontally, which :meth:`LevelFrame.from_gravity` checks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LevelFrame", "LevelGrid", "bilinear"]

#: Largest angle (degrees) between the camera's optical axis and the horizontal plane.
MAX_CAMERA_TILT_DEG = 45.0


def bilinear(z: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of the grid ``z`` at fractional ``(col, row)``.

    NaN outside the grid and wherever one of the four cells around the point is NaN (so a
    hole's border does not leak into the result).
    """
    ny, nx = z.shape
    col = np.asarray(col, dtype=float)
    row = np.asarray(row, dtype=float)
    inside = (col >= 0) & (col <= nx - 1) & (row >= 0) & (row <= ny - 1)
    c = np.where(inside, col, 0.0)
    r = np.where(inside, row, 0.0)
    j0 = np.minimum(np.floor(c).astype(np.intp), max(nx - 2, 0))
    i0 = np.minimum(np.floor(r).astype(np.intp), max(ny - 2, 0))
    j1 = np.minimum(j0 + 1, nx - 1)
    i1 = np.minimum(i0 + 1, ny - 1)
    fx, fy = c - j0, r - i0
    out = (
        z[i0, j0] * (1 - fx) * (1 - fy)
        + z[i0, j1] * fx * (1 - fy)
        + z[i1, j0] * (1 - fx) * fy
        + z[i1, j1] * fx * fy
    )
    return np.where(inside, out, np.nan)


@dataclass(frozen=True)
class LevelGrid:
    """A height field on a regular grid of the level frame.

    Cell ``[i, j]`` is the level point ``(x0 + j * spacing, y0 + i * spacing, z[i, j])``.
    """

    x0: float
    y0: float
    spacing: float
    z: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(ny, nx)``."""
        return int(self.z.shape[0]), int(self.z.shape[1])

    def x_of(self, col: np.ndarray | float) -> np.ndarray:
        """Level ``x'`` (mm) of fractional column(s)."""
        return self.x0 + self.spacing * np.asarray(col, dtype=float)

    def y_of(self, row: np.ndarray | float) -> np.ndarray:
        """Level ``y'`` (mm) of fractional row(s)."""
        return self.y0 + self.spacing * np.asarray(row, dtype=float)

    def col_of(self, x: np.ndarray | float) -> np.ndarray:
        """Fractional column of level ``x'`` (mm)."""
        return (np.asarray(x, dtype=float) - self.x0) / self.spacing

    def row_of(self, y: np.ndarray | float) -> np.ndarray:
        """Fractional row of level ``y'`` (mm)."""
        return (np.asarray(y, dtype=float) - self.y0) / self.spacing

    def depth(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Depth ``z'`` (mm) at level ``(x', y')``, bilinear; NaN off the surface."""
        return bilinear(self.z, self.col_of(x), self.row_of(y))

    def point(self, col: float, row: float) -> np.ndarray | None:
        """The level point ``(x', y', z')`` at a fractional cell, None off the surface."""
        z = float(bilinear(self.z, np.array([col]), np.array([row]))[0])
        if not math.isfinite(z):
            return None
        return np.array([float(self.x_of(col)), float(self.y_of(row)), z])


@dataclass(frozen=True)
class LevelFrame:
    """Rotation between the world frame and the level frame.

    Attributes
    ----------
    rotation : numpy.ndarray
        ``(3, 3)``; its rows are the level axes ``x'``, ``y'`` (gravity), ``z'`` in world
        coordinates, so ``level = world @ rotation.T`` and ``world = level @ rotation``.
    """

    rotation: np.ndarray

    @classmethod
    def from_gravity(cls, gravity: np.ndarray) -> LevelFrame:
        """The level frame of a station whose gravity (world, pointing down) is ``gravity``.

        Raises
        ------
        ValueError
            For a vector that is not finite and non-zero, or a camera looking more than
            :data:`MAX_CAMERA_TILT_DEG` up or down.
        """
        g = np.asarray(gravity, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(g))
        if not (np.all(np.isfinite(g)) and norm > 0):
            raise ValueError(f"gravity must be a finite non-zero vector, got {g.tolist()}")
        ey = g / norm
        optical = np.array([0.0, 0.0, 1.0])
        tilt = math.degrees(math.asin(min(1.0, abs(float(optical @ ey)))))
        if tilt > MAX_CAMERA_TILT_DEG:
            raise ValueError(
                f"the camera looks {tilt:.0f}° up or down from the horizontal (at most "
                f"{MAX_CAMERA_TILT_DEG:.0f}°): the back is not a height field seen from it"
            )
        ez = optical - (optical @ ey) * ey
        ez /= np.linalg.norm(ez)
        ex = np.cross(ey, ez)
        return cls(rotation=np.stack([ex, ey, ez]))

    @property
    def is_identity(self) -> bool:
        """Whether the level frame is the world frame (to rounding)."""
        return bool(np.allclose(self.rotation, np.eye(3), atol=1e-12))

    def to_level(self, points: np.ndarray) -> np.ndarray:
        """World points ``(..., 3)`` in level coordinates."""
        return np.asarray(points, dtype=float) @ self.rotation.T

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Level points ``(..., 3)`` in world coordinates."""
        return np.asarray(points, dtype=float) @ self.rotation

    def vectors_to_world(self, vectors: np.ndarray) -> np.ndarray:
        """Level directions ``(..., 3)`` in world coordinates (rotation only)."""
        return np.asarray(vectors, dtype=float) @ self.rotation

    def level_grid(
        self, x0: float, y0: float, spacing: float, z: np.ndarray, *, iterations: int = 6
    ) -> LevelGrid:
        """The world height field ``z`` (grid origin ``x0, y0``) on a level grid.

        Parameters
        ----------
        x0, y0, spacing : float
            The world grid (as :class:`~rasterserver.records_surface.Surface`).
        z : numpy.ndarray
            ``(ny, nx)`` world depths, NaN where not measured.
        iterations : int, optional
            Fixed-point steps per cell (each divides the error by about the tilt times the
            surface slope).

        Returns
        -------
        LevelGrid
            Same spacing; NaN where the level point falls off the measured surface.
        """
        z = np.asarray(z, dtype=np.float64)
        if self.is_identity or z.size == 0:
            return LevelGrid(float(x0), float(y0), float(spacing), z)
        _ny, _nx = z.shape
        ii, jj = np.nonzero(np.isfinite(z))
        if ii.size == 0:
            return LevelGrid(float(x0), float(y0), float(spacing), z)
        world = np.column_stack([x0 + spacing * jj, y0 + spacing * ii, z[ii, jj]])
        level = self.to_level(world)
        lo = np.floor(level[:, :2].min(axis=0) / spacing) * spacing
        hi = level[:, :2].max(axis=0)
        mx, my = (np.floor((hi - lo) / spacing).astype(int) + 1).tolist()
        u, h = np.meshgrid(lo[0] + spacing * np.arange(mx), lo[1] + spacing * np.arange(my))
        ex, ey, ez = self.rotation
        w = np.full(u.shape, float(np.median(level[:, 2])))
        for _ in range(iterations):
            p = u[..., None] * ex + h[..., None] * ey + w[..., None] * ez
            zs = bilinear(z, (p[..., 0] - x0) / spacing, (p[..., 1] - y0) / spacing)
            # The surface point below p along world Z, and its level depth: the new w.
            q = p.copy()
            q[..., 2] = zs
            w = np.where(np.isfinite(zs), q @ ez, w)
            hit = np.isfinite(zs)
        return LevelGrid(float(lo[0]), float(lo[1]), float(spacing), np.where(hit, w, np.nan))
