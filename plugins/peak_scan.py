"""The peak detector's scans, compiled with numba: extrema along each column, moments per peak.

:func:`rasterserver_plugins.peak_detection.detect_peaks` found the extrema with six passes over
the whole frame (slopes, masks, gathers) and walked the moments out from all maxima at once,
one pixel offset per step with a gather and a scatter each: ~4 of its ~10 ms. A scan reads
each pixel once. Both kernels give the same bits as those passes did (the integer indices
trivially; the moments add the same float32 terms to the same float64 sums in the same order,
offset by offset), so the plugin's version and results do not change.

Importing this module costs the numba import (~0.3 s): the detector imports it on first use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def column_extrema(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the maxima and minima of every row of ``s`` (a column per row).

    Parameters
    ----------
    s : numpy.ndarray
        ``(W, H)`` C-contiguous float32, one image column per row.

    Returns
    -------
    maxima, minima : numpy.ndarray
        int64 flat indices into ``s``, ascending.

    Notes
    -----
    Zero slopes are skipped, so a plateau belongs to the flank it continues: a flat top
    (saturation) gives one maximum at its last pixel, a flat background one minimum at its
    last pixel. A rising sentinel slope after each row's last pixel makes that pixel a
    minimum when the row ends falling, and keeps a peak cut by the image edge from pairing
    with the next row.
    """
    w, h = s.shape
    flat = s.ravel()
    maxima = np.empty(w * h // 2 + 1, dtype=np.int64)
    minima = np.empty(w * h // 2 + 1, dtype=np.int64)
    n_max = 0
    n_min = 0
    seen = False
    prev_up = False
    for r in range(w):
        row0 = r * h
        for c in range(h):
            i = row0 + c
            if c == h - 1:
                up = True  # the sentinel
            else:
                d = flat[i + 1] - flat[i]
                if d > 0:
                    up = True
                elif d < 0:
                    up = False
                else:
                    continue  # flat (or NaN): skipped
            if seen:
                if prev_up and not up:
                    maxima[n_max] = i
                    n_max += 1
                elif up and not prev_up:
                    minima[n_min] = i
                    n_min += 1
            seen = True
            prev_up = up
    return maxima[:n_max].copy(), minima[:n_min].copy()


@kernel()
def run_moments(
    tf: np.ndarray,
    m: np.ndarray,
    level: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    half: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zeroth and first moments of the run of pixels above ``level`` around each maximum.

    Parameters
    ----------
    tf : numpy.ndarray
        Flat float32 pixels, a column after the other.
    m, lo, hi : numpy.ndarray
        ``(N,)`` int64 flat indices of each peak's maximum and its window's ends.
    level : numpy.ndarray
        ``(N,)`` float32 bias of each peak.
    half : int
        Offsets walked at most on each side.

    Returns
    -------
    s0, s1 : numpy.ndarray
        ``(N,)`` float64 sums of ``tf - level`` and of ``offset * (tf - level)`` over the
        pixels of the run (the maximum's own term in ``s0``).
    extent : numpy.ndarray
        ``(2, N)`` int16 length of the run below and above the maximum.
    """
    n = m.shape[0]
    s0 = np.empty(n, dtype=np.float64)
    s1 = np.zeros(n, dtype=np.float64)
    extent = np.zeros((2, n), dtype=np.int16)
    zero = np.float32(0.0)
    for k in range(n):
        c = tf[m[k]] - level[k]
        centre = c if (c >= zero or c != c) else zero  # np.maximum(c, 0): NaN stays NaN
        acc0 = np.float64(centre)
        acc1 = 0.0
        if centre > 0:
            # below first, then above: the order the vectorised walk added them in
            for j in range(1, half + 1):
                pos = m[k] - j
                if pos < lo[k]:  # tested before the read: the window ends the frame
                    break
                v = tf[pos] - level[k]
                if not v > 0:
                    break
                acc0 += v
                acc1 += np.float32(-j) * v
                extent[0, k] = j
            for j in range(1, half + 1):
                pos = m[k] + j
                if pos > hi[k]:
                    break
                v = tf[pos] - level[k]
                if not v > 0:
                    break
                acc0 += v
                acc1 += np.float32(j) * v
                extent[1, k] = j
        s0[k] = acc0
        s1[k] = acc1
    return s0, s1, extent


@kernel()
def bounded_maxima(
    sf: np.ndarray, maxima: np.ndarray, minima: np.ndarray, h: int, min_height: np.float32
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The maxima high enough above both bounding minima, with those minima.

    Parameters
    ----------
    sf : numpy.ndarray
        Flat float32 smoothed pixels, a column of ``h`` after the other.
    maxima, minima : numpy.ndarray
        Ascending int64 flat indices from :func:`column_extrema`.
    h : int
        Pixels per column.
    min_height : numpy.float32
        Least rise and fall (compared in float32, as numpy compares a float32 array).

    Returns
    -------
    m, lo, hi : numpy.ndarray
        int64 flat indices of the kept maxima and of the nearest minimum on each side in
        the same column (the column's first or last pixel where there is none).
    """
    n, n_min = maxima.shape[0], minima.shape[0]
    m = np.empty(n, dtype=np.int64)
    lo_out = np.empty(n, dtype=np.int64)
    hi_out = np.empty(n, dtype=np.int64)
    k = 0
    i = 0  # minima below the current maximum: np.searchsorted(minima, maxima), walked
    for p in range(n):
        mx = maxima[p]
        while i < n_min and minima[i] < mx:
            i += 1
        col_start = (mx // h) * h
        lo = max(minima[i - 1], col_start) if i > 0 else col_start
        hi = min(minima[i], col_start + (h - 1)) if i < n_min else col_start + (h - 1)
        top = sf[mx]
        if top - sf[lo] >= min_height and top - sf[hi] >= min_height:
            m[k], lo_out[k], hi_out[k] = mx, lo, hi
            k += 1
    return m[:k].copy(), lo_out[:k].copy(), hi_out[:k].copy()
