"""Line ends leaving the frame's top or bottom edge: refused where the column shows one side."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.frame_edges import edge_ends

ROWS = 100
SPACING = 8.0


def _frame(lines: list[tuple[int, int, int, float, float]]) -> tuple[np.ndarray, ...]:
    """Peaks of straight lines ``(line_id, first_col, last_col, row_at_first, slope)``,
    numbered by their id, sorted by ``(col, row)``."""
    col, row, lid = [], [], []
    for line, c0, c1, r0, slope in lines:
        cols = np.arange(c0, c1 + 1)
        col.append(cols)
        row.append(r0 + slope * (cols - c0))
        lid.append(np.full(cols.size, line))
    c, r, l_ = np.concatenate(col), np.concatenate(row), np.concatenate(lid)
    keep = (r >= 0) & (r <= ROWS - 1)
    c, r, l_ = c[keep], r[keep], l_[keep]
    order = np.lexsort((r, c))
    return c[order], r[order], l_[order].astype(np.int32), l_[order].astype(np.int32)


def _refused(col, row, lid, number, **kw) -> np.ndarray:
    kw.setdefault("company", 0)  # the geometry alone, whatever lies beside the end
    return edge_ends(col, row, lid, number, np.full(col.size, SPACING), ROWS, **kw)


def test_a_line_leaving_the_bottom_edge_loses_its_last_columns_only() -> None:
    # line 5 runs down into the bottom edge; line 4 above it stays in the frame
    col, row, lid, number = _frame([(4, 0, 60, 60.0, 0.5), (5, 0, 60, 68.0, 0.5)])
    refused = _refused(col, row, lid, number, max_run=6, reach=1.5)
    on5 = lid == 5
    # the last peaks of line 5 lie within 12 px of row 99 and nothing is numbered below
    assert refused[on5].sum() == 6
    assert np.all(col[refused] >= col[on5].max() - 5)
    assert not np.any(refused[lid == 4])  # line 5 lies below it in every column


def test_a_line_ending_far_from_the_edge_is_kept() -> None:
    col, row, lid, number = _frame([(4, 0, 40, 30.0, 0.0), (5, 0, 40, 38.0, 0.1)])
    assert not np.any(_refused(col, row, lid, number))


def test_the_top_edge_is_judged_as_the_bottom_one() -> None:
    # line 2 rises out of the frame through its top edge at its right end
    col, row, lid, number = _frame([(2, 0, 40, 30.0, -0.5), (3, 0, 40, 38.0, -0.5)])
    refused = _refused(col, row, lid, number, max_run=4, reach=1.5)
    assert refused.sum() == 4 and np.all(lid[refused] == 2)
    assert np.all(col[refused] >= col[lid == 2].max() - 3)


def test_a_line_along_the_edge_loses_at_most_max_run_peaks_at_each_end() -> None:
    col, row, lid, number = _frame([(6, 0, 80, 94.0, 0.0), (5, 0, 80, 86.0, 0.0)])
    refused = _refused(col, row, lid, number, max_run=3, reach=1.0)
    assert refused.sum() == 6
    assert set(col[refused].tolist()) == {0, 1, 2, 78, 79, 80}


def test_unnumbered_peaks_below_do_not_confirm_a_line_end() -> None:
    col, row, lid, number = _frame([(4, 0, 30, 60.0, 1.0), (9, 0, 30, 70.0, 1.0)])
    number = np.where(lid == 9, -1, number).astype(np.int32)
    refused = _refused(col, row, lid, number, max_run=6, reach=1.5)
    assert refused.any() and np.all(lid[refused] == 4)


def test_degenerate_inputs_refuse_nothing() -> None:
    col, row, lid, number = _frame([(6, 0, 20, 95.0, 0.0)])
    assert not np.any(_refused(col, row, lid, number, max_run=0))
    assert not np.any(edge_ends(col, row, lid, number, None, ROWS))
    empty = np.zeros(0)
    none = edge_ends(
        empty.astype(np.int32), empty, empty.astype(np.int32), empty.astype(np.int32), empty, 10
    )
    assert none.shape == (0,)
    unnumbered = np.full(col.size, -1, np.int32)
    assert not np.any(_refused(col, row, lid, unnumbered))


def test_an_end_is_refused_only_beside_a_surface_that_was_not_read() -> None:
    """On a whole back the lines leave the frame with every surface beside them numbered;
    a cloth sliver the frame's edge cuts off shows unnumbered pieces beside the end."""
    col, row, lid, number = _frame([(4, 0, 60, 60.0, 0.5), (5, 0, 60, 68.0, 0.5)])
    assert not np.any(_refused(col, row, lid, number, company=3))
    # three unnumbered peaks of a cloth piece just beyond line 5's end, a spacing up
    end = np.flatnonzero(lid == 5)[-1]
    c = np.r_[col, [col[end] + 1, col[end] + 2, col[end] + 3]]
    r = np.r_[row, row[end] - SPACING + np.array([0.5, 1.0, 1.5])]
    piece = np.r_[lid, [9, 9, 9]].astype(np.int32)
    n = np.r_[number, [-1, -1, -1]].astype(np.int32)
    order = np.lexsort((r, c))
    c, r, piece, n = c[order], r[order], piece[order], n[order]
    refused = _refused(c, r, piece, n, company=3, max_run=6, reach=1.5)
    assert refused.sum() == 6 and np.all(piece[refused] == 5)
    assert not np.any(_refused(c, r, piece, n, company=4, max_run=6, reach=1.5))
