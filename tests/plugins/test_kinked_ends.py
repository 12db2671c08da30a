"""A line's end peak that bends off the line's course where its neighbours end: refused."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.kinked_ends import kinked_ends


def _frame(
    lines: list[tuple[int, range, float, float]], bent: dict[tuple[int, int], float] | None = None
) -> tuple[np.ndarray, ...]:
    """Peaks of ``(line, columns, row at column 0, slope)`` lines, numbered 100 + line,
    ``bent`` adding rows to single ``(line, column)`` peaks; sorted by ``(col, row)``.
    Returns col, row, line_id, number."""
    rng = np.random.default_rng(7)
    col, row, lid = [], [], []
    for line, columns, r0, slope in lines:
        for c in columns:
            col.append(c)
            # a line's own course: a slope and a few hundredths of a pixel of noise
            row.append(
                r0 + slope * c + 0.02 * rng.standard_normal() + (bent or {}).get((line, c), 0)
            )
            lid.append(line)
    order = np.lexsort((np.array(row), np.array(col)))
    c, r, li = (np.array(x)[order] for x in (col, row, lid))
    return c.astype(np.int32), r, li.astype(np.int32), (100 + li).astype(np.int32)


def test_a_bent_last_peak_where_the_neighbours_end_is_refused() -> None:
    """Lines 0-2 end at column 39 (an arm's edge); line 1's last peak, at column 40, lies a
    pixel off its course: a peak of the next surface's line linked to it."""
    col, row, lid, num = _frame(
        [(0, range(40), 0.0, 0.3), (1, range(41), 7.0, 0.3), (2, range(40), 14.0, 0.3)],
        bent={(1, 40): 1.0},
    )
    refused = kinked_ends(col, row, lid, num)
    assert np.array_equal(np.nonzero(refused)[0], np.nonzero((lid == 1) & (col == 40))[0])


def test_the_first_peak_is_judged_as_the_last() -> None:
    col, row, lid, num = _frame(
        [
            (0, range(10, 50), 0.0, -0.2),
            (1, range(9, 50), 7.0, -0.2),
            (2, range(10, 50), 14.0, -0.2),
        ],
        bent={(1, 9): -0.9},
    )
    refused = kinked_ends(col, row, lid, num)
    assert np.array_equal(np.nonzero(refused)[0], np.nonzero((lid == 1) & (col == 9))[0])


def test_kept_where_a_neighbour_goes_on_or_the_bend_is_small_or_the_line_short() -> None:
    # the line above goes on beyond the end: the end is no surface's edge
    col, row, lid, num = _frame(
        [(0, range(45), 0.0, 0.3), (1, range(41), 7.0, 0.3), (2, range(40), 14.0, 0.3)],
        bent={(1, 40): 1.0},
    )
    assert not kinked_ends(col, row, lid, num).any()
    # a bend within the least one
    col, row, lid, num = _frame(
        [(0, range(40), 0.0, 0.3), (1, range(41), 7.0, 0.3), (2, range(40), 14.0, 0.3)],
        bent={(1, 40): 0.4},
    )
    assert not kinked_ends(col, row, lid, num).any()
    # five numbered peaks give no course to judge against
    col, row, lid, num = _frame(
        [(0, range(36, 40), 0.0, 0.3), (1, range(36, 41), 7.0, 0.3), (2, range(36, 40), 14.0, 0.3)],
        bent={(1, 40): 1.0},
    )
    assert not kinked_ends(col, row, lid, num).any()


def test_a_line_that_bends_all_along_keeps_its_end() -> None:
    """A wavy line (folds, hair) bends by as much as its end: the ratio keeps it."""
    col, row, lid, num = _frame([(0, range(40), 0.0, 0.3), (1, range(41), 7.0, 0.3)])
    wavy = lid == 1
    row = row.copy()
    row[wavy] += 0.5 * (-1.0) ** col[wavy]
    row[wavy & (col == 40)] += 1.0
    assert not kinked_ends(col, row, lid, num).any()


def test_degenerate_inputs() -> None:
    empty = np.zeros(0, dtype=np.int32)
    assert kinked_ends(empty, empty.astype(float), empty, empty).shape == (0,)
    col, row, lid, num = _frame([(0, range(40), 0.0, 0.3)], bent={(0, 39): 2.0})
    assert not kinked_ends(col, row, lid, -np.ones_like(num)).any()  # nothing numbered
    assert not kinked_ends(col, row, lid, num, least_bend=0).any()  # the check off
    assert kinked_ends(col, row, lid, num).sum() == 1  # a lone line: no neighbour goes on
