"""A component's level differences placed on the code, and its levels' kinds, compiled.

:func:`.code_evidence.code_fit` costs every placement of a component on the code in a few
whole-array passes and a stable argsort, and :func:`.code_evidence.observed_kinds` runs its
two-state Viterbi passes on Python floats: tens of microseconds per component, and a
fragmented clinic frame has a hundred components or more. Here each is one loop. The costs
are summed in numpy's pairwise order (:mod:`.pairwise_sums`), the Viterbi minima are taken
as Python's ``min`` takes them, so the fits and the kinds are the same bits.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel

from .pairwise_sums import pairwise_sum


@kernel()
def best_two(cost: np.ndarray) -> tuple[int, int]:
    """The first two indices of ``np.argsort(cost, kind="stable")`` (NaN sorted last; -1
    where ``cost`` has fewer entries).

    Parameters
    ----------
    cost : numpy.ndarray
        float64 costs.

    Returns
    -------
    best, second : int
        The index of the smallest cost (the first of equals) and of the next.
    """
    best, second = -1, -1
    for i in range(cost.shape[0]):
        c = cost[i]
        if math.isnan(c):
            continue
        if best < 0 or c < cost[best]:
            best, second = i, best
        elif second < 0 or c < cost[second]:
            second = i
    # NaN costs follow the others, in index order
    for i in range(cost.shape[0]):
        if best >= 0 and second >= 0:
            break
        if math.isnan(cost[i]):
            if best < 0:
                best = i
            elif second < 0:
                second = i
    return best, second


@kernel(error_model="numpy")
def placement_costs(
    d: np.ndarray, weight: np.ndarray, code: np.ndarray, lam: float, tolerance: float
) -> tuple[np.ndarray, float, int]:
    """Soft count of the badly explained differences at every placement on the code.

    Parameters
    ----------
    d, weight : numpy.ndarray
        float64 level differences (NaN: unmeasured) and their weights.
    code : numpy.ndarray
        float64 kinds of the raster's lines, at least ``d.size + 1`` of them.
    lam, tolerance : float
        As :func:`.code_evidence.code_fit`.

    Returns
    -------
    cost, terms, n_measured
        ``(code.size - d.size,)`` costs, the total weight of the measured differences and
        their number.
    """
    n_terms = d.shape[0]
    n_off = code.shape[0] - n_terms
    dd = np.empty(n_terms)
    ww = np.empty(n_terms)
    values = np.empty(n_terms)
    n_measured = 0
    for j in range(n_terms):
        if not math.isnan(d[j]) and weight[j] > 0:
            dd[j], ww[j] = d[j], weight[j]
            values[n_measured] = weight[j]
            n_measured += 1
        else:
            dd[j], ww[j] = 0.0, 0.0
    terms = pairwise_sum(values, 0, n_measured)  # weight[measured].sum()
    scale = tolerance * lam
    cost = np.empty(n_off)
    for o in range(n_off):
        for j in range(n_terms):
            u = (dd[j] - (code[o + j] - code[o + j + 1]) * lam) / scale
            v = u * u
            values[j] = (1.0 if v > 1.0 else v) * ww[j]
        cost[o] = pairwise_sum(values, 0, n_terms)
    return cost, terms, n_measured


@kernel()
def _first_min(x: float, y: float) -> float:
    """Python's ``min(x, y)``: ``y`` only when it is smaller."""
    return y if y < x else x


@kernel(error_model="numpy")
def level_kinds(d: np.ndarray, weight: np.ndarray, lam: float, tolerance: float) -> np.ndarray:
    """Most likely kind of every level from the differences alone, by Viterbi
    (:func:`.code_evidence.observed_kinds`, for at least one difference).

    Parameters
    ----------
    d, weight : numpy.ndarray
        float64 level differences (NaN: unmeasured) and their weights.
    lam, tolerance : float
        Log area ratio of a heavy to a light line; departure counted as a miss.

    Returns
    -------
    numpy.ndarray
        ``(d.size + 1,)`` int8: 0 light, 1 heavy, -1 unknown.
    """
    n = d.shape[0] + 1
    scale = tolerance * lam
    # cost[k, a * 2 + b]: level k of kind a followed by level k + 1 of kind b
    expect = (0.0 * lam, -1.0 * lam, 1.0 * lam, 0.0 * lam)
    cost = np.empty((n - 1, 4))
    for k in range(n - 1):
        measured = not math.isnan(d[k])
        x = d[k] if measured else 0.0
        w = weight[k] if measured else 0.0
        for s in range(4):
            u = (x - expect[s]) / scale
            v = u * u
            cost[k, s] = (1.0 if v > 1.0 else v) * w
    fwd = np.zeros((n, 2))
    f0, f1 = 0.0, 0.0
    for k in range(n - 1):
        c00, c01, c10, c11 = cost[k, 0], cost[k, 1], cost[k, 2], cost[k, 3]
        f0, f1 = _first_min(f0 + c00, f1 + c10), _first_min(f0 + c01, f1 + c11)
        fwd[k + 1, 0], fwd[k + 1, 1] = f0, f1
    bwd = np.zeros((n, 2))  # bwd[k]: the best cost of the levels after k
    b0, b1 = 0.0, 0.0
    for k in range(n - 2, -1, -1):
        c00, c01, c10, c11 = cost[k, 0], cost[k, 1], cost[k, 2], cost[k, 3]
        b0, b1 = _first_min(c00 + b0, c01 + b1), _first_min(c10 + b0, c11 + b1)
        bwd[k, 0], bwd[k, 1] = b0, b1
    kinds = np.full(n, -1, dtype=np.int8)
    for k in range(n):
        seen = (k < n - 1 and not math.isnan(d[k])) or (k > 0 and not math.isnan(d[k - 1]))
        gap = (fwd[k, 0] + bwd[k, 0]) - (fwd[k, 1] + bwd[k, 1])  # > 0: heavy explains better
        if seen and abs(gap) >= 0.5:
            kinds[k] = 1 if gap > 0 else 0
    return kinds
