"""A long line's end lying among unnumbered peaks: a line carried onto a refused surface.

Where a waistband's side edge crosses the lines at a back's lower corners, the cloth stands
off the skin so that it shows the next raster line where the skin's line would continue:
the line runs on without a gap, a step or a change of height, and its last columns carry
the skin's number onto the cloth's next line. The cloth's own lines are refused (their code
places them a level off, or is too short to read), so the end of such a line lies among
unnumbered peaks, while the end of a line at the body's silhouette lies among numbered
lines with the background beyond (no peaks at all). The peaks near the end of a long line
are refused where the unnumbered peaks number at least ``share`` of all the peaks in the
square of ``window`` line spacings around them.

Only long lines are judged: in hair, strands cut the lines into dashes whose every end lies
among the unnumbered fragments of the dashes beside it, and a dash's end is a strand, not a
surface's edge (on the window-7 tuning scenes, one pass over the last twelve peaks: lines of
any length 33 -> 6 wrong peaks for 4,079 of the back's crossings, lines of 80 numbered
peaks or more 33 -> 7 for 1,546). Three passes, each among the peaks the pass before left,
erode the longer pieces (7829: 11 peaks of a line on the cloth): on the clinic tuning
scenes (AMD EPYC renderings) 95 wrongly numbered peaks -> 22, for 0.05-0.06 point of the
back's coverage.
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs
from .peak_checks import doubtful_share

__all__ = ["ends_among_unnumbered"]


def ends_among_unnumbered(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray | None,
    *,
    reach: int = 8,
    share: float = 0.4,
    window: float = 2.0,
    min_length: int = 80,
    passes: int = 3,
) -> np.ndarray:
    """Numbered peaks near a long line's end that lie among unnumbered peaks.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``; ``line_id`` -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    spacing : numpy.ndarray or None
        Per-peak local line spacing in rows (:func:`.numbering_checks.local_spacing`); None
        (no pair of consecutive numbered lines) refuses nothing.
    reach : int
        The numbered peaks at each end of a line that are judged (0: none).
    share : float
        Least share of unnumbered peaks among all the peaks around a judged peak (itself
        included) that refuses it.
    window : float
        Half-width, in local line spacings, of the square in which the peaks are counted.
    min_length : int
        Least number of numbered peaks of a line whose ends are judged.
    passes : int
        Times the ends are judged, each time among the peaks the last pass left: a line's
        piece on the cloth ends among more unnumbered peaks once its last peaks are
        refused, a line's end on the skin among numbered ones still.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    refused = np.zeros(col.size, dtype=bool)
    if spacing is None or reach <= 0 or col.size == 0:
        return refused
    number = np.asarray(number)
    more = None
    for _ in range(passes):
        more = _one_pass(col, row, line_id, np.where(refused, -1, number), spacing, reach,
                         share, window, min_length, changed=more)  # fmt: skip
        if not np.any(more):
            break
        refused |= more
    return refused


def _one_pass(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    reach: int,
    share: float,
    window: float,
    min_length: int,
    changed: np.ndarray | None = None,
) -> np.ndarray:
    """The peaks one pass of :func:`ends_among_unnumbered` refuses; after a pass that
    refused ``changed``, only the end peaks it could have changed are judged again."""
    refused = np.zeros(col.size, dtype=bool)
    lid = np.where(number >= 0, line_id, -1).astype(np.int64)
    idx = np.flatnonzero(lid >= 0)
    if idx.size == 0:
        return refused
    order, starts, stops = line_runs(lid, idx)  # numbered peaks, line by line
    # each numbered peak's distance (in numbered peaks) from its line's nearer end
    rank = np.arange(order.size) - np.repeat(starts, stops - starts)
    length = np.repeat(stops - starts, stops - starts)
    near_end = (np.minimum(rank, length - 1 - rank) < reach) & (length >= min_length)
    at = order[near_end]
    if changed is not None and at.size:
        # A peak the last pass kept keeps its verdict unless its line lost peaks (its end
        # moved) or a peak refused since lies in its square: the rest are not counted again
        # (~2.3 ms a frame less on the mseq7 tuning set; BENCHMARKS "Real bodies" (14)).
        lost = np.zeros(int(np.max(line_id, initial=-1)) + 2, dtype=bool)
        lost[line_id[changed]] = True
        gone = np.sort(col[changed])
        half = window * np.asarray(spacing, dtype=np.float64)[at]
        near = np.searchsorted(gone, col[at] + half, "right") > np.searchsorted(
            gone, col[at] - half, "left"
        )
        at = at[near | lost[line_id[at]]]
    if at.size == 0:
        return refused
    n_unnumbered, n_numbered = doubtful_share(
        col, row, at, number < 0, number >= 0, spacing, window
    )
    refused[at[n_unnumbered >= share * (n_unnumbered + n_numbered)]] = True
    return refused
