"""Flanked peaks: untrusted peaks kept where the same line's trusted peaks flank them.

The peak detector (:mod:`~rasterserver_plugins.peak_detection`) drops a peak whose bounding
minima or flanks are unequal: a neighbouring line or an edge crowds one flank and the bias
cuts it unevenly, so its first moment may be biased. Most such peaks sit inside a line the
crowding touches for a column or two, where the line's own trusted peaks in the adjacent
columns say where it runs. Measured on the clinic scenes (BENCHMARKS.md "Real bodies",
2026-11-30 (31)), a dropped peak kept where

- both adjacent columns hold a trusted peak within :data:`REACH` px of its row,
- the two within ``span`` px of each other and their mean within ``tolerance`` px of it,
- their areas within a ratio of ``area_ratio`` (an arm's edge, where the trunk's line
  meets the arm's, puts a bright and a dim line on either side), and
- two columns out on both sides, a peak (trusted or not) continues the line within
  ``run_on`` px of the row the flanking step extrapolates to,

is located about as well as the line around it (0.146 px rms against the line's 0.048)
and numbered as safely; 13 % of the dropped peaks qualify. A peak dropped for being dim or
clipped is never kept: its location is doubtful whatever flanks it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["REACH", "FlankRule", "flanked"]

REACH = 2.5  # px: a flanking peak's row from the dropped peak's


class FlankRule(NamedTuple):
    """Thresholds of :func:`flanked` (px; the area ratio unitless); ``tolerance`` 0 keeps
    nothing, ``run_on`` 0 does not ask the line to run on."""

    tolerance: float = 0.4
    span: float = 1.5
    area_ratio: float = 1.5
    run_on: float = 1.0


def _nearest(keys: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Index into sorted ``keys`` (at least one) of the key nearest each of ``key``."""
    j = np.clip(np.searchsorted(keys, key), 1, max(keys.size - 1, 1))
    lo = np.clip(j - 1, 0, keys.size - 1)
    hi = np.clip(j, 0, keys.size - 1)
    return np.where(np.abs(keys[lo] - key) <= np.abs(keys[hi] - key), lo, hi)


def _sorted(key: np.ndarray, *others: np.ndarray) -> tuple[np.ndarray, ...]:
    """``key`` and ``others`` in the order of ``key``: the detector's peaks come sorted by
    column and row, and sorting them again would cost a third of the stage."""
    if key.size < 2 or np.all(key[1:] >= key[:-1]):
        return (key, *others)
    order = np.argsort(key, kind="stable")
    return (key[order], *(o[order] for o in others))


def flanked(
    col: np.ndarray,
    row: np.ndarray,
    area: np.ndarray,
    trusted: np.ndarray,
    candidate: np.ndarray,
    rule: FlankRule,
    height: int,
) -> np.ndarray:
    """Which of the ``candidate`` peaks trusted peaks of the same line flank.

    Parameters
    ----------
    col, row, area : numpy.ndarray
        Per-peak column, sub-pixel row and area of every peak found (trusted or not).
    trusted : numpy.ndarray
        Boolean mask of the trusted peaks.
    candidate : numpy.ndarray
        Boolean mask of the untrusted peaks that may be kept (dropped for unequal minima or
        flanks only, not dim, not clipped).
    rule : FlankRule
        The thresholds.
    height : int
        The frame's number of rows (rows of different columns are kept apart by it).

    Returns
    -------
    numpy.ndarray
        Boolean mask over all peaks: the candidates kept.
    """
    keep = np.zeros(col.size, dtype=bool)
    if rule.tolerance <= 0 or not np.any(candidate) or np.count_nonzero(trusted) < 2:
        return keep
    stride = height + 10.0  # wider than any row step between columns considered
    ts, ta = _sorted(col[trusted] * stride + row[trusted], area[trusted])
    c = np.flatnonzero(candidate)
    cc, cr = col[c].astype(np.float64), row[c]

    def flank(dc: int) -> tuple[np.ndarray, np.ndarray]:
        key = (cc + dc) * stride + cr
        i = _nearest(ts, key)
        d = ts[i] - key
        return np.where(np.abs(d) <= REACH, cr + d, np.nan), ta[i]

    rl, al = flank(-1)
    rr, ar = flank(+1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.maximum(al, ar) / np.minimum(al, ar)
        ok = np.isfinite(rl) & np.isfinite(rr)
        ok &= np.abs((rl + rr) / 2 - cr) <= rule.tolerance
        ok &= (np.abs(rl - rr) <= rule.span) & (ratio <= rule.area_ratio)
    if rule.run_on > 0:
        # the line runs on: any peak found (trusted or a candidate) where the flanking step
        # extrapolates to, two columns out on each side
        every = trusted | candidate
        akey = _sorted(col[every] * stride + row[every])[0]
        for dc, r in ((-2, 2 * rl - cr), (2, 2 * rr - cr)):
            key = (cc + dc) * stride + np.nan_to_num(r, nan=-1e6)
            ok &= np.abs(akey[_nearest(akey, key)] - key) <= rule.run_on
    keep[c[ok]] = True
    return keep
