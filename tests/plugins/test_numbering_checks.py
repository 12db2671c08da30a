"""Geometric evidence between components: line ends and their slopes, contact votes."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.numbering_checks import _line_ends, contact_votes, pair_contradictions


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
    c0, c1, r0, r1, s0, s1, count = _line_ends(col, row, lid, len(lengths), fit=8)
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
    c0, c1, r0, r1, s0, s1, count = _line_ends(col, row, lid, 2, fit=8)
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


def test_a_peak_taken_from_the_neighbouring_line_is_refused() -> None:
    from rasterserver_plugins.numbering_checks import line_jumps, local_spacing

    cols = np.repeat(np.arange(40), 3)
    rows = np.tile([10.0, 20.0, 30.0], 40) + 0.02 * cols
    lid = np.tile([0, 1, 2], 40)
    number = np.tile([5, 6, 7], 40).astype(np.int32)
    col, row, lid = _sorted(cols, rows, lid)
    assert not np.any(line_jumps(col, row, lid, number))
    # line 1 takes line 2's peak in column 20 (its own is missing there)
    drop = (col == 20) & (lid == 1)
    col, row, lid, number = col[~drop], row[~drop], lid[~drop], number[~drop]
    took = (col == 20) & (lid == 2)
    lid = np.where(took, 1, lid)
    number = np.where(took, 6, number).astype(np.int32)
    refused = line_jumps(col, row, lid, number)
    assert refused[took].all()
    assert np.count_nonzero(refused) <= 5  # the taken peak and two line neighbours each side
    spacing = local_spacing(col, row, number)
    assert spacing is not None and abs(float(np.median(spacing)) - 10.0) < 0.5


def test_line_checks_of_degenerate_inputs() -> None:
    from rasterserver_plugins.numbering_checks import line_jumps, local_spacing

    empty_i = np.zeros(0, np.int64)
    assert line_jumps(empty_i, empty_i * 1.0, empty_i, empty_i).size == 0
    assert local_spacing(empty_i, empty_i * 1.0, empty_i) is None
    # nothing numbered: no spacing, nothing refused
    col = np.array([0, 0, 1, 1])
    row = np.array([1.0, 11.0, 1.0, 11.0])
    none = np.full(4, -1, np.int32)
    assert local_spacing(col, row, none) is None
    assert not np.any(line_jumps(col, row, np.array([0, 1, 0, 1]), none))


def test_numbered_peaks_with_no_numbered_column_neighbour_are_refused() -> None:
    from rasterserver_plugins.numbering_checks import isolated_peaks

    # three columns of three peaks: in column 1 the middle peak's neighbours are not
    # numbered; in column 2 only the top peak is numbered at all
    col = np.repeat(np.arange(3), 3)
    number = np.array([5, 6, 7, -1, 6, -1, 5, -1, -1], np.int32)
    refused = isolated_peaks(col, number)
    assert refused.tolist() == [False] * 4 + [True, False, True, False, False]
    # a peak alone in its column has nothing to confirm it either
    assert isolated_peaks(np.array([0]), np.array([3], np.int32)).tolist() == [True]
    assert isolated_peaks(np.zeros(0, np.int64), np.zeros(0, np.int32)).size == 0


def test_column_order_against_the_gaps_beside_it() -> None:
    """A line's end that took the neighbouring line's peak where lines crowd: numbers two
    apart at one gap of its own column (the cell's mean spacing is wider) are refused."""
    from rasterserver_plugins.line_numbering import _column_order_conflicts

    col = np.zeros(5, np.int64)
    row = np.array([100.0, 108.0, 117.0, 123.0, 129.0])  # gaps 8, 9, 6, 6
    number = np.array([10, 11, 12, 14, 15], np.int32)  # 12 is really 13
    wide = np.full(5, 9.0)  # the cell's spacing: 6 px is 0.67 of it, not one spacing
    clash = _column_order_conflicts(col, row, number, spacing=wide)
    assert clash.tolist() == [False, False, True, True, False]
    # a line missing in between (two gaps wide) is not refused
    row_ok = np.array([100.0, 108.0, 116.0, 128.0, 134.0])
    assert not np.any(_column_order_conflicts(col, row_ok, number, spacing=wide))


def test_peaks_directly_beside_a_doubtful_peak_are_refused() -> None:
    """A numbered line directly above a refused block (one spacing between them: the
    image does not show where the hidden line went) is refused; across a gap of 1.5
    spacings (the hidden line shows) it stays, and so does a peak two spacings away."""
    from rasterserver_plugins.numbering_checks import beside_doubtful

    # column 0: 10, 11 numbered, 12 doubtful one spacing below; column 1: the same with a
    # gap of 1.5 spacings; column 2: the doubtful peak in the middle
    col = np.repeat(np.arange(3), 3)
    row = np.array([100.0, 108.0, 116.0, 100.0, 108.0, 120.0, 100.0, 108.0, 116.0])
    number = np.array([10, 11, -1, 10, 11, -1, 10, -1, 12], np.int32)
    doubtful = np.array([0, 0, 1, 0, 0, 1, 0, 1, 0], bool)
    spacing = np.full(9, 8.0)
    refused = beside_doubtful(col, row, number, doubtful, spacing)
    assert refused.tolist() == [False, True, False, False, False, False, True, False, True]
    # a wider tolerance takes the 1.5-spacing gap as "beside" too
    wide = beside_doubtful(col, row, number, doubtful, spacing, max_gap=1.6)
    assert wide[4] and not wide[3]
    # nothing doubtful, nothing refused; degenerate sizes
    assert not np.any(beside_doubtful(col, row, number, np.zeros(9, bool), spacing))
    one = np.zeros(1)
    assert beside_doubtful(one, one, np.array([3]), np.ones(1, bool), one + 8).tolist() == [False]


def test_short_runs_cut_off_by_refused_peaks_are_refused() -> None:
    """A line's end of three numbered peaks beyond refused ones goes; a run of six stays,
    and so does a short line that nothing was refused from."""
    from rasterserver_plugins.numbering_checks import stranded_runs

    # line 0: 3 numbered, 2 refused, 10 numbered; line 1: 4 numbered (whole, short);
    # line 2: 6 numbered, 1 refused, 2 numbered; peaks of no line (-1) interleaved
    line = np.r_[np.zeros(15), np.ones(4), np.full(9, 2), np.full(2, -1)].astype(np.int32)
    number = np.r_[[7] * 3, [-1] * 2, [7] * 10, [8] * 4, [9] * 6, -1, [9] * 2, -1, -1]
    number = number.astype(np.int32)
    perm = np.random.default_rng(5).permutation(line.size)
    col = np.r_[np.arange(15), np.arange(4), np.arange(9), [3, 4]][perm]
    order = np.lexsort((line[perm], col))  # peaks sorted by column as the stage has them
    line, number = line[perm][order], number[perm][order]
    refused = stranded_runs(line, number, 6)
    assert np.count_nonzero(refused) == 5
    assert np.all(line[refused] != 1)
    assert set(np.flatnonzero(refused & (line == 2))) == set(
        np.flatnonzero((line == 2) & (number >= 0))[-2:]
    )
    assert not np.any(stranded_runs(line, number, 0))
    # shorter runs only: line 0's three stay, line 2's two go
    assert np.count_nonzero(stranded_runs(line, number, 3)) == 2
    assert not np.any(stranded_runs(line, number, 2))
    empty = np.zeros(0, np.int32)
    assert stranded_runs(empty, empty, 6).size == 0
    assert not np.any(stranded_runs(np.full(3, -1, np.int32), np.full(3, 5, np.int32), 6))
