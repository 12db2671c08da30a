"""The compiled order checks of numbered columns against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.numbering_checks import column_order_conflicts, local_spacing


def _local_spacing(col: np.ndarray, row: np.ndarray, number: np.ndarray) -> np.ndarray | None:
    """numbering_checks.local_spacing of rasterserver 0.x."""
    numbered = np.flatnonzero(number >= 0)
    if numbered.size < 2:
        return None
    a, b = numbered[:-1], numbered[1:]
    one = (col[a] == col[b]) & (number[b].astype(np.int64) - number[a] == 1)
    if not np.any(one):
        return None
    a, b = a[one], b[one]
    gap = row[b] - row[a]
    n_rows = int(np.max(row, initial=0.0)) // 32 + 1
    cell_of = (col.astype(np.int64) // 32) * n_rows + np.maximum(row, 0.0).astype(np.int64) // 32
    n_cells = int(cell_of.max()) + 1
    total = np.bincount(cell_of[a], weights=gap, minlength=n_cells)
    cnt = np.bincount(cell_of[a], minlength=n_cells)
    mean = np.where(cnt > 0, total / np.maximum(cnt, 1), float(np.median(gap)))
    return mean[cell_of]


def _conflicts(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray | None = None,
    tolerance: float = 0.3,
    max_multiple: int = 3,
) -> np.ndarray:
    """numbering_checks.column_order_conflicts of rasterserver 0.x."""
    n = col.size
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    numbered = np.flatnonzero(number >= 0)
    if numbered.size < 2:
        return out
    a, b = numbered[:-1], numbered[1:]
    same = col[a] == col[b]
    a, b = a[same], b[same]
    if a.size == 0:
        return out
    gap = row[b] - row[a]
    k = number[b].astype(np.int64) - number[a].astype(np.int64)
    one = k == 1
    if not np.any(one):
        return out
    if spacing is None:
        spacing = _local_spacing(col, row, number)
    if spacing is None:
        return out
    ref = spacing[a]
    steps = gap / ref
    m = np.rint(steps)
    near = (m <= max_multiple) & (np.abs(steps - m) <= tolerance)
    conflict = (near & (m == 1) & (k != 1)) | (near & (m >= 2) & (k > m))
    conflict |= (k <= 0) & (gap < 1.5 * ref)
    contiguous = np.r_[False, b[:-1] == a[1:]]
    single = np.where(one, gap, np.inf)
    above = np.where(contiguous, np.r_[np.inf, single[:-1]], np.inf)
    below = np.where(np.r_[contiguous[1:], False], np.r_[single[1:], np.inf], np.inf)
    beside = np.minimum(above, below)
    conflict |= (k >= 2) & np.isfinite(beside) & (gap < (k - 0.5) * beside)
    widest = np.maximum(
        np.where(np.isfinite(above), above, 0.0), np.where(np.isfinite(below), below, 0.0)
    )
    conflict |= (k >= 1) & (widest > 0) & (gap > (k + 0.5) * widest)
    out[a[conflict]] = True
    out[b[conflict]] = True
    return out


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numbered columns of peaks ~10 px apart over 200 columns and 300 rows (cells of
    varying spacing): numbers skipped, repeated, swapped and a level off; unnumbered peaks,
    peaks a half spacing and two spacings apart."""
    rng = np.random.default_rng(seed)
    cols, rows, numbers = [], [], []
    for c in range(200):
        spacing = 9.0 + 3.0 * np.sin(c / 40.0)
        n = np.arange(30)
        r = 4.0 + spacing * n + rng.normal(0, 0.6, n.size)
        keep = rng.random(n.size) < 0.85  # lines not found
        num = n + 1 + np.where(rng.random(n.size) < 0.05, rng.integers(-2, 3, n.size), 0)
        num = np.where(rng.random(n.size) < 0.1, -1, num)
        extra = rng.random(3) * 300.0  # stray peaks between lines
        cols.append(np.full(int(keep.sum()) + 3, c))
        rows.append(np.concatenate([r[keep], extra]))
        numbers.append(np.concatenate([num[keep], rng.integers(-1, 31, 3)]))
    col = np.concatenate(cols).astype(np.int32)
    row = np.concatenate(rows)
    number = np.concatenate(numbers).astype(np.int32)
    order = np.lexsort((row, col))
    return col[order], row[order], number[order]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_same_spacing_and_conflicts(seed: int) -> None:
    col, row, number = _frame(seed)
    want = _local_spacing(col, row, number)
    got = local_spacing(col, row, number)
    assert want is not None and got is not None
    assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    conflicts = _conflicts(col, row, number)
    assert 0 < conflicts.sum() < col.size // 2
    np.testing.assert_array_equal(column_order_conflicts(col, row, number), conflicts)
    np.testing.assert_array_equal(
        column_order_conflicts(col, row, number, spacing=want, tolerance=0.2, max_multiple=2),
        _conflicts(col, row, number, spacing=want, tolerance=0.2, max_multiple=2),
    )


def test_degenerate_columns() -> None:
    col, row, number = _frame(4)
    cases = [
        (col[:0], row[:0], number[:0]),  # no peaks
        (col[:1], row[:1], number[:1]),  # one peak
        (col[:2], row[:2], number[:2]),
        (col, row, np.full(col.size, -1, np.int32)),  # nothing numbered
        (np.arange(col.size, dtype=np.int32), row, number),  # one peak a column
        (col, row, np.full(col.size, 7, np.int32)),  # no consecutive numbers
        (col, row - 50.0, number),  # negative rows
    ]
    for c, r, n in cases:
        want = _local_spacing(c, r, n)
        got = local_spacing(c, r, n)
        assert (got is None) == (want is None)
        if want is not None and got is not None:
            assert got.tobytes() == want.tobytes()
        np.testing.assert_array_equal(column_order_conflicts(c, r, n), _conflicts(c, r, n))
    # a spacing of zero: steps infinite or not a number
    zero = np.zeros(col.size)
    with np.errstate(divide="ignore", invalid="ignore"):
        want = _conflicts(col, row, number, spacing=zero)
    np.testing.assert_array_equal(column_order_conflicts(col, row, number, spacing=zero), want)
