"""What a simulated back truly is, in the terms of the back-shape analysis.

:func:`rasterserver.simulator.back.make_back` stores the geometry (landmarks, the spinal line
on the skin, the vertebral-body centres, surface normals) in the scene; :func:`truth` turns it
into the analysis's landmarks, lines and clinical parameters, each defined here and in
``docs/simulator_truth.md``. The helpers below are pure functions of arrays, shared by the
simulator and the benchmark.

Frame and signs (world mm, as the simulator and the reconstructed points): X to the patient's
right, Y down (gravity is +Y), Z anterior. Heights along the trunk are fractions ``t`` of the
trunk length, 0 at the vertebra prominens VP, 1 at DM, the midpoint of the lumbar dimples.

* **Sagittal profile**: the spinal line on the skin projected on the world Y–Z plane. Its
  *inclination* at a point is the angle of its tangent from the vertical (gravity),
  ``atan2(dz, dy)`` in degrees: positive where the line runs anteriorly going down. The
  inflection points are the extremes of the inclination (where the curvature changes sign)
  between VP and DM: ITL its maximum between ``t`` = 0.15 and 0.95 (between kyphosis and
  lordosis), ICT its minimum above ITL, ILS its minimum below ITL; an inflection that lies
  beyond VP or DM is taken at VP or DM. The kyphosis apex KA is the most posterior point
  (smallest Z) between ICT and ITL, the lordosis apex LA the most anterior one between ITL
  and ILS (where the tangent is vertical when they lie inside).
* **Vertebral-body centres**: at anatomical depth :func:`body_depth` in front of the skin
  point of the spinal line, along the cross-section's sagittal direction turned by the axial
  rotation, which the simulator applies about that skin point.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from rasterserver.errors import InputError

if TYPE_CHECKING:
    from rasterserver.simulator.scene import Scene

__all__ = [
    "BODY_DEPTH_AT_DM",
    "BODY_DEPTH_AT_VP",
    "ITL_SEARCH",
    "PARAMETER_UNITS",
    "REFERENCE_TRUNK_LENGTH",
    "body_depth",
    "cobb_angle",
    "inclination",
    "sagittal_points",
    "signed_extremes",
    "truth",
    "turning_points",
]

#: Trunk length (VP–DM, mm) the body depths below are given for; they scale with it.
REFERENCE_TRUNK_LENGTH = 440.0
#: Depth of the vertebral-body centre in front of the skin over the spinous process, mm,
#: at VP (C7) and at DM (S1–S2), for the reference trunk length; linear in between.
BODY_DEPTH_AT_VP = 45.0
BODY_DEPTH_AT_DM = 70.0
#: Heights (t) where the thoraco-lumbar inflection ITL is looked for: clear of the vertebra
#: prominens' bump at the top and of the sacrum at the bottom.
ITL_SEARCH = (0.15, 0.95)

#: Unit of every parameter :func:`truth` reports.
PARAMETER_UNITS: dict[str, str] = {
    "trunk_length": "mm",
    "trunk_inclination_mm": "mm",
    "trunk_inclination_deg": "deg",
    "trunk_imbalance_mm": "mm",
    "trunk_imbalance_deg": "deg",
    "pelvic_tilt_mm": "mm",
    "pelvic_tilt_deg": "deg",
    "pelvic_torsion_deg": "deg",
    "pelvic_rotation_deg": "deg",
    "kyphotic_angle_deg": "deg",
    "lordotic_angle_deg": "deg",
    "fleche_cervicale_mm": "mm",
    "fleche_lombaire_mm": "mm",
    "surface_rotation_rms_deg": "deg",
    "surface_rotation_max_deg": "deg",
    "surface_rotation_pos_max_deg": "deg",
    "surface_rotation_neg_max_deg": "deg",
    "lateral_deviation_rms_mm": "mm",
    "lateral_deviation_max_mm": "mm",
    "lateral_deviation_pos_max_mm": "mm",
    "lateral_deviation_neg_max_mm": "mm",
    "scoliosis_angle_deg": "deg",
}


def body_depth(t: np.ndarray, trunk_length: float) -> np.ndarray:
    """Depth (mm) of the vertebral-body centre in front of the spinal line's skin point.

    Linear from :data:`BODY_DEPTH_AT_VP` at ``t = 0`` to :data:`BODY_DEPTH_AT_DM` at ``t = 1``
    for a trunk of :data:`REFERENCE_TRUNK_LENGTH`, scaled in proportion to ``trunk_length``
    (the skeleton scales with the body): spinous process, lamina, canal and half the body
    depth, plus the soft tissue over the spinous process, thicker in the lumbar region.

    Parameters
    ----------
    t : numpy.ndarray
        Heights as fractions of the trunk length (0 = VP, 1 = DM).
    trunk_length : float
        VP–DM distance, mm.

    Returns
    -------
    numpy.ndarray
        Depths in mm, the shape of ``t``.
    """
    t = np.asarray(t, dtype=float)
    scale = float(trunk_length) / REFERENCE_TRUNK_LENGTH
    return scale * (BODY_DEPTH_AT_VP + (BODY_DEPTH_AT_DM - BODY_DEPTH_AT_VP) * t)


def inclination(along: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Angle (degrees) of a polyline's tangent from the ``along`` axis towards ``across``.

    With ``along`` the world Y (down) and ``across`` the world Z (anterior) of a sagittal
    profile, this is the tangent's inclination from gravity, positive where the line runs
    anteriorly going down; with ``across`` the world X of a frontal line, positive where it
    runs to the patient's right going down. Central differences inside, one-sided at the ends.
    """
    along = np.asarray(along, dtype=float)
    across = np.asarray(across, dtype=float)
    if along.shape != across.shape or along.ndim != 1 or along.size < 2:
        raise InputError("inclination needs two 1-D arrays of the same length (>= 2)")
    return np.degrees(np.arctan2(np.gradient(across), np.gradient(along)))


