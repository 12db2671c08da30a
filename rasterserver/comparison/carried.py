"""VP carried from one visit of a patient to another through their registration.

Hair, a shadow or a collar hides the vertebra prominens in some acquisitions; the analysis
then refuses VP, and with it the symmetry line from VP to DM and every parameter measured
along it: the lateral deviation, the surface rotation, the scoliosis angle, the very
parameters a scoliosis follow-up compares. The comparison registers the visit onto another
visit of the patient on the trunk below the neck; where that visit found its VP, the
registration carries it across: C7 is a point of the skeleton, and the trunk's rigid
alignment puts it where the other visit's skin shows it, to about the precision the other
visit found it with (tuning people 0-46: median 0.9 mm, largest 2.8 mm from the true VP).

What the carried point may serve is limited: it starts the symmetry line, so that the
parameters measured *along* the line (the midline's deviation and rotation, the scoliosis
angle) are computed; the parameters that measure VP's own position (trunk length,
inclination, imbalance, the sagittal profile's points) are not, since the registration is
rigid and a growing trunk moves VP relative to the trunk below it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rasterserver.comparison.geometry import apply_transform
from rasterserver.comparison.visits import Registration, Visit

__all__ = ["CARRY_REACH", "CarriedVP", "carry_vp"]

#: Farthest (mm) the carried VP may lie from the measured surface of the visit it is carried
#: to: farther, the symmetry line would start where this visit measured nothing.
CARRY_REACH = 20.0


@dataclass(frozen=True)
class CarriedVP:
    """VP carried to a visit, or why not.

    Attributes
    ----------
    point : numpy.ndarray or None
        ``(3,)`` world mm in the frame of the visit it is carried to; None when refused.
    source : str
        The label of the visit it comes from.
    reason : str
        Why it was not carried, or "".
    surface_distance : float
        Distance (mm) from the carried point to the nearest measured vertex of the visit.
    """

    point: np.ndarray | None
    source: str
    reason: str = ""
    surface_distance: float = float("nan")


def carry_vp(
    source: Visit, target: Visit, registration: Registration, *, source_is_a: bool
) -> CarriedVP:
    """Carry ``source``'s VP onto ``target`` through their accepted registration.

    Parameters
    ----------
    source : Visit
        The visit whose analysis found VP.
    target : Visit
        The visit without its own VP.
    registration : Registration
        Visit B moved onto visit A (``p_a = T p_b``): the comparison of the two.
    source_is_a : bool
        Whether ``source`` is the pair's visit A (then VP goes through ``T⁻¹``).

    Returns
    -------
    CarriedVP
        The point in ``target``'s world frame, or the reason it is not carried.
    """
    label = source.label or "?"
    vp = source.shape.landmark("VP")
    if vp is None:
        return CarriedVP(None, label, f"visit {label} has no VP to carry")
    if target.shape.landmark("VP") is not None:
        return CarriedVP(None, label, f"visit {target.label or '?'} has its own VP")
    move = np.linalg.inv(registration.transform) if source_is_a else registration.transform
    point = apply_transform(move, np.asarray(vp, dtype=float)[None])[0]
    vertices = np.asarray(target.mesh.vertices, dtype=float)
    distance = float(np.min(np.linalg.norm(vertices - point, axis=1))) if len(vertices) else np.inf
    if distance > CARRY_REACH:
        return CarriedVP(
            None,
            label,
            f"VP of visit {label} falls {distance:.0f} mm from the measured surface of visit "
            f"{target.label or '?'} (at most {CARRY_REACH:g} mm): not carried",
            distance,
        )
    return CarriedVP(point, label, "", distance)
