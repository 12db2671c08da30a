"""A calibrated station: camera, projector, the raster they use and the vertical; its JSON
form (``rasterserver.calibration/1``) and the nominal design."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.json_document import JsonDocument
from rasterserver.optics.devices import Camera, Projector

if TYPE_CHECKING:
    from rasterserver.raster import Raster

#: ``format`` tag of the calibration JSON (see ``docs/formats.md``).
CALIBRATION_FORMAT = "rasterserver.calibration/1"


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
class Station(JsonDocument):
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
