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

The package holds the lens model (:mod:`.distortion`), the devices (:mod:`.devices`: camera
and projector) and the station that pairs them with a raster (:mod:`.station`).
"""

from __future__ import annotations

from rasterserver.optics.devices import Camera, PinholeDevice, Projector
from rasterserver.optics.distortion import distort_normalized, undistort_normalized
from rasterserver.optics.station import (
    CALIBRATION_FORMAT,
    Station,
    default_station,
    rotation_matrix,
)

__all__ = [
    "CALIBRATION_FORMAT",
    "Camera",
    "PinholeDevice",
    "Projector",
    "Station",
    "default_station",
    "distort_normalized",
    "rotation_matrix",
    "undistort_normalized",
]
