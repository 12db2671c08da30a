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
  trunk (perpendicular to the line DM → VP in the sagittal plane), then turned about that
  line by the surface's rotation about the same line (:func:`axial_rotation`: the surface
  rotation measured perpendicular to the trunk's axis rather than horizontally, which differs
  only when the trunk leans sideways).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .curvature import fit_quadric_at, window_support
from .level_frame import LevelGrid
from .symmetry_line import SymmetryLine

__all__ = [
    "MIN_SUPPORT",
    "ROTATION_SCALE",
    "SpinalMidline",
    "axial_rotation",
    "body_depth",
    "line_normals",
    "spinal_midline",
    "surface_rotation",
]

#: Gaussian scales (mm) across and along the height of the fit giving the normal's
#: sideways component (the rotation).
ROTATION_SCALE = (25.0, 6.0)
#: Gaussian scales (mm) of the fit giving the normal's tilt along the trunk's axis.
TILT_SCALE = (6.0, 6.0)
#: Least share of each half (across the trunk) of the rotation's window that must lie on
#: measured surface. With less, the wide fit extrapolates the missing side from the other,
#: and its slope across, the rotation, is that side's flank: a hole of a few millimetres
#: beside the furrow moved the midline by 5 mm and more (``BENCHMARKS.md``, 2026-11-30).
MIN_SUPPORT = 0.85
#: Reference trunk length (mm) and depths (mm) of the vertebral-body centres at VP and DM.
REFERENCE_TRUNK_LENGTH = 440.0
BODY_DEPTH_AT_VP = 45.0
BODY_DEPTH_AT_DM = 70.0


@dataclass(frozen=True)
class SpinalMidline:
    """Surface rotation and vertebral-body centres along the symmetry line.

    Rows where the rotation is not measured (:func:`line_normals`) are NaN in every array but
    ``depth``.

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
    axial_rotation : numpy.ndarray
        ``(M,)`` rotation (degrees) about the trunk's axis (:func:`axial_rotation`), which
        turns the bodies' depth direction.
    """

    rotation: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    lateral_deviation: np.ndarray
    axial_rotation: np.ndarray


def _normals(coef: np.ndarray) -> np.ndarray:
    zx, zy = coef[:, 1], coef[:, 2]
    w = np.sqrt(1.0 + zx * zx + zy * zy)
    return np.column_stack([zx / w, zy / w, -1.0 / w])


def line_normals(
    grid: LevelGrid,
    line: SymmetryLine,
    vp: np.ndarray,
    dm: np.ndarray,
    *,
    min_support: float = MIN_SUPPORT,
) -> np.ndarray:
    """Outward unit surface normals (level frame) at the points of the symmetry line.

    In the trunk's frame (:func:`_trunk_axes`), the normal's sideways component comes from the
    wide fit of :data:`ROTATION_SCALE` (which averages the midline furrow out), its component
    along the trunk's axis from a narrow fit (:data:`TILT_SCALE`): the furrow runs along the
    axis and does not disturb that slope, while the vertebra prominens' bump, narrower than
    the wide window, would have its tilt averaged away, and a trunk leaning sideways turns
    that tilt partly into the horizontal rotation of the skin's normal. Both windows lean with
    the trunk (their axes across and along its axis VP–DM in the frontal plane), so they hold
    the same anatomy on both sides (the dimples, for one, at the same height).

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    line : SymmetryLine
        The symmetry line.
    vp, dm : numpy.ndarray
        ``(3,)`` level points of VP and DM (the trunk's axis).
    min_support : float, optional
        Least share of either half of the wide window on measured surface
        (:data:`MIN_SUPPORT`; :func:`rasterserver_plugins.curvature.window_support`).

    Returns
    -------
    numpy.ndarray
        ``(M, 3)`` normals facing the camera; NaN rows where a fit had too few cells or one
        side of the wide window too little surface: the rotation is not measured there.
    """
    cols, rows = grid.col_of(line.x), grid.row_of(line.y)
    v, a0, side = _trunk_axes(vp, dm)
    # The windows lean with the trunk, so that they hold the same anatomy on both sides.
    lean = float(np.arctan2(v[0], -v[1]))
    wide = _normals(
        fit_quadric_at(grid.z, grid.spacing, cols, rows, ROTATION_SCALE, cubic=True, angle=lean)
    )
    narrow = _normals(fit_quadric_at(grid.z, grid.spacing, cols, rows, TILT_SCALE, angle=lean))
    support = window_support(grid.z, grid.spacing, cols, rows, ROTATION_SCALE, angle=lean)
    wide[support.min(axis=1) < min_support] = np.nan
    c_side = wide @ side
    c_axis = np.where(np.isfinite(narrow[:, 0]), narrow @ v, wide @ v)
    c_front = -np.sqrt(np.clip(1.0 - c_side**2 - c_axis**2, 0.0, None))
    return c_side[:, None] * side + c_axis[:, None] * v + c_front[:, None] * a0


