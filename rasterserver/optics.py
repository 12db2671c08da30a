"""The station's geometry: camera, projector and the light surfaces of the raster lines.

One implementation shared by the simulator, the reconstruction and the calibration.

Conventions (OpenCV)
--------------------
* World frame, millimetres: X to the right as the camera sees it, Y down (towards the floor),
  Z away from the camera into the patient. The origin lies on the nominal back plane on the
  camera's optical axis.
* A device (camera or projector) has extrinsics ``R`` (3x3) and ``t`` (3,) mapping world to
  device coordinates, ``p_dev = R @ p_world + t``; device axes are x right, y down, z forward
  (along the optical axis). The projection centre in the world is ``-R.T @ t``.
* Intrinsics ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` and distortion
  ``(k1, k2, p1, p2, k3)`` as in ``cv2.projectPoints``: an ideal normalised point
  ``(x, y) = (X/Z, Y/Z)`` is distorted to ``(xd, yd)`` and mapped by ``K`` to pixel
  coordinates; integer pixel coordinates are pixel *centres* (the top-left pixel's centre is
  ``(0, 0)``, its area spans ``[-0.5, 0.5]²``). ``u`` is the column, ``v`` the row.
* The projector is an inverse camera with the same model; its "pixels" are *diapositive
  coordinates* ``(u, v)`` in diapositive units. Raster lines are lines of constant ``v``. The
  set of world points whose diapositive coordinate is ``v`` (the *light surface* of ``v``) is
  a plane through the projector centre without distortion and a cone-like surface with it.

Everything is vectorised over leading ``(N, ...)`` arrays, in float64.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

if TYPE_CHECKING:
    from rasterserver.raster import Raster

#: ``format`` tag of the calibration JSON (see ``docs/formats.md``).
CALIBRATION_FORMAT = "rasterserver.calibration/1"

_UNDISTORT_TOL = 1e-13  # normalised units: ~1e-10 px at f = 2000 px
_UNDISTORT_MAX_ITER = 30


def _as_points(points: np.ndarray, dim: int, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{what} must have shape (N, {dim}), got {arr.shape}")
    return arr


def distort_normalized(
    x: np.ndarray, y: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the OpenCV distortion ``(k1, k2, p1, p2, k3)`` to ideal normalised coordinates.

    Parameters
    ----------
    x, y : numpy.ndarray
        Ideal normalised coordinates ``X/Z``, ``Y/Z`` (any matching shapes).
    dist : numpy.ndarray
        ``(5,)`` distortion coefficients.

    Returns
    -------
    xd, yd : numpy.ndarray
        Distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    # the common one-term lens takes fewer passes over the renderer's big arrays
    one_term = k2 == 0.0 and k3 == 0.0
    radial = 1.0 + k1 * r2 if one_term else 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if p1 == 0.0 and p2 == 0.0:
        return x * radial, y * radial
    xy = x * y
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    return xd, yd


def _distortion_jacobian(
    x: np.ndarray, y: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Partial derivatives ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)`` of :func:`distort_normalized`."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    dxx = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    dxy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return dxx, dxy, dyx, dyy


def undistort_normalized(
    xd: np.ndarray, yd: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort_normalized` by Newton's method (2x2 Jacobian per point).

    Converges to ~1e-13 normalised units (1e-10 px at f = 2000 px) for any distortion that is
    invertible over the field of view; ``cv2.undistortPoints`` stops far earlier.

    Parameters
    ----------
    xd, yd : numpy.ndarray
        Distorted normalised coordinates.
    dist : numpy.ndarray
        ``(5,)`` distortion coefficients.

    Returns
    -------
    x, y : numpy.ndarray
        Ideal normalised coordinates.
    """
    xd = np.asarray(xd, dtype=np.float64)
    yd = np.asarray(yd, dtype=np.float64)
    if not np.any(dist):
        return xd.copy(), yd.copy()
    x, y = xd.copy(), yd.copy()
    for _ in range(_UNDISTORT_MAX_ITER):
        fx_, fy_ = distort_normalized(x, y, dist)
        rx, ry = fx_ - xd, fy_ - yd
        a, b, c, d = _distortion_jacobian(x, y, dist)
        det = a * d - b * c
        dx = (d * rx - b * ry) / det
        dy = (a * ry - c * rx) / det
        x -= dx
        y -= dy
        step = np.nanmax(np.abs(dx), initial=0.0) + np.nanmax(np.abs(dy), initial=0.0)
        if step < _UNDISTORT_TOL:
            break
    return x, y


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
        pts = _as_points(points_world, 3, "points")
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
        uv = _as_points(pixels, 2, "pixels")
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

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PinholeDevice:
        """Inverse of :meth:`to_dict`, checked by :mod:`rasterserver.documents`; ``centre`` is
        derived (a stored one must agree)."""
        from rasterserver.documents import device_from_document

        return device_from_document(cls, data, source=cls.kind)

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

        Returns
        -------
        numpy.ndarray
            ``(N, 3)`` world points; NaN where the ray misses the surface (parallel, behind
            the ray origin or behind the projector) or Newton did not converge.
        """
        o = _as_points(origins, 3, "origins")
        d = _as_points(directions, 3, "directions")
        v_arr = np.broadcast_to(np.asarray(v, dtype=np.float64), (o.shape[0],))
        n_w, off = self.light_plane(v_arr)
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
        a = o @ self.R.T + self.t  # device coordinates of the origin
        b = d @ self.R.T  # device direction
        fy, cy = self.K[1, 1], self.K[1, 2]
        s = s.copy()
        converged = np.zeros(s.shape, dtype=bool)
        for _ in range(max_iter):
            pc = a + s[:, None] * b
            with np.errstate(divide="ignore", invalid="ignore"):
                x = pc[:, 0] / pc[:, 2]
                y = pc[:, 1] / pc[:, 2]
                dx = (b[:, 0] - x * b[:, 2]) / pc[:, 2]
                dy = (b[:, 1] - y * b[:, 2]) / pc[:, 2]
            _, yd = distort_normalized(x, y, self.dist)
            _, _, dyx, dyy = _distortion_jacobian(x, y, self.dist)
            g = fy * yd + cy - v_target
            dg = fy * (dyx * dx + dyy * dy)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = g / dg
            converged = np.abs(g) < tol
            if np.all(converged | ~np.isfinite(s)):
                break
            s = np.where(converged, s, s - step)
            s = np.where(s > 0, s, np.nan)
        # one last residual check: Newton may have wandered (e.g. grazing rays)
        pc = a + s[:, None] * b
        with np.errstate(divide="ignore", invalid="ignore"):
            _, yd = distort_normalized(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2], self.dist)
        bad = ~(np.abs(fy * yd + cy - v_target) < max(tol, 1e-7) * 10)
        s[bad] = np.nan
        return s


def rotation_matrix(rx_deg: float = 0.0, ry_deg: float = 0.0, rz_deg: float = 0.0) -> np.ndarray:
    """World → device rotation from angles about the device's x, y, z axes (degrees).

    ``R = Rz @ Ry @ Rx`` applied to the untilted device looking along +Z; a positive ``rx``
    tilts the optical axis towards -Y (up).
    """
    ax, ay, az = np.deg2rad([rx_deg, ry_deg, rz_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclass(frozen=True, eq=False)
class Station:
    """A calibrated rasterstereography station: camera, projector and raster diapositive.

    Attributes
    ----------
    camera : Camera
    projector : Projector
    raster : Raster or str
        The raster diapositive, inline or by the name of a built-in definition
        (:func:`rasterserver.raster.get_raster`).
    name : str
        Station / calibration label.
    gravity : numpy.ndarray or None
        ``(3,)`` unit vector: the direction of gravity (down) in the world frame, or None
        when unknown. ``[0, 1, 0]`` when the world's Y axis is plumb, as for the default
        station and a calibration from the control-point body.
    """

    camera: Camera
    projector: Projector
    raster: Raster | str = "default"
    name: str = "default"
    gravity: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.gravity is not None:
            g = np.array(self.gravity, dtype=np.float64).reshape(3)
            if not (np.all(np.isfinite(g)) and abs(np.linalg.norm(g) - 1.0) <= 1e-6):
                raise ValueError(f"gravity must be a finite unit vector, got {g.tolist()}")
            object.__setattr__(self, "gravity", g)

    @property
    def raster_definition(self) -> Raster:
        """The :class:`~rasterserver.raster.Raster`, resolving a built-in name."""
        from rasterserver.raster import Raster, get_raster

        if isinstance(self.raster, Raster):
            return self.raster
        return get_raster(self.raster)

    @property
    def base(self) -> float:
        """Stereo base: distance between camera and projector centres (mm)."""
        return float(np.linalg.norm(self.projector.centre - self.camera.centre))

    def triangulate(
        self, pixels: np.ndarray, v: np.ndarray | float, *, tol: float = 1e-9
    ) -> np.ndarray:
        """3-D points from image points and the diapositive ``v`` of their raster line.

        The camera ray through each image point is intersected with the light surface of
        its ``v`` (:meth:`Projector.light_surface_intersection`): the reconstruction of the
        seed, in one call.

        Parameters
        ----------
        pixels : numpy.ndarray
            ``(N, 2)`` image coordinates ``(column, row)`` of raster line points.
        v : float or numpy.ndarray
            Diapositive ``v`` of each point's line (scalar or ``(N,)``).
        tol : float
            Newton tolerance in diapositive units (distorted projector only).

        Returns
        -------
        numpy.ndarray
            ``(N, 3)`` world points in mm (NaN where the ray misses the light surface).
        """
        origins, directions = self.camera.rays(pixels)
        return self.projector.light_surface_intersection(origins, directions, v, tol=tol)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready calibration (format ``rasterserver.calibration/1``)."""
        from rasterserver.raster import Raster

        raster: Any = self.raster.to_dict() if isinstance(self.raster, Raster) else self.raster
        return {
            "format": CALIBRATION_FORMAT,
            "name": self.name,
            "units": "mm",
            "conventions": (
                "OpenCV: device coordinates x right, y down, z forward; p_dev = R @ p_world + t; "
                "integer image coordinates are pixel centres; distortion (k1, k2, p1, p2, k3)"
            ),
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "raster": raster,
            **({} if self.gravity is None else {"gravity": self.gravity.tolist()}),
        }

    def to_json(self, *, indent: int | None = 2) -> str:
        """Serialise to the calibration JSON text."""
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Station:
        """Inverse of :meth:`to_dict`, checked by
        :func:`rasterserver.documents.calibration_from_document`.

        Raises
        ------
        InputError
            The document is refused (the message names the field).
        """
        from rasterserver.documents import calibration_from_document

        return calibration_from_document(data)

    @classmethod
    def from_json(cls, text: str) -> Station:
        """Parse and check a calibration JSON text (see :meth:`from_dict`)."""
        from rasterserver.documents import load_calibration_document

        return load_calibration_document(text)

    def save(self, path: str | Path) -> Path:
        """Write the calibration JSON to ``path``."""
        path = Path(path)
        path.write_text(self.to_json() + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Station:
        """Read and check a calibration JSON file (see :meth:`from_dict`)."""
        from rasterserver.documents import load_calibration_document

        return load_calibration_document(Path(path))


def default_station(
    width: int = 576,
    height: int = 604,
    *,
    distance: float = 2000.0,
    base: float = 800.0,
    focal_mm: float = 16.0,
    pixel_pitch_mm: float | None = None,
    camera_distortion: tuple[float, ...] = (-0.05, 0.0, 0.0, 0.0, 0.0),
    projector_distortion: tuple[float, ...] = (-0.01, 0.0, 0.0, 0.0, 0.0),
    projector_focal: float = 2000.0,
    diapositive_size: tuple[float, float] = (1000.0, 1000.0),
    raster: Raster | str = "default",
    name: str = "default",
) -> Station:
    """The seed's station: portrait camera at D = 2 m, projector 0.8 m above it.

    Parameters
    ----------
    width, height : int
        Image columns and rows (portrait: 576 x 604 as in the seed).
    distance : float
        Working distance D (mm): camera and projector centres lie at ``Z = -distance``.
    base : float
        Stereo base B (mm): the projector sits at ``Y = -base`` (above the camera), so depth
        moves the horizontal raster lines across image rows.
    focal_mm : float
        Camera focal length (mm).
    pixel_pitch_mm : float, optional
        Pixel pitch (mm). By default 8 µm x 576 / ``width``, which keeps the seed's field of
        view (≈ 1 px per mm at D = 2 m for 576 columns) for any sensor size.
    camera_distortion, projector_distortion : tuple of float
        OpenCV ``(k1, k2, p1, p2, k3)``.
    projector_focal : float
        Projector focal length in diapositive units. With 2000 units at D = 2000 mm one unit
        is 1 mm on the plane Z = 0.
    diapositive_size : (float, float)
        Diapositive extent ``(width, height)`` in units. The principal point is offset
        (a shifted diapositive) so that the world origin maps to the diapositive centre.
    raster : Raster or str
        Raster definition or built-in name.
    name : str
        Station label.

    Returns
    -------
    Station
    """
    pitch = 0.008 * 576.0 / width if pixel_pitch_mm is None else pixel_pitch_mm
    f_px = focal_mm / pitch
    # principal point slightly off-centre, as in a real camera
    cx = (width - 1) / 2.0 + 0.004 * width
    cy = (height - 1) / 2.0 - 0.003 * height
    camera = Camera(
        K=np.array([[f_px, 0.0, cx], [0.0, f_px, cy], [0.0, 0.0, 1.0]]),
        dist=np.asarray(camera_distortion, dtype=np.float64),
        R=np.eye(3),
        t=np.array([0.0, 0.0, distance]),
        width=width,
        height=height,
    )
    dw, dh = diapositive_size
    # world origin seen from the projector: normalised (0, base/distance) → diapositive centre
    cu = (dw - 1) / 2.0
    cv = (dh - 1) / 2.0 - projector_focal * base / distance
    projector = Projector(
        K=np.array([[projector_focal, 0.0, cu], [0.0, projector_focal, cv], [0.0, 0.0, 1.0]]),
        dist=np.asarray(projector_distortion, dtype=np.float64),
        R=np.eye(3),
        t=np.array([0.0, base, distance]),
        width=dw,
        height=dh,
    )
    # the world's Y axis points down (towards the floor) by the conventions above
    return Station(
        camera=camera,
        projector=projector,
        raster=raster,
        name=name,
        gravity=np.array([0.0, 1.0, 0.0]),
    )
