"""Surface rotation along the symmetry line, and the spinal midline behind it.

After Drerup & Hierholzer (*Back shape measurement using video rasterstereography and
three-dimensional reconstruction of spinal shape*, Clin Biomech 9 (1994) 28-36): the
**surface rotation** at a point of the symmetry line is the horizontal component of the
surface normal there, measured against the sagittal direction; it follows the axial rotation
of the vertebra beneath. The **spinal midline**, the line of the vertebral-body centres, is
reconstructed by placing each centre at a depth ``d`` in front of the skin along the
sagittal direction turned by that rotation: in the frontal plane the centre lies
``d · sin φ`` beside the symmetry line, on the side the vertebral body has turned to.

Definitions used here (level frame, :mod:`rasterserver_plugins.level_frame`):

* **surface rotation** ``φ = atan2(-n_x, -n_z)`` (degrees) of the outward unit normal
  ``n = (z_x, z_y, -1) / W`` of the surface smoothed by a local fit (a quadric plus the odd
  cubic terms ``u³``, ``u v²``; Gaussian scales :data:`ROTATION_SCALE` across and along the
  height), wide enough to average the midline furrow out, whose flanks would otherwise make
  the normal swing with every millimetre the line is off its bottom; on turned, strongly
  rounded backs it overestimates the rotation by a few per cent. The reference is the
  station's sagittal direction (the camera's optical axis made horizontal); ``φ > 0`` turns
  the patient's right side (+x) backwards (−z), the simulator's sign of axial rotation.
* **body depth** ``d(t) = (L / 440 mm) · (45 mm + 25 mm · t)``, ``L`` the trunk length VP–DM
  and ``t`` the height fraction from VP (0) to DM (1): 45 mm from the skin over C7 to the
  centre of its body, 70 mm at S1, for a 440 mm trunk, scaled with the trunk (anatomical
  proportions: spinous process, lamina, canal and half a vertebral body, plus the soft
  tissue, thicker in the lumbar region). The same model defines the simulator's vertebral
  bodies (``docs/simulator_truth.md``), so the benchmark measures what the surface tells,
  not a disagreement about anatomy.
* **sagittal direction** at a height: the horizontal camera axis ``z'`` tilted with the
  trunk (perpendicular to the line DM → VP in the sagittal plane), then turned by ``φ``
  about that line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from rasterserver_plugins.curvature import fit_quadric_at
from rasterserver_plugins.level_frame import LevelGrid
from rasterserver_plugins.symmetry_line import SymmetryLine

__all__ = ["ROTATION_SCALE", "SpinalMidline", "body_depth", "spinal_midline", "surface_rotation"]

#: Gaussian scales (mm) across and along the height of the fit giving the normal.
ROTATION_SCALE = (25.0, 6.0)
#: Reference trunk length (mm) and depths (mm) of the vertebral-body centres at VP and DM.
REFERENCE_TRUNK_LENGTH = 440.0
BODY_DEPTH_AT_VP = 45.0
BODY_DEPTH_AT_DM = 70.0


@dataclass(frozen=True)
class SpinalMidline:
    """Surface rotation and vertebral-body centres along the symmetry line.

    Attributes
    ----------
    rotation : numpy.ndarray
        ``(M,)`` surface rotation (degrees) at the symmetry line's points.
    points : numpy.ndarray
        ``(M, 3)`` level-frame vertebral-body centres (mm).
    depth : numpy.ndarray
        ``(M,)`` body depth used (mm).
    lateral_deviation : numpy.ndarray
        ``(M,)`` horizontal distance (mm) of each centre from the line VP–DM at its height,
        in the frontal plane; + to the patient's right.
    """

    rotation: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    lateral_deviation: np.ndarray


def surface_rotation(grid: LevelGrid, line: SymmetryLine) -> np.ndarray:
    """Surface rotation (degrees) at every point of the symmetry line.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    line : SymmetryLine
        The symmetry line.

    Returns
    -------
    numpy.ndarray
        ``(M,)`` degrees; NaN where the fit had too few measured cells.
    """
    coef = fit_quadric_at(
        grid.z, grid.spacing, grid.col_of(line.x), grid.row_of(line.y), ROTATION_SCALE, cubic=True
    )
    zx, zy = coef[:, 1], coef[:, 2]
    w = np.sqrt(1.0 + zx * zx + zy * zy)
    nx, nz = zx / w, -1.0 / w
    return np.degrees(np.arctan2(-nx, -nz))


def body_depth(t: np.ndarray, trunk_length: float) -> np.ndarray:
    """Depth (mm) of the vertebral-body centre in front of the skin (see the module text)."""
    scale = float(trunk_length) / REFERENCE_TRUNK_LENGTH
    return scale * (BODY_DEPTH_AT_VP + (BODY_DEPTH_AT_DM - BODY_DEPTH_AT_VP) * np.asarray(t))


def spinal_midline(
    line: SymmetryLine, rotation: np.ndarray, vp: np.ndarray, dm: np.ndarray
) -> SpinalMidline:
    """Vertebral-body centres behind the symmetry line.

    Parameters
    ----------
    line : SymmetryLine
        The symmetry line from VP to DM.
    rotation : numpy.ndarray
        ``(M,)`` surface rotation along it (degrees); NaN values are bridged.
    vp, dm : numpy.ndarray
        ``(3,)`` level points of VP and DM.

    Returns
    -------
    SpinalMidline
    """
    rot = np.asarray(rotation, dtype=float)
    ok = np.isfinite(rot)
    if ok.any() and not ok.all():
        rot = np.interp(line.y, line.y[ok], rot[ok])
    up = vp - dm
    length = float(np.linalg.norm(up))
    v = up / length
    # The sagittal direction: the camera axis made perpendicular to the trunk's axis.
    a0 = np.array([0.0, 0.0, 1.0]) - v[2] * v
    a0 /= np.linalg.norm(a0)
    side = np.cross(v, a0)  # points to -x for an upright trunk
    t = (line.y - vp[1]) / (dm[1] - vp[1])
    depth = body_depth(t, length)
    phi = np.radians(rot)
    direction = np.cos(phi)[:, None] * a0[None, :] - np.sin(phi)[:, None] * side[None, :]
    points = line.points() + depth[:, None] * direction
    frac = (points[:, 1] - vp[1]) / (dm[1] - vp[1])
    line_x = vp[0] + frac * (dm[0] - vp[0])
    return SpinalMidline(
        rotation=rot, points=points, depth=depth, lateral_deviation=points[:, 0] - line_x
    )
