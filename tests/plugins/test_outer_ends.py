"""A line's end peaks, the outermost of their column, farther from the next line than the
line is further in: refused."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.outer_ends import outer_ends


def _frame(
    lines: list[tuple[int, range, float]], moved: dict[tuple[int, int], float] | None = None
) -> tuple[np.ndarray, ...]:
    """Peaks of ``(line, columns, row)`` lines 6 rows apart, numbered 100 + line, ``moved``
    adding rows to single ``(line, column)`` peaks; sorted by ``(col, row)``.
    Returns col, row, line_id, number."""
    rng = np.random.default_rng(11)
    col, row, lid = [], [], []
    for line, columns, r0 in lines:
        for c in columns:
            col.append(c)
            row.append(r0 + 0.05 * rng.standard_normal() + (moved or {}).get((line, c), 0.0))
            lid.append(line)
    order = np.lexsort((np.array(row), np.array(col)))
    c, r, li = (np.array(x)[order] for x in (col, row, lid))
    return c.astype(np.int32), r, li.astype(np.int32), (100 + li).astype(np.int32)


def _peaks(col: np.ndarray, lid: np.ndarray, line: int, columns: list[int]) -> np.ndarray:
    return np.nonzero((lid == line) & np.isin(col, columns))[0]


def test_the_top_lines_first_peaks_on_a_raised_surface_are_refused() -> None:
    """Line 0 is its columns' top line; over its first two columns it lies 2.5 rows higher
    (an arm a line's depth in front of the trunk, the trunk's line hidden): its gap to
    line 1 grows from 6 to 8.5 rows there."""
    col, row, lid, num = _frame(
        [(0, range(10, 40), 100.0), (1, range(10, 40), 106.0), (2, range(10, 40), 112.0)],
        moved={(0, 10): -2.5, (0, 11): -2.5},
    )
    refused = outer_ends(col, row, lid, num)
    assert np.array_equal(np.nonzero(refused)[0], _peaks(col, lid, 0, [10, 11]))


def test_the_bottom_line_is_judged_as_the_top_one() -> None:
    col, row, lid, num = _frame(
        [(0, range(10, 40), 100.0), (1, range(10, 40), 106.0), (2, range(10, 40), 112.0)],
        moved={(2, 39): 2.0},
    )
    refused = outer_ends(col, row, lid, num)
    assert np.array_equal(np.nonzero(refused)[0], _peaks(col, lid, 2, [39]))


def test_kept_where_the_gap_holds_a_peak_beyond_or_the_rule_is_off() -> None:
    lines = [(0, range(10, 40), 100.0), (1, range(10, 40), 106.0), (2, range(10, 40), 112.0)]
    # the gap grows by less than the ratio
    col, row, lid, num = _frame(lines, moved={(0, 10): -1.0})
    assert not outer_ends(col, row, lid, num).any()
    # a peak above the end (a line of the surface beyond): the column confirms both sides
    col, row, lid, num = _frame(
        [*lines, (3, range(10, 12), 92.0)], moved={(0, 10): -2.5, (0, 11): -2.5}
    )
    assert not outer_ends(col, row, lid, num)[lid != 3].any()
    col, row, lid, num = _frame(lines, moved={(0, 10): -2.5})
    assert not outer_ends(col, row, lid, num, gap_ratio=0.0).any()


def test_judged_from_the_outermost_in_and_short_lines_not_at_all() -> None:
    # the outermost peak keeps its gap: the end is not judged further in
    col, row, lid, num = _frame(
        [(0, range(10, 40), 100.0), (1, range(10, 40), 106.0)], moved={(0, 11): -2.5}
    )
    assert not outer_ends(col, row, lid, num).any()
    # fewer than depth + inner numbered peaks
    col, row, lid, num = _frame(
        [(0, range(10, 16), 100.0), (1, range(10, 16), 106.0)], moved={(0, 10): -2.5}
    )
    assert not outer_ends(col, row, lid, num).any()
    # unnumbered peaks are not judged, and nothing breaks on an empty frame
    col, row, lid, num = _frame(
        [(0, range(10, 40), 100.0), (1, range(10, 40), 106.0)], moved={(0, 10): -2.5}
    )
    assert not outer_ends(col, row, lid, np.full_like(num, -1)).any()
    empty = np.zeros(0, dtype=np.int32)
    assert outer_ends(empty, empty.astype(float), empty, empty).shape == (0,)
