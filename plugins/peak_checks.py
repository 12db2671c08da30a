"""Peak-by-peak checks of numbered peaks: along their line and in their column.

Line numbering decides numbers by component and by line; these checks then judge single
peaks where the image speaks against their line's number locally: a line that jumps onto
its neighbour (:func:`line_jumps`), a peak nothing in its column confirms
(:func:`isolated_peaks`), a peak directly beside a doubtful one with no gap between
(:func:`beside_doubtful`), what the others leave of a line between refused peaks
(:func:`stranded_runs`) and a line's end run onto another surface (:func:`line_ends`).
:func:`.numbering_refusals.refuse_peaks` runs them in order.
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import by_line, local_spacing

__all__ = [
    "beside_doubtful",
    "column_islands",
    "doubtful_share",
    "isolated_peaks",
    "line_ends",
    "line_jumps",
    "numbered_column_neighbours",
    "stranded_runs",
]


def line_jumps(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    max_jump: float = 0.3,
    max_columns: int = 2,
    spacing: np.ndarray | None = None,
) -> np.ndarray:
    """Numbered peaks where their line jumps: two consecutive peaks of a line (at most
    ``max_columns`` apart) whose row step departs from the line's steps on either side by
    more than ``max_jump`` of the local line spacing (or, at a line's end, from the next
    step). Line search took a peak of the neighbouring line there (where lines are dim and
    crowd); both peaks are refused, the image cannot tell which one it was.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    max_jump : float
        Largest departure of a step, in local line spacings.
    max_columns : int
        Largest column gap between consecutive peaks of a line that is judged.
    spacing : numpy.ndarray, optional
        Per-peak local line spacing (:func:`local_spacing`), when already computed.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    n = col.size
    out = np.zeros(n, dtype=bool)
    lid = line_id.astype(np.int64)
    idx = np.flatnonzero((lid >= 0) & (number >= 0))
    if idx.size < 3:
        return out
    if spacing is None:
        spacing = local_spacing(col, row, number)
    if spacing is None:
        return out
    from .line_steps import jumping_peaks  # compiled; the numba import costs ~0.3 s

    order = idx[by_line(lid[idx])]
    return jumping_peaks(
        order.astype(np.int64),
        lid,
        col.astype(np.int64),
        np.asarray(row, dtype=np.float64),
        np.asarray(spacing, dtype=np.float64),
        float(max_jump),
        int(max_columns),
    )


