"""The runs of neighbouring peaks along the lines and their means, compiled.

:func:`.smoothing.smooth_along_lines` found the runs (a stretch of one line over
consecutive columns), their kept centres and the means of the peaks around them in some
twenty whole-array passes and five gathers of a ``(window, runs)`` table: ~1 ms of the
surface stage's ~2. Here one loop finds the centres and one computes the five means, each
sum added peak by peak from 0 as numpy's ``sum(axis=0)`` adds, so the means are the same
bits. (The 3-D jumps stay numpy's ``einsum``, whose order of additions is its own.)

Importing this module costs the numba import (~0.3 s): the surface stage imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def run_centres(
    number: np.ndarray,
    col: np.ndarray,
    jump: np.ndarray,
    window: int,
    step: int,
    end_block: bool = False,
) -> np.ndarray:
    """Positions (in line, column order) of the centres of the kept runs.

    Parameters
    ----------
    number, col : numpy.ndarray
        Line number and column of the peaks sorted by line, then column.
    jump : numpy.ndarray
        ``(N - 1,)`` bool: the 3-D step from a peak to the next ends the run.
    window, step : int
        Peaks averaged (odd) and the distance of kept centres along a run.
    end_block : bool
        Add a last centre ``window // 2`` peaks before a run's end where the steps leave
        its last peaks in no average (the block overlaps the one before it).

    Returns
    -------
    numpy.ndarray
        int64 positions: every ``step``-th peak from ``window // 2`` on with ``window // 2``
        peaks of its run on either side.
    """
    n = number.shape[0]
    half = window // 2
    out = np.empty(n, dtype=np.int64)
    m = 0
    first = 0
    while first < n:
        end = first + 1  # one past the run's last peak
        while end < n and not (
            col[end] - col[end - 1] != 1 or number[end] != number[end - 1] or jump[end - 1]
        ):
            end += 1
        length = end - first
        last = -1
        for pos in range(half, length - half, step):
            out[m] = first + pos
            m += 1
            last = pos
        if end_block and last >= 0 and last < length - 1 - half:
            out[m] = first + length - 1 - half
            m += 1
        first = end
    return out[:m]


@kernel()
def window_means(
    order: np.ndarray,
    idx: np.ndarray,
    window: int,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    row: np.ndarray,
    area: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Means of ``x, y, z, row, area`` over the ``window`` peaks around every centre.

    Parameters
    ----------
    order : numpy.ndarray
        The peaks in line, column order.
    idx : numpy.ndarray
        Positions (in that order) of the centres (:func:`run_centres`).
    window : int
        Peaks averaged (odd).
    x, y, z, row, area : numpy.ndarray
        Per-peak values.

    Returns
    -------
    tuple of numpy.ndarray
        float64 means, one per centre.
    """
    n = idx.shape[0]
    half = window // 2
    means = np.empty((5, n))
    for c in range(n):
        sx, sy, sz, sr, sa = 0.0, 0.0, 0.0, 0.0, 0.0
        for j in range(-half, half + 1):
            p = order[idx[c] + j]
            sx += np.float64(x[p])
            sy += np.float64(y[p])
            sz += np.float64(z[p])
            sr += np.float64(row[p])
            sa += np.float64(area[p])
        means[0, c] = sx / window
        means[1, c] = sy / window
        means[2, c] = sz / window
        means[3, c] = sr / window
        means[4, c] = sa / window
    return means[0].copy(), means[1].copy(), means[2].copy(), means[3].copy(), means[4].copy()
