"""The compiled line-jump check against the whole-array passes it replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.numbering_checks import by_line
from rasterserver_plugins.peak_checks import line_jumps


def _passes(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    max_jump: float = 0.3,
    max_columns: int = 2,
) -> np.ndarray:
    """numbering_checks.line_jumps of rasterserver 0.x."""
    n = col.size
    out = np.zeros(n, dtype=bool)
    lid = line_id.astype(np.int64)
    idx = np.flatnonzero((lid >= 0) & (number >= 0))
    order = idx[by_line(lid[idx])]
    same = (lid[order][1:] == lid[order][:-1]) & (
        np.diff(col[order].astype(np.int64)) <= max_columns
    )
    dcol = np.maximum(np.diff(col[order].astype(np.float64)), 1.0)
    slope = np.diff(row[order]) / dcol
    slope = np.where(same, slope, np.nan)
    left = np.concatenate([[np.nan], slope[:-1]])
    right = np.concatenate([slope[1:], [np.nan]])
    ref = np.where(np.isnan(left), right, np.where(np.isnan(right), left, 0.5 * (left + right)))
    depart = np.abs(slope - ref) * dcol
    a, b = order[:-1], order[1:]
    with np.errstate(invalid="ignore"):
        bad = same & ~np.isnan(ref) & (depart > max_jump * spacing[a])
    out[a[bad]] = True
    out[b[bad]] = True
    return out


def _frame(seed: int) -> tuple[np.ndarray, ...]:
    """Lines over 300 columns with gaps, jumps of a spacing, unnumbered and unlined peaks."""
    rng = np.random.default_rng(seed)
    cols, rows, lids = [], [], []
    for line in range(30):
        c = np.sort(rng.choice(300, 240, replace=False))
        r = 20.0 + 10.0 * line + 0.01 * c + rng.normal(0, 0.3, c.size)
        jumps = rng.random(c.size) < 0.02
        r[jumps] += 10.0  # a peak of the neighbouring line
        cols.append(c)
        rows.append(r)
        lids.append(np.full(c.size, line if rng.random() > 0.1 else -1))
    col, row, lid = np.concatenate(cols), np.concatenate(rows), np.concatenate(lids)
    order = np.lexsort((row, col))
    col, row, lid = col[order], row[order], lid[order]
    number = np.where(rng.random(col.size) < 0.95, lid + 3, -1)
    number[lid < 0] = -1
    spacing = rng.uniform(8.0, 12.0, col.size)
    return col.astype(np.int32), row, lid.astype(np.int32), number.astype(np.int32), spacing


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_refusals_as_the_passes(seed: int) -> None:
    col, row, lid, number, spacing = _frame(seed)
    got = line_jumps(col, row, lid, number, spacing=spacing)
    want = _passes(col, row, lid, number, spacing)
    np.testing.assert_array_equal(got, want)
    assert 20 < got.sum() < col.size // 10


def test_too_few_peaks_refuse_nothing() -> None:
    col, row, lid, number, spacing = _frame(0)
    got = line_jumps(col[:2], row[:2], lid[:2], number[:2], spacing=spacing[:2])
    assert not got.any() and got.shape == (2,)