def beside_doubtful(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    doubtful: np.ndarray,
    spacing: np.ndarray,
    *,
    max_gap: float = 1.25,
    min_share: float = 0.0,
    window: float = 2.0,
) -> np.ndarray:
    """Numbered peaks directly above or below a doubtful peak, with no gap between them.

    Doubtful peaks are those of a block the code bands refused as ordered levels off
    (:mod:`.code_tiles`: the cloth below a waistband, where a line is hidden along the
    edge) and those out of order in their column (:func:`column_order_conflicts`: a peak
    of the neighbouring line taken where lines crowd). Where a gap of 1.5 spacings or more
    separates a numbered peak from them, the hidden line shows and the numbered peak is
    safe; where the gap is about one spacing, the image cannot tell on which side of the
    numbered peak the line went missing: at a flank, a line's end crosses the edge and
    carries its number onto the block's next line. Such a peak is refused (on the clinic
    tuning scenes, 63 % of the wrong peaks for 0.2 % of the back's coverage).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    doubtful : numpy.ndarray
        ``(N,)`` bool, the doubtful peaks.
    spacing : numpy.ndarray
        Per-peak local line spacing (:func:`local_spacing`).
    max_gap : float
        Largest row gap, in local line spacings, at which a neighbour in the column counts
        as directly beside.
    min_share : float
        With a share above 0, a peak beside a doubtful one is refused only where the
        doubtful peaks around it (:func:`doubtful_share`) number at least ``min_share``
        of the numbered ones: a line's end carried onto a refused block lies among the
        block's peaks, while the lines beside a lone refused line (or a lone peak out of
        order) have numbered neighbours that confirm them.
    window : float
        Half-width, in local line spacings, of the square around a peak in which
        :func:`doubtful_share` counts.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    if col.size < 2 or not np.any(doubtful):
        return np.zeros(col.size, dtype=bool)
    from .check_scans import beside_flags  # compiled; the numba import costs ~0.3 s

    out = beside_flags(
        col,
        np.asarray(row, dtype=np.float64),
        number,
        np.asarray(doubtful, dtype=bool),
        np.asarray(spacing, dtype=np.float64),
        float(max_gap),
    )
    if min_share > 0 and np.any(out):
        cand = np.flatnonzero(out)
        numbered = number >= 0
        n_doubtful, n_numbered = doubtful_share(col, row, cand, doubtful, numbered, spacing, window)
        out[cand[n_doubtful < min_share * n_numbered]] = False
    return out


def doubtful_share(
    col: np.ndarray,
    row: np.ndarray,
    at: np.ndarray,
    doubtful: np.ndarray,
    numbered: np.ndarray,
    spacing: np.ndarray,
    window: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Doubtful and numbered peaks in the square of ``window`` local spacings around
    peaks ``at`` (both counts include the peak itself when it is either).

    On the clinic tuning scenes, of the numbered peaks directly beside a doubtful one, the
    wrong ones (a line's end carried onto a cloth's next line) had at least half as many
    doubtful as numbered peaks around them in 144 of 156 cases, the right ones in 1,291 of
    23,563 (the lines along the block's edge).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    at : numpy.ndarray
        Indices of the peaks to count around.
    doubtful, numbered : numpy.ndarray
        ``(N,)`` bool flags counted.
    spacing : numpy.ndarray
        Per-peak local line spacing (:func:`local_spacing`).
    window : float
        Half-width of the square, in local line spacings.

    Returns
    -------
    n_doubtful, n_numbered : numpy.ndarray
        ``(len(at),)`` int64 counts.
    """
    half = window * np.asarray(spacing, dtype=np.float64)[at]
    reach = int(np.ceil(half.max(initial=0.0)))
    # one key orders the peaks as they are sorted: a column's rows stay inside its stride
    stride = float(np.ceil(np.max(row, initial=0.0))) + 2.0 * reach + 2.0
    rows = np.asarray(row, dtype=np.float64)
    key = col.astype(np.float64) * stride + rows
    from .check_scans import doubtful_counts  # compiled; the numba import costs ~0.3 s

    return doubtful_counts(
        key,
        col,
        rows,
        np.asarray(at, dtype=np.int64),
        half,
        np.asarray(doubtful, dtype=bool),
        np.asarray(numbered, dtype=bool),
        stride,
        reach,
    )


def isolated_peaks(col: np.ndarray, number: np.ndarray) -> np.ndarray:
    """Numbered peaks with no numbered peak directly above or below them in their column.

    Such a peak is numbered by the continuity of its line alone: nothing in its column
    confirms the number, and the column order check cannot judge it. On the clinic scenes
    these were mostly a line's first or last peaks taken from the neighbouring line where
    lines crowd at a cloth's side edge or a silhouette, and lines next to a refused block.

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    if col.size == 0:
        return np.zeros(0, dtype=bool)
    above, below = numbered_column_neighbours(col, number)
    return (number >= 0) & ~above & ~below


def numbered_column_neighbours(col: np.ndarray, number: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per peak, whether the peak directly above it and the one directly below it in its
    column (the previous and next peak of the ``(col, row)`` order, at any gap) are numbered.

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.

    Returns
    -------
    above, below : numpy.ndarray
        ``(N,)`` bool each.
    """
    col, number = np.asarray(col), np.asarray(number)
    if col.size == 0:
        return np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)
    same_prev = np.r_[False, col[1:] == col[:-1]]
    same_next = np.r_[col[1:] == col[:-1], False]
    above = same_prev & (np.r_[-1, number[:-1]] >= 0)
    below = same_next & (np.r_[number[1:], -1] >= 0)
    return above, below


