"""Line ends at the frame's top and bottom edges, where the column shows one side only.

A numbered peak's column confirms its number from both sides: the numbered lines above and
below it lie the right count of spacings away. Where a line leaves the frame through its
top or bottom edge, the peaks of its last columns have no room for a line beyond them, and
the image cannot show whether a line is hidden there: a line running off the trunk onto a
cloth below a waistband, whose surface stands off the skin so that the cloth shows the next
raster line at the same row, continues without a step, and the cloth piece the frame's
edge cuts off is too small to read its own code (on the clinic tuning scenes, 20 of the 25
wrongly numbered peaks lay there, in the last ten rows of the frame). Such ends are
refused: the peaks of a line's end, contiguous from the end, that are the outermost
numbered peak of their column toward the edge and lie within ``reach`` line spacings of
it, where ``company`` unnumbered peaks lie beyond the end, toward the frame's inside and
within ``near`` spacings of it (a surface the end runs onto that was not read). On a whole
back most lines leave the frame with the surface beyond them numbered and keep their ends
(a simulated back's truth lines: 81 peaks refused without that condition, 12 with it); at
a back's lower corners, where the flank's lines are unnumbered, they lose them (0.06 point
of the coverage of backs without heads).
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs

__all__ = ["edge_ends"]


def _outermost(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    n_rows: int,
    spacing: np.ndarray,
    reach: float,
) -> np.ndarray:
    """Numbered peaks that are the first (last) numbered peak of their column and lie
    within ``reach`` spacings of the frame's top (bottom) edge."""
    out = np.zeros(col.size, dtype=bool)
    idx = np.flatnonzero(number >= 0)
    if idx.size == 0:
        return out
    c = col[idx]
    first = np.r_[True, c[1:] != c[:-1]]  # peaks are sorted by (col, row)
    last = np.r_[c[1:] != c[:-1], True]
    near = reach * spacing[idx]
    out[idx[first & (row[idx] < near)]] = True
    out[idx[last & (n_rows - 1 - row[idx] < near)]] = True
    return out


def edge_ends(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray | None,
    n_rows: int,
    *,
    max_run: int = 6,
    reach: float = 1.5,
    company: int = 3,
    near: float = 2.0,
) -> np.ndarray:
    """Numbered peaks at a line's end where the line leaves the frame's top or bottom edge.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``; ``line_id`` -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    spacing : numpy.ndarray or None
        Per-peak local line spacing in rows (:func:`.numbering_checks.local_spacing`); None
        (no pair of consecutive numbered lines) refuses nothing.
    n_rows : int
        The frame's height in pixels.
    max_run : int
        The most peaks refused at one end of a line (0: none): the columns where a line
        exits the frame, not a line running along its edge.
    reach : float
        How near the edge, in local line spacings, the outermost peak of a column lies to
        be unconfirmed on that side.
    company : int
        Unnumbered peaks beyond the end peak (in the columns past it) and toward the
        frame's inside, within ``near`` line spacings of it, that make the end doubtful
        (0: every end at the edge is).
    near : float
        The reach of that neighbourhood, in local line spacings.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    refused = np.zeros(col.size, dtype=bool)
    if spacing is None or max_run <= 0 or col.size == 0:
        return refused
    flag = _outermost(col, row, number, int(n_rows), spacing, reach)
    if not np.any(flag):
        return refused
    lid = np.where(number >= 0, line_id, -1).astype(np.int64)
    # only the lines with a peak at the edge: a few of the frame's hundreds
    idx = np.flatnonzero((lid >= 0) & np.isin(lid, np.unique(lid[flag])))
    order, starts, stops = line_runs(lid, idx)  # numbered peaks, line by line
    f = flag[order]
    for a, b in zip(starts, stops, strict=True):
        if not (f[a] or f[b - 1]):
            continue
        run = f[a:b]
        n = int(np.argmin(run)) if not run.all() else run.size  # flagged run at the start
        m = int(np.argmin(run[::-1])) if not run.all() else run.size  # and at the end
        if n and _unread_beyond(col, row, number, spacing, order[a], -1, n_rows, company, near):
            refused[order[a : a + min(n, max_run)]] = True
        if m and _unread_beyond(col, row, number, spacing, order[b - 1], 1, n_rows, company, near):
            refused[order[b - min(m, max_run) : b]] = True
    return refused


def _unread_beyond(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    end: int,
    side: int,
    n_rows: int,
    company: int,
    near: float,
) -> bool:
    """Whether at least ``company`` unnumbered peaks lie beyond peak ``end`` (in the
    columns past it on ``side``, -1 left, 1 right), within ``near`` line spacings of it: a
    surface the line's end runs onto that was not read."""
    if company <= 0:
        return True
    d = near * float(spacing[end])
    span = [col[end] + 1, col[end] + d + 1] if side > 0 else [col[end] - d, col[end]]
    lo, hi = np.searchsorted(col, span)
    box = slice(int(lo), int(hi))
    # toward the frame's inside only: a line peeking in through the edge beyond the end is
    # a fragment too short to number on any back, not a surface the end runs onto
    inward = row[box] - row[end] if row[end] < n_rows / 2 else row[end] - row[box]
    return int(np.count_nonzero((number[box] < 0) & (inward >= 0) & (inward <= d))) >= company
