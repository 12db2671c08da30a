"""The body-fixed frame of a back, from the vertebra prominens and the lumbar dimples.

After Drerup & Hierholzer (J Biomech 20 (1987) 961-970), who construct a body-fixed
coordinate system from VP, DL and DR so that measurements of one patient at different visits
(standing a little differently each time) can be compared:

* origin: DM, midway between DL and DR (the analysis takes the skin point there, see
  :func:`rasterserver_plugins.landmarks.midpoint`);
* vertical axis: from DM up to VP;
* transverse axis: along DL → DR (towards the patient's right), made perpendicular to the
  vertical axis;
* sagittal axis: transverse × vertical, pointing posterior (towards the camera), so the
  three form a right-handed frame.
"""

from __future__ import annotations

import numpy as np

__all__ = ["body_frame"]


def body_frame(
    vp: np.ndarray, dl: np.ndarray, dr: np.ndarray, dm: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """Origin and axes of the body-fixed frame.

    Parameters
    ----------
    vp, dl, dr : numpy.ndarray
        ``(3,)`` points of VP, DL and DR (any right-handed frame; the result is in the same).
    dm : numpy.ndarray, optional
        ``(3,)`` DM; the midpoint of DL and DR when not given.

    Returns
    -------
    tuple of numpy.ndarray or None
        ``origin`` ``(3,)`` (DM) and ``axes`` ``(3, 3)`` whose rows are the unit transverse,
        vertical and sagittal axes; None when the points are degenerate (VP on DM, or the
        dimples on the vertical axis).
    """
    vp, dl, dr = (np.asarray(p, dtype=float) for p in (vp, dl, dr))
    origin = 0.5 * (dl + dr) if dm is None else np.asarray(dm, dtype=float)
    up = vp - origin
    norm = float(np.linalg.norm(up))
    if not np.isfinite(norm) or norm < 1e-6:
        return None
    vertical = up / norm
    across = dr - dl
    transverse = across - (across @ vertical) * vertical
    norm = float(np.linalg.norm(transverse))
    if not np.isfinite(norm) or norm < 1e-6:
        return None
    transverse /= norm
    sagittal = np.cross(transverse, vertical)
    return origin, np.stack([transverse, vertical, sagittal])
