"""Peaks of straight line pieces, for the tests of the line-end checks."""

from __future__ import annotations

import numpy as np


def line_pieces(pieces: list[tuple[int, range, float, float, int]]) -> tuple[np.ndarray, ...]:
    """Peaks of ``(line, columns, row at column 0, slope, number)`` pieces (number -1:
    unnumbered; one line may be given as several pieces), rows with 0.02 px of noise from a
    fixed seed, sorted by ``(col, row)``.

    Returns
    -------
    col, row, line_id, number : numpy.ndarray
    """
    rng = np.random.default_rng(5)
    col, row, lid, num = [], [], [], []
    for line, columns, r0, slope, number in pieces:
        for c in columns:
            col.append(c)
            row.append(r0 + slope * c + 0.02 * rng.standard_normal())
            lid.append(line)
            num.append(number)
    order = np.lexsort((np.array(row), np.array(col)))
    c, r, li, n = (np.array(x)[order] for x in (col, row, lid, num))
    return c.astype(np.int32), r, li.astype(np.int32), n.astype(np.int32)
