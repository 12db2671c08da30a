"""The compiled scans of the peak checks against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.numbering_checks import by_line
from rasterserver_plugins.peak_checks import (
    beside_doubtful,
    column_islands,
    doubtful_share,
    stranded_runs,
)

# ---- the whole-array passes of rasterserver 0.x (plugins/peak_checks.py, version 7)


def _beside(col, row, number, doubtful, spacing, max_gap):  # type: ignore[no-untyped-def]
    out = np.zeros(col.size, dtype=bool)
    if col.size < 2 or not np.any(doubtful):
        return out
    a, b = np.arange(col.size - 1), np.arange(1, col.size)
    near = (col[a] == col[b]) & (row[b] - row[a] < max_gap * np.minimum(spacing[a], spacing[b]))
    out[a[near & doubtful[b]]] = True
    out[b[near & doubtful[a]]] = True
    out &= number >= 0
    return out


def _share(col, row, at, doubtful, numbered, spacing, window):  # type: ignore[no-untyped-def]
    half = window * np.asarray(spacing, dtype=np.float64)[at]
    reach = int(np.ceil(half.max(initial=0.0)))
    stride = float(np.ceil(np.max(row, initial=0.0))) + 2.0 * reach + 2.0
    key = col.astype(np.float64) * stride + row
    cum_d = np.r_[0, np.cumsum(doubtful, dtype=np.int64)]
    cum_n = np.r_[0, np.cumsum(numbered, dtype=np.int64)]
    offsets = np.arange(-reach, reach + 1)
    centre = col[at].astype(np.float64)[:, None] + offsets[None, :]
    lo = np.searchsorted(key, centre * stride + (row[at] - half)[:, None], side="left")
    hi = np.searchsorted(key, centre * stride + (row[at] + half)[:, None], side="right")
    inside = np.abs(offsets)[None, :] <= half[:, None]
    n_doubtful = np.where(inside, cum_d[hi] - cum_d[lo], 0).sum(axis=1)
    n_numbered = np.where(inside, cum_n[hi] - cum_n[lo], 0).sum(axis=1)
    return n_doubtful, n_numbered


def _islands(col, row, number, spacing, min_peaks, min_gap):  # type: ignore[no-untyped-def]
    out = np.zeros(col.size, dtype=bool)
    idx = np.flatnonzero(number >= 0)
    if idx.size == 0 or min_peaks <= 1:
        return out
    c, r, n, s = col[idx], row[idx], number[idx], spacing[idx]
    same = c[1:] == c[:-1]
    gap = np.where(same, r[1:] - r[:-1], np.inf)
    unit = np.minimum(s[1:], s[:-1])
    linked = same & (n[1:] - n[:-1] == 1) & (gap < 1.5 * unit)
    start = np.r_[True, ~linked]
    run = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    last = np.r_[first[1:], idx.size] - 1
    length = last - first + 1
    with np.errstate(divide="ignore", invalid="ignore"):
        above = np.r_[np.inf, gap][first] / s[first]
        below = np.r_[gap, np.inf][last] / s[last]
    alone = (length < min_peaks) & (above >= min_gap) & (below >= min_gap)
    out[idx[alone[run]]] = True
    return out


def _stranded(line_id, number, min_run):  # type: ignore[no-untyped-def]
    out = np.zeros(line_id.size, dtype=bool)
    lid = line_id.astype(np.int64)
    idx = np.flatnonzero(lid >= 0)
    if idx.size == 0:
        return out
    order = idx[by_line(lid[idx])]
    line = lid[order]
    numbered = number[order] >= 0
    same_line = line[1:] == line[:-1]
    start = numbered & ~np.r_[False, numbered[:-1] & same_line]
    first = np.flatnonzero(start)
    if first.size == 0:
        return out
    run = np.cumsum(start) - 1
    length = np.bincount(run[numbered], minlength=first.size)
    last = first + length - 1
    before = np.zeros(first.size, dtype=bool)
    after = np.zeros(first.size, dtype=bool)
    has = first > 0
    before[has] = same_line[first[has] - 1] & ~numbered[first[has] - 1]
    has = last < line.size - 1
    after[has] = same_line[last[has]] & ~numbered[last[has] + 1]
    drop = (length < min_run) & (before | after)
    out[order[numbered & drop[np.maximum(run, 0)]]] = True
    return out


# ---- random peaks: columns of lines about ``spacing`` apart, numbers with gaps and errors


def _peaks(seed: int, n_cols: int = 40, n_lines: int = 25) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    cols, rows, numbers, lines = [], [], [], []
    for c in range(n_cols):
        k = rng.integers(0, n_lines + 1)
        r = np.sort(rng.uniform(0, 12.0 * n_lines, k))
        if rng.random() < 0.3:  # evenly spaced lines, as on a back
            r = np.arange(k) * 12.0 + rng.normal(0, 0.5, k) + 5
            r = np.sort(np.round(r, int(rng.integers(0, 3))))  # ties in some columns
        n = np.arange(k) + int(rng.integers(0, 5))
        n[rng.random(k) < 0.2] = -1
        jump = rng.random(k) < 0.1
        n[jump & (n >= 0)] += 1
        cols.append(np.full(k, c))
        rows.append(r)
        numbers.append(n)
        lines.append(np.where(rng.random(k) < 0.1, -1, np.arange(k) % 7))
    col = np.concatenate(cols).astype(np.int32)
    row = np.concatenate(rows).astype(np.float64)
    spacing = rng.uniform(6.0, 16.0, col.size)
    if seed % 3 == 0:
        spacing[rng.random(col.size) < 0.05] = 0.0  # degenerate spacings: inf and NaN ratios
    return {
        "col": col,
        "row": row,
        "number": np.concatenate(numbers).astype(np.int32),
        "line": np.concatenate(lines).astype(np.int32),
        "spacing": spacing,
        "doubtful": rng.random(col.size) < rng.uniform(0.0, 0.4),
    }


@pytest.mark.parametrize("seed", range(40))
def test_compiled_checks_decide_as_the_whole_array_passes(seed: int) -> None:
    p = _peaks(seed)
    col, row, number, spacing, doubtful = (
        p["col"],
        p["row"],
        p["number"],
        p["spacing"],
        p["doubtful"],
    )
    for gap in (0.5, 1.25, 2.0):
        expected = _beside(col, row, number, doubtful, spacing, gap)
        got = beside_doubtful(col, row, number, doubtful, spacing, max_gap=gap)
        np.testing.assert_array_equal(got, expected)
    at = np.flatnonzero(np.random.default_rng(seed).random(col.size) < 0.2)
    for window in (0.0, 0.7, 2.0, 3.5):
        expected_counts = _share(col, row, at, doubtful, number >= 0, spacing, window)
        got_counts = doubtful_share(col, row, at, doubtful, number >= 0, spacing, window)
        np.testing.assert_array_equal(got_counts[0], expected_counts[0])
        np.testing.assert_array_equal(got_counts[1], expected_counts[1])
    for min_peaks, min_gap in ((1, 2.5), (2, 1.0), (3, 2.5), (5, 0.0)):
        expected = _islands(col, row, number, spacing, min_peaks, min_gap)
        with np.errstate(divide="ignore", invalid="ignore"):
            got = column_islands(col, row, number, spacing, min_peaks=min_peaks, min_gap=min_gap)
        np.testing.assert_array_equal(got, expected)
    for min_run in (0, 2, 6, 50):
        np.testing.assert_array_equal(
            stranded_runs(p["line"], number, min_run), _stranded(p["line"], number, min_run)
        )


def test_compiled_checks_of_degenerate_inputs() -> None:
    empty_i, empty_f = np.zeros(0, dtype=np.int32), np.zeros(0)
    assert beside_doubtful(empty_i, empty_f, empty_i, empty_f > 0, empty_f).size == 0
    assert column_islands(empty_i, empty_f, empty_i, empty_f).size == 0
    assert stranded_runs(empty_i, empty_i, 6).size == 0
    counts = doubtful_share(
        empty_i, empty_f, np.zeros(0, dtype=np.int64), empty_f > 0, empty_f > 0, empty_f, 2.0
    )
    assert counts[0].size == counts[1].size == 0
    one = np.array([3], dtype=np.int32)
    assert column_islands(one, np.array([5.0]), one, np.array([10.0])).tolist() == [True]
    assert stranded_runs(one, one, 6).tolist() == [False]
    # every peak unnumbered, every peak in no line
    minus = np.full(4, -1, dtype=np.int32)
    cols = np.array([0, 0, 1, 1], dtype=np.int32)
    rows = np.array([0.0, 10.0, 0.0, 10.0])
    spacing = np.full(4, 10.0)
    assert not column_islands(cols, rows, minus, spacing).any()
    assert not beside_doubtful(cols, rows, minus, np.ones(4, dtype=bool), spacing).any()
    assert not stranded_runs(minus, cols, 6).any()