def sagittal_points(t: np.ndarray, y: np.ndarray, z: np.ndarray) -> dict[str, int]:
    """Indices of the inflection points and apices of a sagittal profile.

    Parameters
    ----------
    t : numpy.ndarray
        Heights (fractions of VP–DM, increasing) of the profile samples; the profile may
        extend beyond [0, 1] (better tangents at VP and DM), the points are looked for in
        [0, 1] only.
    y, z : numpy.ndarray
        World Y (down) and Z (anterior) of the samples, mm.

    Returns
    -------
    dict of str to int
        ``ICT``, ``KA``, ``ITL``, ``LA``, ``ILS``: indices into the arrays (see the module
        docstring for the definitions); ``ICT <= KA <= ITL <= LA <= ILS`` in height.

    Raises
    ------
    InputError
        When the profile does not cover the ITL search range.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    z = np.asarray(z, dtype=float)
    alpha = inclination(y, z)
    eps = 1e-9
    inside = np.flatnonzero((t >= -eps) & (t <= 1.0 + eps))
    search = np.flatnonzero((t >= ITL_SEARCH[0]) & (t <= ITL_SEARCH[1]))
    if inside.size < 3 or search.size == 0:
        raise InputError("the sagittal profile must cover VP to DM")
    itl = int(search[np.argmax(alpha[search])])
    above = inside[inside <= itl]
    below = inside[inside >= itl]
    ict = int(above[np.argmin(alpha[above])])
    ils = int(below[np.argmin(alpha[below])])
    ka = ict + int(np.argmin(z[ict : itl + 1]))
    la = itl + int(np.argmax(z[itl : ils + 1]))
    return {"ICT": ict, "KA": ka, "ITL": itl, "LA": la, "ILS": ils}


def turning_points(values: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """Indices of the first sample and of the alternating extremes of a sequence after it.

    A maximum (minimum) counts once the sequence has fallen (risen) more than ``tolerance``
    below (above) it, so flat stretches and rounding noise make no extremes; the last
    extreme is the largest (smallest) value of the final rise (fall), often the last sample.

    Parameters
    ----------
    values : numpy.ndarray
        1-D sequence.
    tolerance : float
        Smallest excursion that makes an extreme.

    Returns
    -------
    numpy.ndarray
        Increasing indices starting with 0 (only 0 for a sequence that never moves by more
        than ``tolerance``; empty for an empty one).
    """
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        return np.zeros(0, dtype=int)
    points = [0]
    direction, extreme = 0, 0  # direction +1: rising towards a maximum at `extreme`
    for i in range(1, v.size):
        if direction == 0:
            if abs(v[i] - v[0]) > tolerance:
                direction, extreme = (1 if v[i] > v[0] else -1), i
        elif direction * (v[i] - v[extreme]) >= 0.0:
            extreme = i
        elif direction * (v[extreme] - v[i]) > tolerance:
            points.append(extreme)
            direction, extreme = -direction, i
    if direction != 0:
        points.append(extreme)
    return np.asarray(points, dtype=int)


def cobb_angle(vertical: np.ndarray, lateral: np.ndarray) -> float:
    """Cobb-like angle (degrees) of a line in the frontal plane.

    The tangent's angle from the vertical is taken along the line; between two consecutive
    extremes of it (the inflection points of the line, or its ends) lies one curve, whose angle
    is the difference of the tangents there, as the Cobb angle is the angle between the end
    plates most tilted into a curve. The result is the largest such angle (0 for a straight
    line).

    Parameters
    ----------
    vertical : numpy.ndarray
        World Y (down) of the points, mm, monotonic.
    lateral : numpy.ndarray
        Their world X (patient's right), mm.
    """
    beta = inclination(vertical, lateral)
    tp = turning_points(beta, tolerance=1e-3)
    if tp.size < 2:
        return 0.0
    return float(np.abs(np.diff(beta[tp])).max())


def signed_extremes(values: np.ndarray) -> tuple[float, float, float, float]:
    """The rms, the value of largest magnitude (signed), the largest and the smallest value.

    The largest value is at least 0 and the smallest at most 0 (``+max`` and ``-max`` of a
    curve that never crosses to that side are 0), as DIERS reports them.
    """
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return (math.nan,) * 4
    signed_max = float(v[np.argmax(np.abs(v))])
    return (
        float(np.sqrt(np.mean(v * v))),
        signed_max,
        max(float(v.max()), 0.0),
        min(float(v.min()), 0.0),
    )


def _point(landmarks: Mapping[str, Any], name: str) -> np.ndarray:
    try:
        point = np.asarray(landmarks[name], dtype=float)
    except KeyError:
        raise InputError(f"the scene has no landmark {name!r}: not made by make_back?") from None
    return point


def _frontal_deviation(points: np.ndarray, vp: np.ndarray, dm: np.ndarray) -> np.ndarray:
    """Horizontal X distance of ``points`` from the VP–DM line at their height (frontal)."""
    line_x = vp[0] + (dm[0] - vp[0]) * (points[:, 1] - vp[1]) / (dm[1] - vp[1])
    return points[:, 0] - line_x


def truth(scene: Scene) -> dict[str, Any]:
    """The truth of a simulated back, in the terms of the back-shape analysis.

    Parameters
    ----------
    scene : Scene
        A scene made by :func:`rasterserver.simulator.back.make_back` or by
        :func:`rasterserver.simulator.body.make_body` (a clinic scene's trunk is its back's,
        and so is its truth).

    Returns
    -------
    dict
        ``landmarks``: name → ``(3,)`` world mm for ``VP``, ``DL``, ``DR``, ``DM``, ``SP``
        (the analysis's landmarks) and ``ICT``, ``KA``, ``ITL``, ``LA``, ``ILS`` (sagittal
        profile, on the skin).

        ``spine``: arrays along the spinal line from VP to DM (2 mm steps): ``t``; ``skin``
        ``(M, 3)`` the spinal line on the skin (spinous processes); ``body`` ``(M, 3)`` the
        vertebral-body centres; ``body_depth_mm``; ``lateral_deviation_mm`` of the body
        centres and ``skin_lateral_deviation_mm`` of the skin line from the VP–DM line in the
        frontal plane (horizontal X distance, + to the patient's right);
        ``axial_rotation_deg`` as applied; ``surface_rotation_deg``, the angle of the
        horizontal part of the skin's outward normal on the spinal line from the camera's
        axis (``atan2(-n_x, -n_z)``; + turns the right side backwards, the applied rotation
        plus the posture's turn, up to the inclination); ``sagittal_inclination_deg`` of the
        profile (see :func:`inclination`).

        ``parameters``: name → ``{"value": float, "unit": "mm" | "deg"}``, see
        :data:`PARAMETER_UNITS` and ``docs/simulator_truth.md``.

    Raises
    ------
    InputError
        For a scene that is not a simulated back.
    """
    metadata = scene.metadata
    if metadata.get("kind") not in ("back", "body") or "truth" not in metadata:
        raise InputError("not a simulated back: truth needs a scene made by make_back or make_body")
    lm = scene.landmarks
    spine, extra = metadata["spine"], metadata["truth"]
    vp, dm = _point(lm, "vertebra_prominens"), _point(lm, "dimple_midpoint")
    dl, dr = _point(lm, "dimple_left"), _point(lm, "dimple_right")
    landmarks = {
        "VP": vp,
        "DL": dl,
        "DR": dr,
        "DM": dm,
        "SP": _point(lm, "sacrum_point"),
        **{name: _point(lm, f"sagittal_{name}") for name in ("ICT", "KA", "ITL", "LA", "ILS")},
    }
    skin = np.asarray(lm["spinal_midline"], dtype=float)
    body = np.asarray(lm["vertebral_bodies"], dtype=float)
    rotation = np.asarray(spine["surface_rotation_deg"], dtype=float)
    deviation = _frontal_deviation(body, vp, dm)
    lines = {
        "t": np.asarray(spine["t"], dtype=float),
        "skin": skin,
        "body": body,
        "body_depth_mm": np.asarray(spine["body_depth_mm"], dtype=float),
        "lateral_deviation_mm": deviation,
        "skin_lateral_deviation_mm": _frontal_deviation(skin, vp, dm),
        "axial_rotation_deg": np.asarray(spine["axial_rotation_deg"], dtype=float),
        "surface_rotation_deg": rotation,
        "sagittal_inclination_deg": np.asarray(spine["sagittal_inclination_deg"], dtype=float),
    }

    height = dm[1] - vp[1]
    sag = extra["sagittal"]
    ka = landmarks["KA"]
    rot_rms, rot_max, rot_pos, rot_neg = signed_extremes(rotation)
    dev_rms, dev_max, dev_pos, dev_neg = signed_extremes(deviation)
    nl, nr = (np.asarray(extra["dimple_normals"][side], dtype=float) for side in ("left", "right"))

    def upward(n: np.ndarray) -> float:
        # Tilt of an outward normal (facing the camera, -Z) above the horizontal.
        return math.degrees(math.atan2(-n[1], -n[2]))

    values = {
        "trunk_length": float(np.linalg.norm(vp - dm)),
        "trunk_inclination_mm": float(vp[2] - dm[2]),
        "trunk_inclination_deg": math.degrees(math.atan2(vp[2] - dm[2], height)),
        "trunk_imbalance_mm": float(vp[0] - dm[0]),
        "trunk_imbalance_deg": math.degrees(math.atan2(vp[0] - dm[0], height)),
        "pelvic_tilt_mm": float(dl[1] - dr[1]),
        "pelvic_tilt_deg": math.degrees(math.atan2(dl[1] - dr[1], dr[0] - dl[0])),
        "pelvic_torsion_deg": upward(nr) - upward(nl),
        "pelvic_rotation_deg": math.degrees(math.atan2(dl[2] - dr[2], dr[0] - dl[0])),
        "kyphotic_angle_deg": sag["ITL"]["inclination_deg"] - sag["ICT"]["inclination_deg"],
        "lordotic_angle_deg": sag["ITL"]["inclination_deg"] - sag["ILS"]["inclination_deg"],
        "fleche_cervicale_mm": float(vp[2] - ka[2]),
        "fleche_lombaire_mm": float(landmarks["LA"][2] - ka[2]),
        "surface_rotation_rms_deg": rot_rms,
        "surface_rotation_max_deg": rot_max,
        "surface_rotation_pos_max_deg": rot_pos,
        "surface_rotation_neg_max_deg": rot_neg,
        "lateral_deviation_rms_mm": dev_rms,
        "lateral_deviation_max_mm": dev_max,
        "lateral_deviation_pos_max_mm": dev_pos,
        "lateral_deviation_neg_max_mm": dev_neg,
        "scoliosis_angle_deg": cobb_angle(body[:, 1], body[:, 0]),
    }
    parameters = {
        name: {"value": float(v), "unit": PARAMETER_UNITS[name]} for name, v in values.items()
    }
    return {"landmarks": landmarks, "spine": lines, "parameters": parameters}
