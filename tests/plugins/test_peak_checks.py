"""Peak-by-peak checks: line jumps, isolated peaks, peaks beside doubtful ones, stranded
runs."""

from __future__ import annotations

import numpy as np


def _sorted(col: np.ndarray, row: np.ndarray, line_id: np.ndarray) -> tuple[np.ndarray, ...]:
    order = np.lexsort((row, col))
    return col[order], row[order], line_id[order]


def test_a_peak_taken_from_the_neighbouring_line_is_refused() -> None:
    from rasterserver_plugins.numbering_checks import local_spacing
    from rasterserver_plugins.peak_checks import line_jumps

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
    from rasterserver_plugins.numbering_checks import local_spacing
    from rasterserver_plugins.peak_checks import line_jumps

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
    from rasterserver_plugins.peak_checks import isolated_peaks

    # three columns of three peaks: in column 1 the middle peak's neighbours are not
    # numbered; in column 2 only the top peak is numbered at all
    col = np.repeat(np.arange(3), 3)
    number = np.array([5, 6, 7, -1, 6, -1, 5, -1, -1], np.int32)
    refused = isolated_peaks(col, number)
    assert refused.tolist() == [False] * 4 + [True, False, True, False, False]
    # a peak alone in its column has nothing to confirm it either
    assert isolated_peaks(np.array([0]), np.array([3], np.int32)).tolist() == [True]
    assert isolated_peaks(np.zeros(0, np.int64), np.zeros(0, np.int32)).size == 0


def test_peaks_directly_beside_a_doubtful_peak_are_refused() -> None:
    """A numbered line directly above a refused block (one spacing between them: the
    image does not show where the hidden line went) is refused; across a gap of 1.5
    spacings (the hidden line shows) it stays, and so does a peak two spacings away."""
    from rasterserver_plugins.peak_checks import beside_doubtful

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


def test_with_a_share_peaks_beside_a_lone_doubtful_line_stay() -> None:
    """With a share, the lines beside one doubtful line amid numbered ones stay (their
    neighbours confirm them); beside a block of doubtful lines they are refused."""
    from rasterserver_plugins.peak_checks import beside_doubtful, doubtful_share

    spacing = 8.0
    col, row = np.meshgrid(np.arange(60), 100.0 + spacing * np.arange(10), indexing="ij")
    col, row = col.ravel(), row.ravel()  # sorted by (col, row)
    line = np.tile(np.arange(10), 60)
    # columns 0-29: line 5 alone is doubtful; columns 30-59: lines 5-9 (a block); the
    # square counted spans two spacings (16 columns) either side
    doubtful = (line == 5) | ((col >= 30) & (line > 5))
    number = np.where(doubtful, -1, 10 + line).astype(np.int32)
    spacings = np.full(col.size, spacing)
    every = beside_doubtful(col, row, number, doubtful, spacings)
    shared = beside_doubtful(col, row, number, doubtful, spacings, min_share=0.5)
    lone = np.isin(line, (4, 6)) & (col < 14)
    block = (line == 4) & (col >= 46)
    assert np.all(every[lone]) and not np.any(shared[lone])
    assert np.all(every[block]) and np.all(shared[block])
    assert not np.any(shared & ~every)
    at = np.flatnonzero(lone)[:1]
    n_doubtful, n_numbered = doubtful_share(col, row, at, doubtful, number >= 0, spacings, 2.0)
    assert (n_doubtful[0], n_numbered[0]) == (17, 68)  # 17 columns of 1 doubtful, 4 numbered
    none = beside_doubtful(col[:0], row[:0], number[:0], doubtful[:0], spacings[:0], min_share=0.5)
    assert none.size == 0


