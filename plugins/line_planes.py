"""Every peak's raster line looked up and its light plane gathered, compiled.

:func:`.reconstruction._line_planes` found each peak's line among the raster's numbers by
``searchsorted`` and gathered its position and plane in several whole-array passes (clips,
masks, fancy indexing of an ``(N, 3)`` table, NaN fills): ~0.6 ms of the points stage. Here
one loop over the peaks does the same lookup (a binary search, leftmost match) and copies
the same values, so the planes are the same bits.

Importing this module costs the numba import (~0.3 s): the points stage imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def gathered_planes(
    numbers: np.ndarray,
    positions: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    number: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position and light plane of the raster line of every number.

    Parameters
    ----------
    numbers : numpy.ndarray
        The raster's line numbers, ascending (at least one).
    positions, normals, offsets : numpy.ndarray
        Per raster line (in the order of ``numbers``): ``v`` and its plane.
    number : numpy.ndarray
        ``(N,)`` int64 line numbers.

    Returns
    -------
    v, n_w, off : numpy.ndarray
        ``(N,)``, ``(N, 3)``, ``(N,)`` float64; NaN for numbers the raster does not have.
    """
    n_raster = numbers.shape[0]
    n = number.shape[0]
    v = np.empty(n)
    n_w = np.empty((n, 3))
    off = np.empty(n)
    for i in range(n):
        x = number[i]
        lo, hi = 0, n_raster  # np.searchsorted(numbers, x, side="left")
        while lo < hi:
            mid = (lo + hi) // 2
            if numbers[mid] < x:
                lo = mid + 1
            else:
                hi = mid
        k = min(lo, n_raster - 1)
        if numbers[k] == x:
            v[i] = positions[k]
            for j in range(3):
                n_w[i, j] = normals[k, j]
            off[i] = offsets[k]
        else:
            v[i] = np.nan
            for j in range(3):
                n_w[i, j] = np.nan
            off[i] = np.nan
    return v, n_w, off
