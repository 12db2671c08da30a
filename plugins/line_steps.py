"""The line-jump check of the numbering, compiled with numba.

:func:`rasterserver_plugins.peak_checks.line_jumps` compared every step of every line
with the steps beside it in a dozen whole-array passes (differences, masks, the two
neighbours' slopes, their mean, the departure): ~1 ms of the numbering's ~15. One loop over
the steps computes the same expressions in the same order, so the refusals are the same.

Importing this module costs the numba import (~0.3 s): the check imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel(error_model="numpy")
def jumping_peaks(
    order: np.ndarray,
    lid: np.ndarray,
    col: np.ndarray,
    row: np.ndarray,
    spacing: np.ndarray,
    max_jump: float,
    max_columns: int,
) -> np.ndarray:
    """Peaks at either end of a step that departs from its line's steps beside it.

    Parameters
    ----------
    order : numpy.ndarray
        int64 indices of the judged peaks, by line and then column.
    lid, col : numpy.ndarray
        int64 line and column of every peak.
    row, spacing : numpy.ndarray
        float64 row and local line spacing of every peak.
    max_jump : float
        Largest departure of a step, in local line spacings.
    max_columns : int
        Largest column gap of a judged step.

    Returns
    -------
    numpy.ndarray
        bool, one per peak: True at both ends of a step that jumps.
    """
    out = np.zeros(lid.shape[0], dtype=np.bool_)
    m = order.shape[0] - 1  # steps
    if m < 1:
        return out
    slope = np.empty(m)
    dcol = np.empty(m)
    for k in range(m):
        a, b = order[k], order[k + 1]
        dcol[k] = max(np.float64(col[b]) - np.float64(col[a]), 1.0)
        same = lid[b] == lid[a] and col[b] - col[a] <= max_columns
        slope[k] = (row[b] - row[a]) / dcol[k] if same else np.nan
    for k in range(m):
        if math.isnan(slope[k]):
            continue  # across a line's end or a gap: not judged
        left = slope[k - 1] if k > 0 else np.nan
        right = slope[k + 1] if k + 1 < m else np.nan
        if math.isnan(left):
            ref = right
        elif math.isnan(right):
            ref = left
        else:
            ref = 0.5 * (left + right)
        if math.isnan(ref):
            continue
        a, b = order[k], order[k + 1]
        if abs(slope[k] - ref) * dcol[k] > max_jump * spacing[a]:
            out[a] = True
            out[b] = True
    return out