def test_short_runs_standing_alone_in_their_column_are_refused() -> None:
    """Two numbered lines four spacings below the rest of their column go (numbered across
    a gap hiding an unknown count of lines); a run of three, a run with a near neighbour
    and a pair broken by a skipped number (two runs of one) are judged by their kind."""
    from rasterserver_plugins.peak_checks import column_islands

    s = 8.0
    # column 0: lines 10-14, then 19, 20 four spacings on (an island of two)
    # column 1: lines 10-14, then 19, 20, 21 (a run of three stays)
    # column 2: lines 10-14, then 16, 17 two spacings on (under 2.5: stays)
    # column 3: 30 alone, far from 40 (runs of one each: both go)
    rows = {
        0: [100 + s * k for k in range(5)] + [100 + s * 9, 100 + s * 10],
        1: [100 + s * k for k in range(5)] + [100 + s * 9, 100 + s * 10, 100 + s * 11],
        2: [100 + s * k for k in range(5)] + [100 + s * 6, 100 + s * 7],
        3: [100.0, 100 + s * 5],
    }
    numbers = {
        0: [10, 11, 12, 13, 14, 19, 20],
        1: [10, 11, 12, 13, 14, 19, 20, 21],
        2: [10, 11, 12, 13, 14, 16, 17],
        3: [30, 40],
    }
    col = np.concatenate([np.full(len(rows[c]), c) for c in rows])
    row = np.concatenate([rows[c] for c in rows])
    number = np.concatenate([numbers[c] for c in numbers]).astype(np.int32)
    spacing = np.full(col.size, s)
    refused = column_islands(col, row, number, spacing)
    assert sorted(zip(col[refused].tolist(), number[refused].tolist(), strict=True)) == [
        (0, 19),
        (0, 20),
        (3, 30),
        (3, 40),
    ]
    # unnumbered peaks neither count nor get refused; a larger least run takes column 1 too
    number[0] = -1
    assert not column_islands(col, row, number, spacing)[0]
    assert column_islands(col, row, number, spacing, min_peaks=4)[col == 1].sum() == 3
    assert not np.any(column_islands(col, row, number, spacing, min_peaks=1))
    empty = np.zeros(0)
    assert column_islands(empty, empty, empty.astype(np.int32), empty).size == 0


def test_short_runs_cut_off_by_refused_peaks_are_refused() -> None:
    """A line's end of three numbered peaks beyond refused ones goes; a run of six stays,
    and so does a short line that nothing was refused from."""
    from rasterserver_plugins.peak_checks import stranded_runs

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


def _ends_reference(line, number, height, min_refused, margin, dim_ratio, jump=0.0, inner=6):  # type: ignore[no-untyped-def]
    """Line by line in plain Python: what :func:`line_ends` must flag."""
    out = np.zeros(line.size, dtype=bool)
    for k in set(line[line >= 0].tolist()):
        peaks = np.flatnonzero(line == k)  # column order: the peaks are sorted by column
        kept = peaks[number[peaks] >= 0]
        if kept.size == 0:
            continue
        for ends, beyond in (
            (kept, np.flatnonzero(peaks == kept[0])[0]),
            (kept[::-1], peaks.size - 1 - np.flatnonzero(peaks == kept[-1])[0]),
        ):
            if margin > 0 and beyond >= min_refused:
                out[ends[:margin]] = True
            inner_mean = height[ends[1 : inner + 1]].mean() if kept.size > inner else 0.0
            if dim_ratio > 0 and height[ends[0]] < dim_ratio * inner_mean:
                out[ends[0]] = True
            near = height[ends[1:3]].mean() if kept.size >= 3 else 0.0
            step = max(height[ends[0]] / near, near / height[ends[0]]) if near > 0 else 0.0
            if jump > 0 and step > jump:
                out[ends[0]] = True
    return out


