"""Camera rays of sub-pixel rows interpolated from the per-pixel table, compiled.

:func:`.reconstruction.camera_rays` interpolated the ray of every peak between the table's
rays of the pixel rows around it in a dozen whole-array passes (floor, clip, two index
arrays, four gathers, the blends): ~1 ms of the points stage's ~5. Here one loop over the
peaks computes the same expressions in the same order, so the rays are the same bits.

Importing this module costs the numba import (~0.3 s): the points stage imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def interpolated_rays(table: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Ideal normalised device directions ``(x, y, 1)`` of image points.

    Parameters
    ----------
    table : numpy.ndarray
        ``(2, H, W)`` ideal normalised ``x`` and ``y`` of the rays through every pixel centre.
    col : numpy.ndarray
        ``(N,)`` integer image columns, within the image.
    row : numpy.ndarray
        ``(N,)`` float64 image rows, finite; rows beyond the first or last pair of pixel
        rows extrapolate from that pair.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` float64 directions in the camera frame.
    """
    h, w = table.shape[1], table.shape[2]
    tx = table[0].reshape(-1)
    ty = table[1].reshape(-1)
    last = max(h - 2, 0)
    down = w if h > 1 else 0
    n = col.shape[0]
    device = np.empty((n, 3))
    for i in range(n):
        r0 = min(max(np.intp(math.floor(row[i])), 0), last)
        f = row[i] - r0
        flat = r0 * w + np.intp(col[i])
        x0, y0 = tx[flat], ty[flat]
        device[i, 0] = x0 + f * (tx[flat + down] - x0)
        device[i, 1] = y0 + f * (ty[flat + down] - y0)
        device[i, 2] = 1.0
    return device