def surface_rotation(normals: np.ndarray) -> np.ndarray:
    """Surface rotation (degrees): the horizontal part of each normal against the sagittal
    direction, ``atan2(-n_x, -n_z)``; + turns the patient's right side backwards."""
    n = np.asarray(normals, dtype=float)
    return np.degrees(np.arctan2(-n[:, 0], -n[:, 2]))


def _trunk_axes(vp: np.ndarray, dm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trunk's axis ``v`` (DM → VP), the sagittal direction ``a0`` (the camera axis made
    perpendicular to ``v``, anterior) and ``side = v × a0`` (towards −x when upright)."""
    v = (vp - dm) / float(np.linalg.norm(vp - dm))
    a0 = np.array([0.0, 0.0, 1.0]) - v[2] * v
    a0 /= np.linalg.norm(a0)
    return v, a0, np.cross(v, a0)


def axial_rotation(normals: np.ndarray, vp: np.ndarray, dm: np.ndarray) -> np.ndarray:
    """Rotation (degrees) of the surface about the trunk's own axis VP–DM.

    The surface rotation is measured in the horizontal plane; when the trunk leans sideways,
    the normal's upward or downward tilt (steep at VP and at the sacrum) leans with it and
    shows there as a rotation that no vertebra has. Measured in the plane perpendicular to
    the trunk's axis instead, ``atan2(n · side, −n · a0)`` (see :func:`_trunk_axes`), the
    lean drops out; for an upright trunk both are the same. This is the rotation that turns
    the vertebral bodies' depth direction.
    """
    n = np.asarray(normals, dtype=float)
    _, a0, side = _trunk_axes(vp, dm)
    return np.degrees(np.arctan2(n @ side, -(n @ a0)))


def body_depth(t: np.ndarray, trunk_length: float) -> np.ndarray:
    """Depth (mm) of the vertebral-body centre in front of the skin (see the module text)."""
    scale = float(trunk_length) / REFERENCE_TRUNK_LENGTH
    return scale * (BODY_DEPTH_AT_VP + (BODY_DEPTH_AT_DM - BODY_DEPTH_AT_VP) * np.asarray(t))


def spinal_midline(
    line: SymmetryLine, normals: np.ndarray, vp: np.ndarray, dm: np.ndarray
) -> SpinalMidline:
    """Surface rotation and vertebral-body centres along the symmetry line.

    Parameters
    ----------
    line : SymmetryLine
        The symmetry line from VP to DM.
    normals : numpy.ndarray
        ``(M, 3)`` outward surface normals at its points (:func:`line_normals`). Where a row is
        NaN, the rotation is not measured, and neither is the centre: its rows are NaN too
        (refused, not bridged: a bridge across a hole draws a midline that nothing measured).
    vp, dm : numpy.ndarray
        ``(3,)`` level points of VP and DM.

    Returns
    -------
    SpinalMidline
    """
    rot = surface_rotation(normals)
    axial = axial_rotation(normals, vp, dm)
    length = float(np.linalg.norm(vp - dm))
    _, a0, side = _trunk_axes(vp, dm)
    t = (line.y - vp[1]) / (dm[1] - vp[1])
    depth = body_depth(t, length)
    phi = np.radians(axial)
    direction = np.cos(phi)[:, None] * a0[None, :] - np.sin(phi)[:, None] * side[None, :]
    points = line.points() + depth[:, None] * direction
    frac = (points[:, 1] - vp[1]) / (dm[1] - vp[1])
    line_x = vp[0] + frac * (dm[0] - vp[0])
    return SpinalMidline(
        rotation=rot,
        points=points,
        depth=depth,
        lateral_deviation=points[:, 0] - line_x,
        axial_rotation=axial,
    )