def test_line_ends_beyond_refused_peaks_and_dim_end_peaks_are_refused() -> None:
    """Beyond six refused peaks, a line's first three numbered peaks go (the change of
    surface the refusals mark is placed to a few columns only); a line's last peak at a
    fifth of its line's height goes (a peak of the next surface, past an arm's edge); a
    line refused over fewer peaks, or dimming gradually, keeps its ends."""
    from rasterserver_plugins.peak_checks import line_ends

    # line 0: 6 refused + 20 numbered; line 1: 5 refused + 20 numbered; line 2: 20
    # numbered, the last at a fifth of the height; line 3: 20 numbered dimming gradually
    n = 26 + 25 + 20 + 20
    line = np.r_[np.zeros(26), np.ones(25), np.full(20, 2), np.full(20, 3)].astype(np.int32)
    number = np.r_[[-1] * 6, [7] * 20, [-1] * 5, [8] * 20, [9] * 20, [10] * 20].astype(np.int32)
    height = np.full(n, 50.0)
    height[51 + 19] = 10.0
    height[71:91] = np.linspace(50.0, 20.0, 20)
    refused = line_ends(line, number, height, min_refused=6, margin=3, dim_ratio=0.3)
    assert np.flatnonzero(refused).tolist() == [6, 7, 8, 70]
    assert not np.any(line_ends(line, number, height, margin=0, dim_ratio=0.0))
    # the margin at both ends, and every combination against the plain reference
    rng = np.random.default_rng(11)
    for _ in range(40):
        m = 300
        line = np.sort(rng.integers(-1, 12, m)).astype(np.int32)
        line = line[rng.permutation(m)]
        number = np.where(rng.random(m) < 0.7, 5, -1).astype(np.int32)
        height = rng.uniform(1.0, 60.0, m)
        for args in ((6, 3, 0.3, 0.0), (1, 1, 0.0, 2.2), (3, 5, 0.9, 0.0), (2, 0, 0.5, 1.5)):
            assert np.array_equal(
                line_ends(line, number, height, min_refused=args[0], margin=args[1],
                          dim_ratio=args[2], jump=args[3]),
                _ends_reference(line, number, height, *args),
            )  # fmt: skip


def test_a_line_end_a_step_in_brightness_off_its_line_is_refused() -> None:
    """An end peak 2.2 times brighter or dimmer than the two peaks next to it lies on
    another surface (an arm's line where the trunk's line turns away, the skin beside a
    cloth's line) and is refused; a line dimming gradually to its end, or an end peak
    stepping by less, keeps it; a line of two numbered peaks is not judged."""
    from rasterserver_plugins.peak_checks import line_ends

    gradual = np.linspace(50.0, 12.0, 20)  # a surface turning away: 0.9 per column
    brighter = np.r_[np.linspace(50.0, 18.0, 19), 57.0]  # 66005: an arm's peak at the end
    dimmer = np.r_[17.0, 38.0, 59.0, np.full(17, 50.0)]  # 65930: the skin's peak first
    small = np.r_[np.full(19, 30.0), 60.0]  # twice as bright: within the factor
    height = np.r_[gradual, brighter, dimmer, small, 5.0, 50.0]
    line = np.repeat(np.arange(5), [20, 20, 20, 20, 2]).astype(np.int32)
    number = np.full(line.size, 7, np.int32)
    refused = line_ends(line, number, height, margin=0, dim_ratio=0.0, jump=2.2)
    assert np.flatnonzero(refused).tolist() == [39, 40]
    assert not np.any(line_ends(line, number, height, margin=0, dim_ratio=0.0, jump=0.0))
    # the step is judged among the numbered peaks: a refused peak between does not count
    number[39] = -1
    assert not np.any(line_ends(line, number, height, margin=0, dim_ratio=0.0, jump=2.2)[:40])


def test_line_ends_of_degenerate_inputs() -> None:
    from rasterserver_plugins.peak_checks import line_ends

    empty = np.zeros(0, np.int32)
    assert line_ends(empty, empty, np.zeros(0)).size == 0
    none = np.full(4, -1, np.int32)
    assert not np.any(line_ends(none, np.full(4, 3, np.int32), np.ones(4)))
    unnumbered = np.zeros(9, np.int32)
    assert not np.any(line_ends(unnumbered, np.full(9, -1, np.int32), np.ones(9)))
    # a line shorter than the end's comparison keeps its dim end
    short = np.zeros(5, np.int32)
    assert not np.any(line_ends(short, short + 2, np.r_[1.0, [50.0] * 4], margin=0))
