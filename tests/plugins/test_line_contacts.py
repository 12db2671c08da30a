"""The compiled column neighbourhoods against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.line_sequence import _count_pairs, _lookup, line_neighbours

Pairs = tuple[np.ndarray, np.ndarray, np.ndarray]


def _passes(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    n_lines: int,
    gap_ratio: float = 1.6,
    cell: int = 24,
) -> Pairs:
    """line_sequence.line_neighbours of rasterserver 0.x."""
    n = col.size
    empty = np.zeros(0, dtype=np.int64)
    if n < 2 or n_lines < 2:
        return empty, empty, empty
    same_col = col[1:] == col[:-1]
    gap = row[1:] - row[:-1]
    g_prev = np.full(n - 1, np.nan)
    g_prev[1:] = np.where(same_col[:-1], gap[:-1], np.nan)
    g_next = np.full(n - 1, np.nan)
    g_next[:-1] = np.where(same_col[1:], gap[1:], np.nan)
    with np.errstate(invalid="ignore"):
        ref = np.where(
            np.isnan(g_prev),
            np.where(np.isnan(g_next), gap, g_next),
            np.where(np.isnan(g_next), g_prev, 0.5 * (g_prev + g_next)),
        )
    cell_col = col[:-1].astype(np.int64) // cell
    cell_row = (np.maximum(row[:-1], 0.0) * (1.0 / cell)).astype(np.int64)
    cell_id = cell_col * (int(cell_row.max()) + 1 if cell_row.size else 1) + cell_row
    cell_id = np.where(same_col, cell_id, -1)
    sel = cell_id >= 0
    if np.any(sel):
        n_cells = int(cell_id.max()) + 1
        for_mean = sel.copy()
        for _ in range(2):
            total = np.bincount(cell_id[for_mean], weights=gap[for_mean], minlength=n_cells)
            count = np.bincount(cell_id[for_mean], minlength=n_cells)
            typical = np.where(count > 0, total / np.maximum(count, 1), np.inf)
            for_mean = sel & (gap <= 1.4 * typical[np.maximum(cell_id, 0)])
        cell_ref = typical[np.maximum(cell_id, 0)]
    else:
        cell_ref = np.full(n - 1, np.inf)
    a, b = line_id[:-1].astype(np.int64), line_id[1:].astype(np.int64)
    ok = same_col & (a >= 0) & (b >= 0) & (a != b)
    ok &= (gap <= gap_ratio * ref) & (gap <= gap_ratio * cell_ref)
    if not np.any(ok):
        return empty, empty, empty
    keys, counts = _count_pairs(a[ok] * n_lines + b[ok], n_lines)
    if keys.size == 0:
        return empty, empty, empty
    upper, lower = keys // n_lines, keys % n_lines
    net = counts - _lookup(keys, counts, lower * n_lines + upper)
    lined = np.flatnonzero(line_id >= 0)
    if lined.size > 1:
        la, lb = line_id[lined[:-1]].astype(np.int64), line_id[lined[1:]].astype(np.int64)
        skipped = (col[lined[1:]] == col[lined[:-1]]) & (lined[1:] - lined[:-1] > 1) & (la != lb)
        s_keys, s_counts = _count_pairs(la[skipped] * n_lines + lb[skipped], n_lines)
        net = net - _lookup(s_keys, s_counts, keys)
    keep = net > 0
    return upper[keep], lower[keep], net[keep]


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Lines ~10 px apart over 300 columns, broken, some missing in stretches (wide gaps),
    some swapped, unlined peaks between; spacing varying across the image."""
    rng = np.random.default_rng(seed)
    cols, rows, lids = [], [], []
    n_lines = 40
    for line in range(n_lines):
        c = np.arange(int(rng.integers(0, 100)), int(rng.integers(150, 300)))
        c = c[rng.random(c.size) < 0.9]
        r = 6.0 + (9.0 + 0.01 * c) * line + rng.normal(0, 0.4, c.size)
        cols.append(c)
        rows.append(r)
        lid = np.full(c.size, line)
        lid[rng.random(c.size) < 0.03] = int(rng.integers(0, n_lines))  # mislabelled
        lids.append(lid)
    c = rng.integers(0, 300, 400)
    cols.append(c)
    rows.append(rng.uniform(-5.0, 400.0, c.size))
    lids.append(np.full(c.size, -1))
    col = np.concatenate(cols).astype(np.int32)
    row = np.concatenate(rows)
    lid = np.concatenate(lids).astype(np.int32)
    order = np.lexsort((row, col))
    return col[order], row[order], lid[order], n_lines


def _same(got: Pairs, want: Pairs) -> None:
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and np.array_equal(g, w)


@pytest.mark.parametrize("seed", range(4))
def test_same_neighbourhoods(seed: int) -> None:
    col, row, lid, n_lines = _frame(seed)
    want = _passes(col, row, lid, n_lines)
    assert want[0].size > 30
    _same(line_neighbours(col, row, lid, n_lines), want)
    _same(
        line_neighbours(col, row, lid, n_lines, gap_ratio=1.2, cell=16),
        _passes(col, row, lid, n_lines, gap_ratio=1.2, cell=16),
    )


def test_degenerate_frames() -> None:
    col, row, lid, n_lines = _frame(5)
    cases = [
        (col[:0], row[:0], lid[:0], n_lines),
        (col[:1], row[:1], lid[:1], n_lines),
        (col, row, lid, 1),
        (col, row, np.full(lid.size, -1, np.int32), n_lines),
        (np.arange(col.size, dtype=np.int32), row, lid, n_lines),  # one peak a column
        (col, row, lid % 2, 2),  # two lines
    ]
    for case in cases:
        _same(line_neighbours(*case), _passes(*case))
