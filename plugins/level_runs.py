"""Runs of a numbered component's levels placed on the code on their own, compiled.

:func:`.code_evidence.locally_contradicted` placed every run of ``span`` levels on every
offset of the code with a few whole-array passes per run (a cost matrix, its row sums, a
stable argsort for the best two): ~0.8 ms per frame, mostly numpy's call overhead on small
arrays. Here one loop per run and offset; each offset's cost is summed in numpy's pairwise
order (:mod:`.pairwise_sums`), so the costs, and the levels refused, are the same.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel

from .code_placements import best_two
from .pairwise_sums import pairwise_sum


@kernel(error_model="numpy")
def contradicted_levels(
    d: np.ndarray,
    w: np.ndarray,
    code: np.ndarray,
    offset: int,
    span: int,
    lam: float,
    tolerance: float,
    min_margin: float,
    max_cost_rate: float,
    poor_factor: float,
) -> np.ndarray:
    """Levels of a numbered component where a run of ``span`` levels contradicts its
    placement (:func:`.code_evidence.locally_contradicted`, which checks the sizes).

    Parameters
    ----------
    d, w : numpy.ndarray
        float64 level differences (NaN: unmeasured) and their weights.
    code : numpy.ndarray
        float64 kinds of the raster's lines.
    offset : int
        The component's placement.
    span, lam, tolerance, min_margin, max_cost_rate, poor_factor
        As :func:`.code_evidence.locally_contradicted`.

    Returns
    -------
    numpy.ndarray
        bool per level: in a contradicting run.
    """
    n_levels = d.shape[0] + 1
    bad = np.zeros(n_levels, dtype=np.bool_)
    n_off = code.shape[0] - span + 1
    n_terms = span - 1
    dd = np.empty(n_terms)
    ww = np.empty(n_terms)
    terms = np.empty(n_terms)
    cost = np.empty(n_off)
    scale = tolerance * lam
    for start in range(0, n_levels - span + 1, 2):
        n_measured = 0
        for j in range(n_terms):
            x, y = d[start + j], w[start + j]
            if not math.isnan(x) and y > 0:
                dd[j], ww[j] = x, y
                terms[n_measured] = y
                n_measured += 1
            else:
                dd[j], ww[j] = 0.0, 0.0
        total = pairwise_sum(terms, 0, n_measured)  # ww[measured].sum()
        here = offset + start
        if total < 0.5 * (span - 1) or not 0 <= here < n_off:
            continue
        for o in range(n_off):
            for j in range(n_terms):
                u = (dd[j] - (code[o + j] - code[o + j + 1]) * lam) / scale
                v = u * u
                terms[j] = (1.0 if v > 1.0 else v) * ww[j]
            cost[o] = pairwise_sum(terms, 0, n_terms)
        best, second = best_two(cost)
        if best == here:
            continue
        excess = cost[here] - cost[best]
        local_margin = cost[second] - cost[best]
        # another placement reads cleanly and uniquely here, or the component's placement
        # explains this run of lines far worse than the component as a whole allows
        clean_elsewhere = cost[best] <= max_cost_rate * total and local_margin >= min_margin
        poorly_explained = poor_factor > 0 and cost[here] > poor_factor * max_cost_rate * total
        if excess >= min_margin and (clean_elsewhere or poorly_explained):
            bad[start : start + span] = True
    return bad
