"""The reconstructed points screened and gathered, compiled.

:meth:`.reconstruction.RayPlaneReconstruction.run` judged every point (finite, within the
measuring depth) and took the kept ones' coordinates in a dozen whole-array passes, one of
them a slow ``all(axis=1)`` over three columns: ~0.5 ms of the points stage. Here one loop
over the points gives the same mask, counts and coordinates (copies: the same bits).

Importing this module costs the numba import (~0.3 s): the points stage imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def screened_points(
    xyz: np.ndarray, v: np.ndarray, depth_limit: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int]]:
    """The points kept, their coordinates, and the counts of those dropped.

    Parameters
    ----------
    xyz : numpy.ndarray
        ``(N, 3)`` float64 world points (NaN rows: not reconstructed).
    v : numpy.ndarray
        ``(N,)`` diapositive ``v`` of every point's line (NaN: a number the raster lacks).
    depth_limit : float
        Largest ``|z|`` (mm) kept.

    Returns
    -------
    keep, x, y, z, dropped
        bool per point: finite and within the depth; the kept points' coordinates; and
        the numbers of points with an unknown line, whose ray missed (not finite, line
        known), and beyond the depth.
    """
    n = xyz.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    unknown = missed = beyond = 0
    m = 0
    for i in range(n):
        finite = math.isfinite(xyz[i, 0]) and math.isfinite(xyz[i, 1]) and math.isfinite(xyz[i, 2])
        inside = abs(xyz[i, 2]) <= depth_limit
        keep[i] = finite and inside
        if keep[i]:
            m += 1
        if math.isnan(v[i]):
            unknown += 1
        elif not finite:
            missed += 1
        if finite and not inside:
            beyond += 1
    x = np.empty(m)
    y = np.empty(m)
    z = np.empty(m)
    k = 0
    for i in range(n):
        if keep[i]:
            x[k], y[k], z[k] = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            k += 1
    return keep, x, y, z, (unknown, missed, beyond)
