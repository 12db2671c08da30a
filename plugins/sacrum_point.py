"""The sacrum point SP: the top of the rima ani (gluteal cleft), below DM on the midline.

After Drerup & Hierholzer's landmarks (:mod:`rasterserver_plugins.landmarks`, which finds
VP, the dimples and DM): going down the midline from DM, the lateral concavity of the
surface first falls (the sacral plateau) and then rises where the gluteal cleft begins.
"""

from __future__ import annotations

import numpy as np

from .curvature import Curvature
from .landmarks import MIN_SUPPORT, Landmark, _missing, _surface_point, _vertex
from .level_frame import LevelGrid
from .trunk import Trunk

__all__ = ["CLEFT_CONCAVITY", "CLEFT_ROWS", "find_sacrum_point"]

#: Lateral concavity (1/mm, ``-z_xx`` at the landmark scale) that marks the top of the cleft.
CLEFT_CONCAVITY = 0.02
#: Rows below SP the cleft must stay that concave (so that SP is not an edge artefact).
CLEFT_ROWS = 2


def find_sacrum_point(
    grid: LevelGrid, curv: Curvature, trunk: Trunk, dl: Landmark, dr: Landmark
) -> Landmark:
    """The sacrum point SP: the top of the rima ani (gluteal cleft), below DM on the midline.

    Going down from DM along the midline (columns within a quarter of the dimple distance of
    DM), the lateral concavity ``c = -∂²z/∂x²`` of the smoothed surface first falls as the
    lumbar furrow ends over the sacrum (the *sacral plateau*, ``c`` below half of
    :data:`CLEFT_CONCAVITY`), then rises where the gluteal cleft begins. SP is where ``c``
    crosses :data:`CLEFT_CONCAVITY` (interpolated between rows), at the cleft's bottom; the
    cleft must then stay at least that concave for :data:`CLEFT_ROWS` more rows of measured
    surface, or SP is refused as not in view.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature.
    trunk : Trunk
        The trunk.
    dl, dr : Landmark
        The lumbar dimples.

    Returns
    -------
    Landmark
        ``SP`` in level coordinates, or missing with a reason.
    """
    if dl.point is None or dr.point is None:
        return _missing("SP", "needs both lumbar dimples (it is looked for below DM)")
    s = grid.spacing
    dm = 0.5 * (dl.point + dr.point)
    half = 0.25 * float(np.linalg.norm(dr.point - dl.point)) / s
    c_dm = float(grid.col_of(dm[0]))
    r0 = int(np.ceil(float(grid.row_of(dm[1]))))
    r1 = trunk.bottom
    if r1 - r0 < 3:
        return _missing("SP", "the image ends at DM: the gluteal cleft is not in view")
    j0 = max(0, int(np.floor(c_dm - half)))
    j1 = min(grid.shape[1], int(np.ceil(c_dm + half)) + 1)
    band = -curv.zxx[r0 : r1 + 1, j0:j1]
    band = np.where(curv.support[r0 : r1 + 1, j0:j1] >= MIN_SUPPORT, band, np.nan)
    has = np.isfinite(band).any(axis=1)
    conc = np.where(has, np.nanmax(np.where(np.isfinite(band), band, -np.inf), axis=1), np.nan)
    cols = np.where(has, np.argmax(np.where(np.isfinite(band), band, -np.inf), axis=1) + j0, -1)
    low = np.flatnonzero(conc < 0.5 * CLEFT_CONCAVITY)
    if low.size == 0:
        return _missing("SP", "no sacral plateau below DM: the midline furrow runs on")
    start = int(low[0])
    above = conc >= CLEFT_CONCAVITY
    for k in range(start + 1, conc.size):
        if not above[k]:
            continue
        run = above[k : k + 1 + CLEFT_ROWS]
        if run.size < 1 + CLEFT_ROWS or not run.all():
            break
        c_prev, c_here = conc[k - 1], conc[k]
        frac = (CLEFT_CONCAVITY - c_prev) / (c_here - c_prev) if c_here > c_prev else 1.0
        row = r0 + k - 1 + float(np.clip(frac, 0.0, 1.0))
        col = float(
            np.mean([_vertex(band[j], cols[j] - j0) + j0 for j in range(k, k + 1 + CLEFT_ROWS)])
        )
        point = _surface_point(grid, curv, row, col)
        visible = int(np.argmin(np.append(above[k:], False)))
        return Landmark("SP", point, float(min(1.0, visible / (2.0 * (CLEFT_ROWS + 1)))))
    below = (r1 - r0) * s
    return _missing(
        "SP",
        f"the gluteal cleft is not in view: the measured surface ends {below:.0f} mm below DM",
    )
