"""Numbered pieces that nothing holds to the frame's main numbered block any more.

A piece of a component takes its number from the component's line order, and that order
rests on the contacts between its lines and the rest: column neighbours one spacing apart,
a line running on. The checks after the numbering refuse peaks where those contacts were
false (a depth step, a line skipped on a dark cloth, a line's end run onto another
surface), and a piece may be left numbered whose every contact with the rest was such a
peak: its number now rests on evidence the numbering itself refused. Below a waistband,
on the window-8 tuning twin of the held-out raster, such pieces of the cloth (a few lines
of 6-25 peaks each) were numbered one or two lines off with the back's component, and a
block of short lines at the frame's top two off.

The numbered peaks are joined into blocks by the contacts that still stand: two peaks of
one line and number at most ``col_gap`` columns apart, and column neighbours numbered
``n`` and ``n + 1`` whose gap lies within ``gap_low``-``gap_high`` times the single gaps
beside them in their column (:func:`.skipped_lines.consecutive_pairs`) and whose
brightness ratio departs from the code's at their numbers by at most ``brightness``
(natural log of the peak areas' ratio: a material's edge, as skin onto a dark cloth,
changes it by a factor of 3-7; a misread kind by the code's own ratio). Every block but
the frame's largest with at most ``max_peaks`` peaks is refused: too small for its own
code to have decided its number (a code window's lines over a few columns), it has no
contact left with the block that was decided.
"""

from __future__ import annotations

import numpy as np

from rasterserver.raster import Raster

from .skipped_lines import consecutive_pairs

__all__ = ["detached_pieces", "numbered_blocks"]


def numbered_blocks(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    area: np.ndarray,
    raster: Raster,
    *,
    col_gap: int = 2,
    gap_low: float = 0.6,
    gap_high: float = 1.6,
    brightness: float = 1.0,
) -> np.ndarray:
    """Label the numbered peaks by the blocks their standing contacts join them into.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``; ``line_id`` -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    area : numpy.ndarray
        Per-peak area.
    raster : Raster
        The diapositive's code (its line widths give the expected brightness ratios).
    col_gap : int
        Largest column step between two peaks of one line that joins them.
    gap_low, gap_high : float
        Range of a column pair's gap, in medians of the single gaps beside it, that joins
        it (a pair with too few gaps beside it to judge joins when its brightness agrees).
    brightness : float
        Largest departure of a column pair's log area ratio from the code's at its numbers.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` int64 block label (a peak of the block), -1 for unnumbered peaks.
    """
    number = np.asarray(number)
    labels = np.full(number.size, -1, dtype=np.int64)
    if not np.any(number >= 0):
        return labels
    a, b, gap, median = consecutive_pairs(col, row, number)
    log_width = np.log(np.asarray(raster.widths, dtype=np.float64))
    # the raster's index of every number (numbers outside it, impossible in a numbering of
    # it, read as its last line's: the lookup stays total for foreign input)
    index = np.full(int(max(raster.numbers.max(), number.max())) + 1, log_width.size - 1)
    index[raster.numbers] = np.arange(log_width.size)
    expected = log_width[index[number[b]]] - log_width[index[number[a]]]
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero area joins nothing
        departure = np.abs(np.log(area[b] / area[a]) - expected)
    ratio = gap / median  # median inf where not judged: ratio 0
    joined = (departure <= brightness) & (
        ~np.isfinite(median) | ((ratio >= gap_low) & (ratio <= gap_high))
    )
    from .check_scans import block_roots  # compiled; the numba import costs ~0.3 s

    lid = np.asarray(line_id, dtype=np.int64)
    n_lines = int(lid.max()) + 1 if lid.size else 0
    return block_roots(
        np.asarray(col, dtype=np.int64), lid, np.asarray(number, dtype=np.int64),
        a[joined].astype(np.int64), b[joined].astype(np.int64), col_gap, max(n_lines, 1),
    )  # fmt: skip


def detached_pieces(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    area: np.ndarray,
    raster: Raster,
    *,
    max_peaks: int = 100,
    col_gap: int = 2,
    gap_low: float = 0.6,
    gap_high: float = 1.6,
    brightness: float = 1.0,
) -> np.ndarray:
    """The numbered peaks of the blocks, other than the frame's largest, too small to stand.

    Parameters
    ----------
    col, row, line_id, number, area, raster
        As :func:`numbered_blocks`.
    max_peaks : int
        Largest block refused (0: none).
    col_gap, gap_low, gap_high, brightness
        As :func:`numbered_blocks`.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    refused = np.zeros(np.asarray(number).size, dtype=bool)
    if max_peaks <= 0:
        return refused
    labels = numbered_blocks(
        col, row, line_id, number, area, raster,
        col_gap=col_gap, gap_low=gap_low, gap_high=gap_high, brightness=brightness,
    )  # fmt: skip
    inside = labels >= 0
    if not np.any(inside):
        return refused
    sizes = np.bincount(labels[inside], minlength=labels.size)
    small = (sizes > 0) & (sizes <= max_peaks)
    small[int(np.argmax(sizes))] = False
    refused[inside] = small[labels[inside]]
    return refused
