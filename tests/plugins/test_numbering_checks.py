"""Geometric evidence between components: line ends and their slopes, contact votes; the
column order every numbering must keep."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.contact_tallies import line_ends
from rasterserver_plugins.numbering_checks import (
    contact_votes,
    pair_contradictions,
    unordered_pairs,
)


def _sorted(col: np.ndarray, row: np.ndarray, line_id: np.ndarray) -> tuple[np.ndarray, ...]:
    order = np.lexsort((row, col))
    return col[order], row[order], line_id[order]


def test_line_ends_and_slopes_match_a_least_squares_fit() -> None:
    rng = np.random.default_rng(3)
    cols, rows, ids = [], [], []
    lengths = [2, 3, 5, 8, 40]  # shorter than 3: no slope; shorter than the window: all
    for k, n in enumerate(lengths):
        c = np.arange(10 + 3 * k, 10 + 3 * k + n)
        r = 50.0 * k + 0.3 * (c - c[0]) + 0.01 * (c - c[0]) ** 2 + rng.normal(0, 0.1, n)
        cols.append(c)
        rows.append(r)
        ids.append(np.full(n, k))
    col, row, lid = _sorted(np.concatenate(cols), np.concatenate(rows), np.concatenate(ids))
    c0, c1, r0, r1, s0, s1, count = line_ends(col, row, lid, len(lengths), fit=8)
    for k, n in enumerate(lengths):
        c, r = cols[k], rows[k]
        assert count[k] == n and c0[k] == c[0] and c1[k] == c[-1]
        assert r0[k] == r[0] and r1[k] == r[-1]
        m = min(8, n)
        if m < 3:
            assert s0[k] == 0.0 and s1[k] == 0.0
            continue
        assert np.isclose(s0[k], np.polyfit(c[:m], r[:m], 1)[0], rtol=1e-9, atol=1e-12)
        assert np.isclose(s1[k], np.polyfit(c[-m:], r[-m:], 1)[0], rtol=1e-9, atol=1e-12)


def test_line_ends_of_a_line_without_peaks_are_empty() -> None:
    col = np.arange(5)
    row = np.full(5, 10.0)
    lid = np.zeros(5, dtype=np.int64)
    c0, c1, r0, r1, s0, s1, count = line_ends(col, row, lid, 2, fit=8)
    assert np.isnan(r1[1])
    assert count.tolist() == [5, 0] and c0[1] == -1 and c1[1] == -1 and np.isnan(r0[1])
    assert s0[0] == 0.0 and s1[0] == 0.0  # a flat line


def test_continuation_across_a_gap_votes_for_the_same_number() -> None:
    # two raster lines 10 px apart, interrupted for 10 columns: components 0 (left) and 1
    # (right), two levels each; the lines continue, so the offsets must be equal
    cols, rows, ids = [], [], []
    for k, (start, stop) in enumerate(((0, 30), (0, 30), (40, 70), (40, 70))):
        c = np.arange(start, stop)
        cols.append(c)
        rows.append(100.0 + 10.0 * (k % 2) + 0.2 * c)
        ids.append(np.full(c.size, k))
    col, row, lid = _sorted(np.concatenate(cols), np.concatenate(rows), np.concatenate(ids))
    order = np.array([0, 1, 0, 1], np.int32)
    comp = np.array([0, 0, 1, 1], np.int32)
    votes = contact_votes(col, row, lid, order, comp, min_line=5)
    assert set(votes[(0, 1)]) == {0} and votes[(0, 1)][0] > 0
    assert set(votes[(1, 0)]) == {0}
    # the right part one level lower (a line missing): the vote says so
    shifted = contact_votes(col, row, lid, np.array([0, 1, 1, 2], np.int32), comp, min_line=5)
    assert set(shifted[(0, 1)]) == {-1}


def _coded_lines(kind_of_piece: int | None, noise: float = 0.03) -> tuple[np.ndarray, ...]:
    """20 lines of the w8-1to2 raster over 30 columns, areas by their kinds; with a piece
    (columns 20-29 of line 10, a line of its own) of the given kind when not None."""
    from rasterserver.raster import get_raster

    raster = get_raster("w8-1to2")
    rng = np.random.default_rng(5)
    cols, rows, lids, areas = [], [], [], []
    for i in range(20):
        for c in range(30):
            piece = kind_of_piece is not None and i == 10 and c >= 20
            kind = kind_of_piece if piece else raster.code[i]
            cols.append(c)
            rows.append(10.0 * i)
            lids.append(20 if piece else i)
            areas.append((200.0 if kind else 100.0) * (1.0 + noise * rng.standard_normal()))
    col, _row, lid = _sorted(np.array(cols), np.array(rows), np.array(lids))
    area = np.array(areas)[np.lexsort((np.array(rows), np.array(cols)))]
    line_number = np.append(raster.numbers[:20], raster.numbers[10]).astype(np.int32)
    return col, area, lid, line_number, raster


def test_a_piece_of_the_wrong_kind_contradicts_its_neighbours() -> None:
    col, area, lid, line_number, raster = _coded_lines(1 - 1)  # line 10 is heavy: a light piece
    assert raster.code[10] == 1
    upper, lower, columns = pair_contradictions(col, area, lid, line_number, raster, np.log(2.0))
    assert 20 in set(upper.tolist()) | set(lower.tolist())
    assert np.all(columns == 10)
    # the long lines around it agree with one another
    assert all(20 in (u, v) for u, v in zip(upper.tolist(), lower.tolist(), strict=True))


def test_lines_of_the_right_kinds_contradict_nothing() -> None:
    col, area, lid, line_number, raster = _coded_lines(None, noise=0.1)
    upper, _, _ = pair_contradictions(col, area, lid, line_number, raster, np.log(2.0))
    assert upper.size == 0
    # degenerate inputs: no peaks, nothing numbered
    empty = np.zeros(0, np.int64)
    assert pair_contradictions(empty, empty * 1.0, empty, line_number, raster, 0.7)[0].size == 0
    none = np.full(line_number.shape, -1, np.int32)
    assert pair_contradictions(col, area, lid, none, raster, 0.7)[0].size == 0


def test_column_order_against_the_gaps_beside_it() -> None:
    """A line's end that took the neighbouring line's peak where lines crowd: numbers two
    apart at one gap of its own column (the cell's mean spacing is wider) are refused."""
    from rasterserver_plugins.numbering_checks import column_order_conflicts

    col = np.zeros(5, np.int64)
    row = np.array([100.0, 108.0, 117.0, 123.0, 129.0])  # gaps 8, 9, 6, 6
    number = np.array([10, 11, 12, 14, 15], np.int32)  # 12 is really 13
    wide = np.full(5, 9.0)  # the cell's spacing: 6 px is 0.67 of it, not one spacing
    clash = column_order_conflicts(col, row, number, spacing=wide)
    assert clash.tolist() == [False, False, True, True, False]
    # a line missing in between (two gaps wide) is not refused
    row_ok = np.array([100.0, 108.0, 116.0, 128.0, 134.0])
    assert not np.any(column_order_conflicts(col, row_ok, number, spacing=wide))


def test_line_runs_orders_the_taken_peaks_line_by_line() -> None:
    from rasterserver_plugins.numbering_checks import line_runs

    lid = np.array([3, 1, 3, 1, 7, 3], dtype=np.int64)  # peaks in column order
    order, starts, stops = line_runs(lid, np.array([0, 1, 2, 3, 5]))
    assert order.tolist() == [1, 3, 0, 2, 5]
    assert starts.tolist() == [0, 2] and stops.tolist() == [2, 5]
    empty = line_runs(lid, np.zeros(0, dtype=np.int64))
    assert [a.size for a in empty] == [0, 0, 0]


def test_unordered_pairs_refuses_numbers_that_do_not_increase_down_a_column() -> None:
    # one column, lines 8 px apart: 10, 11, 11 (equal, two spacings on: no gap tells) and
    # a second column 20, 19 (decreasing); a third column in order is left alone
    col = np.array([0, 0, 0, 1, 1, 2, 2, 2])
    row = np.array([100.0, 108.0, 124.0, 100.0, 108.0, 100.0, 108.0, 116.0])
    number = np.array([10, 11, 11, 20, 19, 5, 6, 7])
    got = unordered_pairs(col, row, number)
    assert got.tolist() == [False, True, True, True, True, False, False, False]


def test_unordered_pairs_judges_again_the_neighbours_a_refusal_leaves() -> None:
    # 100, 105, 98, 99 down one column: (105, 98) refused leaves 100 above 99, refused too;
    # unnumbered peaks between do not break a pair
    col = np.zeros(5, dtype=np.int64)
    row = np.array([100.0, 108.0, 112.0, 116.0, 124.0])
    number = np.array([100, 105, -1, 98, 99])
    assert unordered_pairs(col, row, number).tolist() == [True, True, False, True, True]


def test_unordered_pairs_degenerate_inputs() -> None:
    empty = np.zeros(0, dtype=np.int64)
    assert unordered_pairs(empty, empty.astype(float), empty).size == 0
    one = np.array([3])
    assert unordered_pairs(one, np.array([1.0]), one).tolist() == [False]
    # nothing numbered
    col = np.array([0, 0])
    assert not unordered_pairs(col, np.array([1.0, 9.0]), np.array([-1, -1])).any()
