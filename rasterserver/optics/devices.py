"""The two devices of a station: the pinhole model with distortion and pose, the camera (pixels)
and the projector (an inverse camera in diapositive units, whose lines of constant ``v`` light
the surfaces that triangulation intersects)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from rasterserver.optics.distortion import (
    as_points,
    distort_normalized,
    undistort_normalized,
)


@dataclass(frozen=True, eq=False)
class PinholeDevice:
    """A central projection with OpenCV intrinsics and distortion (camera or projector).

    Attributes
    ----------
    K : numpy.ndarray
        ``(3, 3)`` intrinsic matrix in pixels (camera) or diapositive units (projector).
    dist : numpy.ndarray
        ``(5,)`` distortion ``(k1, k2, p1, p2, k3)``, OpenCV model, on normalised coordinates.
    R : numpy.ndarray
        ``(3, 3)`` rotation world → device.
    t : numpy.ndarray
        ``(3,)`` translation world → device in mm: ``p_dev = R @ p_world + t``.
    width, height : float
        Extent of the image (pixels) or diapositive (units); valid coordinates lie in
        ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    width: float = 0.0
    height: float = 0.0

    kind: ClassVar[str] = "device"

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.array(self.K, dtype=np.float64).reshape(3, 3))
        dist = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > 5:
            raise ValueError("only the 5 OpenCV coefficients (k1, k2, p1, p2, k3) are supported")
        dist[: given.size] = given
        object.__setattr__(self, "dist", dist)
        rot = np.array(self.R, dtype=np.float64).reshape(3, 3)
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise ValueError("R must be a proper rotation matrix")
        object.__setattr__(self, "R", rot)
        object.__setattr__(self, "t", np.array(self.t, dtype=np.float64).reshape(3))

    # ---------------------------------------------------------------- frames
    @property
    def centre(self) -> np.ndarray:
        """Projection centre in world mm, ``-R.T @ t``."""
        return -self.R.T @ self.t

    @property
    def axis(self) -> np.ndarray:
        """Unit optical axis (+z of the device) in the world frame."""
        return self.R[2].copy()

    def to_device(self, points_world: np.ndarray) -> np.ndarray:
        """World points ``(N, 3)`` → device coordinates ``(N, 3)`` (mm)."""
        pts = as_points(points_world, 3, "points")
        if np.array_equal(self.R, np.eye(3)):
            return pts + self.t
        return pts @ self.R.T + self.t

    # ---------------------------------------------------------------- intrinsics
    def normalized_to_image(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates → image coordinates ``(N, 2)`` via ``K``."""
        # python floats keep float32 inputs float32 (NEP 50)
        fx, s, cx, fy, cy = (float(c) for c in self.K[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]])
        return np.stack([fx * x + s * y + cx, fy * y + cy], axis=-1)

    def image_to_normalized(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates ``(N, 2)`` → distorted normalised coordinates via ``K⁻¹``."""
        k = self.K
        yd = (uv[:, 1] - k[1, 2]) / k[1, 1]
        xd = (uv[:, 0] - k[0, 2] - k[0, 1] * yd) / k[0, 0]
        return xd, yd

    # ---------------------------------------------------------------- projection
    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Project world points to image coordinates, with distortion.

        Parameters
        ----------
        points_world : numpy.ndarray
            ``(N, 3)`` points in world mm. Computed in float64, or in float32 if the points
            are float32 (fast, ~1e-4 px).

        Returns
        -------
        numpy.ndarray
            ``(N, 2)`` image coordinates ``(u, v)`` (column, row); NaN for points on or
            behind the device's focal plane.
        """
        pts = np.asarray(points_world)
        if pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == 3:
            # single precision on request (the renderer's millions of samples): ~1e-4 units
            t = [float(c) for c in self.t]
            if np.array_equal(self.R, np.eye(3)):
                xc, yc, zc = pts[:, 0] + t[0], pts[:, 1] + t[1], pts[:, 2] + t[2]
            else:
                pc = pts @ self.R.T.astype(np.float32) + self.t.astype(np.float32)
                xc, yc, zc = pc[:, 0], pc[:, 1], pc[:, 2]
        else:
            pc = self.to_device(pts)
            xc, yc, zc = pc[:, 0], pc[:, 1], pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = 1.0 / zc
            inv_z[~(zc > 0)] = np.nan
            x = xc * inv_z
            y = yc * inv_z
        xd, yd = distort_normalized(x, y, self.dist)
        return self.normalized_to_image(xd, yd)

    def rays(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rays through image coordinates (inverse of :meth:`project`).

        Parameters
        ----------
        pixels : numpy.ndarray
            ``(N, 2)`` image coordinates ``(u, v)``.

        Returns
        -------
        origins : numpy.ndarray
            ``(N, 3)`` ray origins: the projection centre (world mm).
        directions : numpy.ndarray
            ``(N, 3)`` unit directions in the world frame, pointing forward (z_dev > 0).
        """
        uv = as_points(pixels, 2, "pixels")
        xd, yd = self.image_to_normalized(uv)
        x, y = undistort_normalized(xd, yd, self.dist)
        d_dev = np.stack([x, y, np.ones_like(x)], axis=-1)
        d_dev /= np.linalg.norm(d_dev, axis=-1, keepdims=True)
        directions = d_dev @ self.R  # R.T @ d for each row
        origins = np.broadcast_to(self.centre, directions.shape).copy()
        return origins, directions

    def in_bounds(self, uv: np.ndarray) -> np.ndarray:
        """Whether image coordinates ``(N, 2)`` fall inside the image/diapositive area."""
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (see ``docs/formats.md``)."""
        return {
            "model": "opencv-pinhole",
            # integers for a camera's pixels, floats for a diapositive's extent
            "width": self.width if isinstance(self.width, int) else float(self.width),
            "height": self.height if isinstance(self.height, int) else float(self.height),
            "K": self.K.tolist(),
            "distortion": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "centre": self.centre.tolist(),
        }

    def key(self) -> str:
        """Stable text identifying the model's parameters (for caches)."""
        return json.dumps(self.to_dict(), sort_keys=True)


@dataclass(frozen=True, eq=False)
class Camera(PinholeDevice):
    """The recording camera: image coordinates in pixels, ``width`` columns x ``height`` rows."""

    kind: ClassVar[str] = "camera"

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def shape(self) -> tuple[int, int]:
        """Image array shape ``(height, width)``."""
        return int(self.height), int(self.width)


@dataclass(frozen=True, eq=False)
class Projector(PinholeDevice):
    """The raster projector, an inverse camera whose image is the diapositive.

    Its coordinates ``(u, v)`` are diapositive units; raster lines have constant ``v``.
    ``width``/``height`` bound the illuminated diapositive area.
    """

    kind: ClassVar[str] = "projector"

    def diapositive_coordinates(self, points_world: np.ndarray) -> np.ndarray:
        """Diapositive coordinates ``(N, 2)`` of the light reaching world points ``(N, 3)``.

        Same as :meth:`project`; NaN for points behind the projector.
        """
        return self.project(points_world)

    def light_plane(self, v: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World plane(s) of diapositive coordinate ``v`` ignoring distortion.

        Returns
        -------
        normals : numpy.ndarray
            ``(N, 3)`` unit plane normals (world).
        offsets : numpy.ndarray
            ``(N,)`` with ``normals @ p == offsets`` on the plane.
        """
        v_arr = np.atleast_1d(np.asarray(v, dtype=np.float64))
        y_n = (v_arr - self.K[1, 2]) / self.K[1, 1]
        n_dev = np.stack([np.zeros_like(y_n), np.ones_like(y_n), -y_n], axis=-1)
        n_world = n_dev @ self.R
        n_world /= np.linalg.norm(n_world, axis=-1, keepdims=True)
        return n_world, n_world @ self.centre

    def light_surface_intersection(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        v: np.ndarray | float,
        *,
        tol: float = 1e-9,
        max_iter: int = 50,
        planes: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Intersect rays with the light surfaces of diapositive coordinates ``v``.

        Without distortion the light surface of ``v`` is the plane through the projector
        centre containing the diapositive line ``v`` (closed form). With distortion it is a
        cone-like surface; starting from the plane solution, Newton's method on the ray
        parameter drives the projected ``v`` of the point to the requested value.

        Parameters
        ----------
        origins, directions : numpy.ndarray
            ``(N, 3)`` rays in world mm (directions need not be unit).
        v : float or numpy.ndarray
            Diapositive coordinate of the light surface, scalar or ``(N,)`` (one per ray).
        tol : float
            Convergence tolerance on ``v`` in diapositive units.
        max_iter : int
            Newton iterations at most.
        planes : tuple of numpy.ndarray, optional
            ``light_plane(v)`` when the caller has it (the planes of a raster's few hundred
            lines, gathered per ray, instead of one plane per ray).

        Returns
        -------
        numpy.ndarray
            ``(N, 3)`` world points; NaN where the ray misses the surface (parallel, behind
            the ray origin or behind the projector) or Newton did not converge.
        """
        o = as_points(origins, 3, "origins")
        d = as_points(directions, 3, "directions")
        v_arr = np.broadcast_to(np.asarray(v, dtype=np.float64), (o.shape[0],))
        n_w, off = self.light_plane(v_arr) if planes is None else planes
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (off - np.einsum("ij,ij->i", n_w, o)) / np.einsum("ij,ij->i", n_w, d)
        s = np.where(np.isfinite(s) & (s > 0), s, np.nan)
        if np.any(self.dist):
            s = self._newton_on_ray(o, d, v_arr, s, tol=tol, max_iter=max_iter)
        points = o + s[:, None] * d
        in_front = self.to_device(points)[:, 2] > 0
        points[~in_front] = np.nan
        return points

    def _newton_on_ray(
        self,
        o: np.ndarray,
        d: np.ndarray,
        v_target: np.ndarray,
        s: np.ndarray,
        *,
        tol: float,
        max_iter: int,
    ) -> np.ndarray:
        # compiled per ray (see light_surface_newton); imported here, not at start-up,
        # because importing numba costs ~0.3 s that commands without reconstruction skip
        from rasterserver.optics.light_surface_newton import newton_on_rays

        a = o @ self.R.T + self.t  # device coordinates of the origin
        b = d @ self.R.T  # device direction
        return newton_on_rays(
            np.ascontiguousarray(a),
            np.ascontiguousarray(b),
            np.ascontiguousarray(v_target, dtype=np.float64),
            np.ascontiguousarray(s, dtype=np.float64),
            float(self.K[1, 1]),
            float(self.K[1, 2]),
            np.asarray(self.dist, dtype=np.float64),
            float(tol),
            int(max_iter),
        )