def column_islands(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    *,
    min_peaks: int = 3,
    min_gap: float = 2.5,
) -> np.ndarray:
    """Numbered peaks in short runs of consecutive numbers in their column, far from any
    other numbered peak of the column.

    A run is a column's numbered peaks whose numbers go up one by one at about one local
    spacing apart. A run of fewer than ``min_peaks`` with no numbered peak within
    ``min_gap`` spacings above and below is numbered by its lines' order alone, across
    the gaps where the lines between went unfound: the image does not show how many were
    hidden there (a bright cloth whose clipped peaks were dropped: two lines numbered
    four off, held-out scene 15994).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    spacing : numpy.ndarray
        Per-peak local line spacing (:func:`local_spacing`).
    min_peaks : int
        Least peaks of a run that stands alone.
    min_gap : float
        Gap, in local spacings, that makes a run stand alone.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    if min_peaks <= 1:
        return np.zeros(col.size, dtype=bool)
    from .check_scans import island_flags  # compiled; the numba import costs ~0.3 s

    return island_flags(
        col,
        np.asarray(row, dtype=np.float64),
        number,
        np.asarray(spacing, dtype=np.float64),
        int(min_peaks),
        float(min_gap),
    )


def stranded_runs(line_id: np.ndarray, number: np.ndarray, min_run: int) -> np.ndarray:
    """Numbered peaks in runs of fewer than ``min_run`` along their line, next to peaks of
    the same line that were refused.

    The peak checks refuse a line's peaks where the evidence speaks against them (out of
    column order, beside a block ordered off, alone in their column). What they leave of a
    line between refused peaks, a few columns long, lies in the same confusion (on the
    clinic tuning scenes: a line's end at a cloth's side edge, partly refused, partly not)
    and nothing but the line's continuity through refused peaks carries its number there.

    Parameters
    ----------
    line_id : numpy.ndarray
        Line of every peak (-1: none), peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    min_run : int
        Least length (peaks) of a run kept beside refused peaks.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    order, line = _line_by_line(line_id)
    if order.size == 0:
        return np.zeros(line_id.size, dtype=bool)
    from .check_scans import stranded_flags  # compiled; the numba import costs ~0.3 s

    return stranded_flags(order, line, number, int(min_run))


def _line_by_line(line_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 indices of the peaks of a line, line by line, each line in column order (the
    peaks' order), and the line of each."""
    lid = line_id.astype(np.int64)
    idx = np.flatnonzero(lid >= 0)
    order = idx[by_line(lid[idx])].astype(np.int64)
    return order, lid[order]


def line_ends(
    line_id: np.ndarray,
    number: np.ndarray,
    height: np.ndarray,
    *,
    min_refused: int = 6,
    margin: int = 3,
    dim_ratio: float = 0.3,
    inner: int = 6,
    jump: float = 0.0,
) -> np.ndarray:
    """Numbered peaks at the ends of a line's numbered peaks that the end leaves in doubt.

    Three kinds of end, all where a line runs off one surface onto another (on the clinic
    tuning scenes: a line's end crossing a cloth's side edge or the edge of an arm, where
    the next surface shows the next raster line at the same row):

    - beyond at least ``min_refused`` refused (or otherwise unnumbered) peaks of the line,
      its first ``margin`` numbered peaks: the checks that refused the end place the change
      of surface to a few columns only, and nothing but the line's continuity carries the
      number of the peaks next to it;
    - the end peak, when lower than ``dim_ratio`` of the mean height of the ``inner``
      numbered peaks next to it: a line dims gradually where its surface turns away, so a
      sudden drop in its last column is a peak of another surface (or a pixel shared with
      it);
    - the end peak, when ``jump`` times higher or lower than the two numbered peaks next
      to it: along one line the kind and the lighting change slowly, so a step of that
      size between neighbouring columns is the edge of another surface, and the end peak
      lies on it (an arm's line where the trunk's line turns away, the skin beside a
      cloth's line).

    Parameters
    ----------
    line_id : numpy.ndarray
        Line of every peak (-1: none), peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    height : numpy.ndarray
        Height of every peak.
    min_refused, margin : int
        Unnumbered peaks beyond an end that make its first ``margin`` numbered peaks
        doubtful (``margin`` 0: none).
    dim_ratio : float
        Share of the inner peaks' mean height below which the end peak is doubtful (0:
        none).
    inner : int
        Numbered peaks the end peak is compared with.
    jump : float
        Factor of the step in height from the two numbered peaks next to the end peak up
        or down to it that makes it doubtful (0: none).

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    order, line = _line_by_line(line_id)
    if order.size == 0 or (margin <= 0 and dim_ratio <= 0 and jump <= 0):
        return np.zeros(line_id.size, dtype=bool)
    from .check_scans import end_flags  # compiled; the numba import costs ~0.3 s

    return end_flags(
        order,
        line,
        number,
        np.asarray(height, dtype=np.float64),
        int(min_refused),
        int(margin),
        float(dim_ratio),
        int(inner),
        float(jump),
    )
