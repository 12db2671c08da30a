"""A line's end peak that breaks the line's course where its neighbours end.

Where an arm's edge, a cloth's side edge or the trunk's silhouette behind an arm cuts the
raster, the lines of the one surface end and the next surface shows its own lines at
nearly the same rows: the line search may link the last peak of a skin line to the first
peak of a line one or two numbers off on the other surface, and the number is carried
over. The link is smooth enough to pass the line search (a fraction of a pixel), but it
bends the line: a line on one surface runs with a second difference of its rows of a few
hundredths of a pixel, while the link to another surface's line steps off that course by
more than half a pixel. Where the neighbouring lines end in the same column (no numbered
peak of the numbers either side one column beyond the end), the end lies at a surface's
edge, and a bent end peak there is one of another surface.

On the tuning frames version 23 left 8 wrongly numbered peaks on the twin raster's scenes
7000-7799 and 15 on the clinic rasters' 48000-49199, single peaks on an arm or a cloth at
a line's first or last column among them. The rule (tried as numbering version 24: a bend over
0.8 px and over five times the line's typical second difference, at an end its
neighbours do not pass) refuses 4 and 3 of them, for 0.003 point of the back's coverage
on each set; a least bend of 0.6 px took one more for three times the coverage. On fresh
held-out frames it caught none of the 64 wrong peaks (one arm block of 43 among them), so
it is an option of the stage (``kink_bend``), off (BENCHMARKS.md "Real bodies",
2026-11-30 (34)).
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs, numbered_peaks

__all__ = ["kinked_ends"]


def kinked_ends(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    least_bend: float = 0.8,
    bend_ratio: float = 5.0,
    inner: int = 5,
) -> np.ndarray:
    """The first and last numbered peaks of lines that bend off the line's course at an
    end where the neighbouring numbers' lines do not go on.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    least_bend : float
        Least distance (rows) of the end peak from the straight continuation of the two
        numbered peaks before it; 0 judges none.
    bend_ratio : float
        The bend must also exceed this many times the median absolute second difference
        of the rows of the ``inner`` numbered peaks before the end.
    inner : int
        Numbered peaks before the end that give the line's course; lines of fewer than
        ``inner + 1`` numbered peaks are not judged.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    col, row, lid, number = numbered_peaks(col, row, line_id, number)
    refused = np.zeros(number.size, dtype=bool)
    numbered = np.nonzero((number >= 0) & (lid >= 0))[0]
    if least_bend <= 0 or numbered.size == 0 or inner < 3:
        return refused
    idx, starts, ends = line_runs(lid, numbered)
    long_enough = (ends - starts) >= inner + 1
    # a numbered (column, number) present in the frame: the neighbours' lines going on
    key = col * 1_000_003 + number
    present = np.unique(key[numbered])

    for first, stop in zip(starts[long_enough], ends[long_enough], strict=True):
        seq = idx[first:stop]
        for end_seq, step in ((seq, 1), (seq[::-1], -1)):
            e, p1, p2 = end_seq[-1], end_seq[-2], end_seq[-3]
            run = col[p1] - col[p2]
            if run == 0:
                continue
            predicted = row[p1] + (row[p1] - row[p2]) * (col[e] - col[p1]) / run
            bend = abs(row[e] - predicted)
            if bend <= least_bend:
                continue
            course = row[end_seq[-inner - 1 : -1]]
            typical = float(np.median(np.abs(np.diff(course, 2))))
            if bend <= bend_ratio * typical:
                continue
            beyond = col[e] + step
            n = number[e]
            passed = np.isin([beyond * 1_000_003 + n - 1, beyond * 1_000_003 + n + 1], present)
            if not passed.any():
                refused[e] = True
    return refused
