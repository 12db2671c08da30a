"""Robust centres of grouped log area ratios, compiled with numba.

:func:`rasterserver_plugins.code_evidence.robust_centres` took them with eight ``bincount``
passes and their temporaries (a ratio's distance to its group's centre, twice over, the
near ones gathered twice each): ~1 ms per call, and the numbering calls it twice per frame.
Here each pass is one loop over the ratios. The sums are taken in the same order as
``bincount`` takes them (ratio by ratio), so the centres are the same bits.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def grouped_centres(
    key: np.ndarray, lr: np.ndarray, windows: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust centre, count and mean absolute spread of the ratios of every key.

    Parameters
    ----------
    key : numpy.ndarray
        ``(N,)`` non-negative int64 group of every ratio.
    lr : numpy.ndarray
        ``(N,)`` float64 ratios, finite.
    windows : numpy.ndarray
        Half-widths of the successive means around the previous centre.

    Returns
    -------
    groups, centre, count, spread : numpy.ndarray
        One entry per key present, ascending.
    """
    n = key.shape[0]
    n_keys = 0
    for i in range(n):
        n_keys = max(n_keys, key[i] + 1)
    counts = np.zeros(n_keys, dtype=np.int64)
    total = np.zeros(n_keys)
    clipped = np.empty(n)
    for i in range(n):
        v = min(max(lr[i], -1.0), 1.0)
        clipped[i] = v
        counts[key[i]] += 1
        total[key[i]] += v
    centre = np.empty(n_keys)
    for g in range(n_keys):
        centre[g] = total[g] / max(counts[g], 1)
    near_total = np.empty(n_keys)
    near_count = np.empty(n_keys, dtype=np.int64)
    for window in windows:
        near_total[:] = 0.0
        near_count[:] = 0
        for i in range(n):
            g = key[i]
            if abs(clipped[i] - centre[g]) <= window:
                near_total[g] += clipped[i]
                near_count[g] += 1
        for g in range(n_keys):
            if near_count[g] > 0:
                centre[g] = near_total[g] / max(near_count[g], 1)
    spread_total = np.zeros(n_keys)
    for i in range(n):
        spread_total[key[i]] += abs(clipped[i] - centre[key[i]])
    n_groups = 0
    for g in range(n_keys):
        if counts[g] > 0:
            n_groups += 1
    groups = np.empty(n_groups, dtype=np.int64)
    out_centre = np.empty(n_groups)
    out_count = np.empty(n_groups, dtype=np.int64)
    spread = np.empty(n_groups)
    k = 0
    for g in range(n_keys):
        if counts[g] > 0:
            groups[k] = g
            out_centre[k] = centre[g]
            out_count[k] = counts[g]
            spread[k] = spread_total[g] / max(counts[g], 1)
            k += 1
    return groups, out_centre, out_count, spread
