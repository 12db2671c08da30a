"""Column neighbours on consecutive levels or raster lines and their area ratios, compiled.

The code evidence (:func:`.code_evidence.level_pairs`), the column bands
(:class:`.code_tiles.CodeBands`) and the pair check
(:func:`.numbering_checks.pair_contradictions`) each found the pairs of peaks directly above
one another in a column in a handful of whole-array masks over the peaks, gathered the two
areas, and grouped the pairs by a sort (the pair check by two radix argsorts, ~0.9 ms).
Here each is one loop. The ratios are divided as numpy divided them and their logarithm is
left to numpy (whose ``log`` is not the C library's), so the evidence is the same bits.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def peak_levels(
    line_id: np.ndarray, line_order: np.ndarray, line_component: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Component and level of every peak (-1 for peaks outside the lines).

    Parameters
    ----------
    line_id : numpy.ndarray
        Line of every peak (-1: none).
    line_order, line_component : numpy.ndarray
        Per-line level and component.

    Returns
    -------
    comp, lev : numpy.ndarray
        int64 per peak.
    """
    n = line_id.shape[0]
    comp = np.empty(n, dtype=np.int64)
    lev = np.empty(n, dtype=np.int64)
    for i in range(n):
        line = line_id[i]
        if line >= 0:
            comp[i] = line_component[line]
            lev[i] = line_order[line]
        else:
            comp[i] = -1
            lev[i] = -1
    return comp, lev


@kernel(error_model="numpy")
def level_pair_ratios(
    col: np.ndarray, area: np.ndarray, comp: np.ndarray, lev: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Column neighbours on consecutive levels of one component and their area ratio.

    Parameters
    ----------
    col, area : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    comp, lev : numpy.ndarray
        Per-peak component and level (-1: none).

    Returns
    -------
    k, ratio : numpy.ndarray
        Index of the upper peak of every pair (the lower is ``k + 1``) and
        ``area[k] / area[k + 1]`` in float64.
    """
    n = col.shape[0]
    k = np.empty(max(n - 1, 0), dtype=np.int64)
    ratio = np.empty(max(n - 1, 0))
    m = 0
    for i in range(n - 1):
        if (
            col[i + 1] == col[i]
            and comp[i + 1] == comp[i]
            and comp[i] >= 0
            and lev[i] >= 0
            and lev[i + 1] == lev[i] + 1
        ):
            k[m] = i
            ratio[m] = np.float64(area[i]) / np.float64(area[i + 1])
            m += 1
    return k[:m], ratio[:m]


@kernel(error_model="numpy")
def raster_pair_ratios(
    col: np.ndarray, area: np.ndarray, line_id: np.ndarray, line_pos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Column neighbours numbered as consecutive raster lines and their area ratio.

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_pos : numpy.ndarray
        Per-line index into the raster's lines (-1: unnumbered).

    Returns
    -------
    a, ratio : numpy.ndarray
        Index of the upper peak of every pair (the lower is ``a + 1``) and
        ``area[a] / area[a + 1]`` in float64.
    """
    n = col.shape[0]
    a = np.empty(max(n - 1, 0), dtype=np.int64)
    ratio = np.empty(max(n - 1, 0))
    m = 0
    here = -1
    if n > 0 and line_id[0] >= 0:
        here = line_pos[line_id[0]]
    for i in range(n - 1):
        below = line_pos[line_id[i + 1]] if line_id[i + 1] >= 0 else -1
        if col[i + 1] == col[i] and here >= 0 and below == here + 1:
            a[m] = i
            ratio[m] = np.float64(area[i]) / np.float64(area[i + 1])
            m += 1
        here = below
    return a[:m], ratio[:m]


@kernel()
def grouped_pairs(
    first: np.ndarray, second: np.ndarray, span: int
) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(first * span + second, return_inverse=True)`` without a comparison sort.

    Parameters
    ----------
    first, second : numpy.ndarray
        int64 ids in ``[0, span)``.
    span : int
        Bound of the ids.

    Returns
    -------
    keys, inv : numpy.ndarray
        The distinct keys ascending, and the index into them of every pair.
    """
    n = first.shape[0]
    if span * span <= max(8 * n, 1 << 16):
        # few lines: a table of every possible key, marked, then numbered in key order
        table = np.zeros(span * span, dtype=np.int64)
        for i in range(n):
            table[first[i] * span + second[i]] = 1
        n_keys = 0
        for key in range(span * span):
            if table[key]:
                table[key] = n_keys
                n_keys += 1
        keys = np.empty(n_keys, dtype=np.int64)
        inv = np.empty(n, dtype=np.int64)
        for i in range(n):
            key = first[i] * span + second[i]
            inv[i] = table[key]
            keys[inv[i]] = key
        return keys, inv
    # many: least significant id first, then the most (each counting sort is stable)
    by_second = _counting_order(second, np.arange(n), span)
    order = _counting_order(first, by_second, span)
    keys = np.empty(n, dtype=np.int64)
    inv = np.empty(n, dtype=np.int64)
    m = -1
    last = -1
    for j in range(n):
        i = order[j]
        key = first[i] * span + second[i]
        if m < 0 or key != last:
            m += 1
            keys[m] = key
            last = key
        inv[i] = m
    return keys[: m + 1], inv


@kernel()
def _counting_order(ids: np.ndarray, within: np.ndarray, span: int) -> np.ndarray:
    """The permutation ``within`` stably sorted by ``ids[within]`` (ids in ``[0, span)``)."""
    start = np.zeros(span + 1, dtype=np.int64)
    for i in within:
        start[ids[i] + 1] += 1
    for v in range(span):
        start[v + 1] += start[v]
    out = np.empty_like(within)
    for i in within:
        out[start[ids[i]]] = i
        start[ids[i]] += 1
    return out


@kernel()
def band_keys(
    k: np.ndarray,
    lr: np.ndarray,
    comp: np.ndarray,
    lev: np.ndarray,
    col: np.ndarray,
    compact: np.ndarray,
    step: int,
    n_bands: int,
    n_lev: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Every level pair's key in the two overlapping column bands holding it, and its ratio.

    Parameters
    ----------
    k, lr : numpy.ndarray
        Level pairs (upper peaks) and their log ratios (:func:`.code_evidence.level_pairs`).
    comp, lev, col : numpy.ndarray
        Per-peak component, level and column.
    compact : numpy.ndarray
        Compact index of every component with pairs.
    step : int
        Columns between the starts of two bands.
    n_bands, n_lev : int
        Bands and levels (the keys' strides).

    Returns
    -------
    keys, ratios : numpy.ndarray
        ``(compact component * n_bands + band) * n_lev + level``: first every pair in its
        own band, then every pair in the band before (where there is one), each in pair
        order (the order in which the robust centres add them up).
    """
    n = k.shape[0]
    keys = np.empty(2 * n, dtype=np.int64)
    ratios = np.empty(2 * n)
    m = 0
    for db in range(2):
        for j in range(n):
            i = k[j]
            band = col[i] // step - db
            if band >= 0:
                keys[m] = (compact[comp[i]] * n_bands + band) * n_lev + lev[i]
                ratios[m] = lr[j]
                m += 1
    return keys[:m], ratios[:m]
