"""numpy's order of summation, for compiled loops that must give the bits numpy gave.

``ndarray.sum`` along a contiguous axis does not add left to right: it sums blocks of up to
128 values in eight interleaved partial sums, combined as a tree, and halves longer runs
recursively (pairwise summation), starting from the identity 0.0. A kernel that replaces
such a sum adds in that order here; ``bincount`` and ``cumsum`` add left to right and need
nothing of this.

Importing this module costs the numba import (~0.3 s): kernels' modules import it.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def _block(values: np.ndarray, start: int, n: int) -> float:
    """numpy's ``pairwise_sum`` of up to 128 values: eight interleaved partial sums."""
    if n < 8:
        res = 0.0
        for i in range(start, start + n):
            res += values[i]
        return res
    r0, r1, r2, r3 = values[start], values[start + 1], values[start + 2], values[start + 3]
    r4, r5, r6, r7 = values[start + 4], values[start + 5], values[start + 6], values[start + 7]
    i = 8
    while i < n - n % 8:
        j = start + i
        r0 += values[j]
        r1 += values[j + 1]
        r2 += values[j + 2]
        r3 += values[j + 3]
        r4 += values[j + 4]
        r5 += values[j + 5]
        r6 += values[j + 6]
        r7 += values[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += values[start + i]
        i += 1
    return res


@kernel()
def _halves(values: np.ndarray, start: int, n: int) -> float:
    """numpy's ``pairwise_sum`` of more than 128 values: the two halves' sums (a multiple of
    8 in the first), recursively. An explicit stack: numba's cache cannot hold a
    recursive function."""
    starts = np.empty(64, dtype=np.int64)
    sizes = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)  # 0: left half next, 1: right half, 2: add them
    left = np.empty(64)
    top = 0
    starts[0], sizes[0] = start, n
    ret = 0.0
    while top >= 0:
        s, m = starts[top], sizes[top]
        if m <= 128:
            ret = _block(values, s, m)
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 0:
            stage[top] = 1
            top += 1
            starts[top], sizes[top], stage[top] = s, half, 0
        elif stage[top] == 1:
            left[top] = ret
            stage[top] = 2
            top += 1
            starts[top], sizes[top], stage[top] = s + half, m - half, 0
        else:
            ret = left[top] + ret
            top -= 1
    return ret


@kernel()
def pairwise_sum(values: np.ndarray, start: int, n: int) -> float:
    """``values[start:start + n].sum()`` as numpy takes it along a contiguous axis.

    Parameters
    ----------
    values : numpy.ndarray
        float64 values (1-D).
    start, n : int
        First index and number of the values summed.

    Returns
    -------
    float
        The sum, the same bits as numpy's.
    """
    return 0.0 + (_block(values, start, n) if n <= 128 else _halves(values, start, n))
