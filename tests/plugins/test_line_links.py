"""The compiled scans of the line search against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.line_links import chain_heads, mutual_links, ranked_labels


def _nearest_passes(
    key: np.ndarray, col: np.ndarray, row: np.ndarray, target_col: np.ndarray, span: float
) -> tuple[np.ndarray, np.ndarray]:
    n = key.size
    j = np.searchsorted(key, target_col * span + row)
    best = np.full(n, -1, dtype=np.int64)
    dist = np.full(n, np.inf)
    for cand in (j - 1, j):
        valid = (cand >= 0) & (cand < n)
        c = np.clip(cand, 0, max(n - 1, 0))
        dd = np.where(valid & (col[c] == target_col), np.abs(row[c] - row), np.inf)
        better = dd < dist
        best[better] = c[better]
        dist[better] = dd[better]
    return best, dist


def _links_passes(
    col: np.ndarray, row: np.ndarray, max_step: float, span: float
) -> tuple[np.ndarray, np.ndarray]:
    """link_peaks of rasterserver 0.x, whole-array."""
    n = col.size
    col64 = col.astype(np.int64)
    key = col64 * span + row
    nxt, dn = _nearest_passes(key, col64, row, col64 + 1, span)
    ok = (nxt >= 0) & (dn <= max_step)
    p = np.flatnonzero(ok)
    q = nxt[p]
    d = np.abs(row[p] - row[q])
    for nb in (p - 1, p + 1):
        inside = (nb >= 0) & (nb < n)
        nb = np.clip(nb, 0, n - 1)
        nearer = inside & (col64[nb] == col64[p]) & (np.abs(row[nb] - row[q]) <= d)
        ok[p[nearer]] = False
    right = np.where(ok, nxt, -1)
    left = np.full(n, -1, dtype=np.int64)
    left[right[ok]] = np.flatnonzero(ok)
    return right, left


def _peaks(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Lines with noise, gaps, crossings and equal distances (rows on a 0.25 px grid)."""
    rng = np.random.default_rng(seed)
    cols, rows = [], []
    for c in range(200):
        base = np.arange(5, 300, rng.uniform(6, 12)) + 3 * np.sin(c / 17.0)
        keep = rng.random(base.size) > 0.1
        r = np.round((base[keep] + rng.normal(0, 0.8, keep.sum())) * 4) / 4
        extra = np.round(rng.uniform(0, 300, rng.integers(0, 4)) * 4) / 4
        r = np.unique(np.concatenate([r, extra]))
        cols.append(np.full(r.size, c))
        rows.append(r)
    return np.concatenate(cols).astype(np.int64), np.concatenate(rows)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_links_as_the_passes(seed: int) -> None:
    col, row = _peaks(seed)
    span = float(np.ceil(row.max() - min(row.min(), 0.0))) + 2.0 * 4.0 + 2.0
    got = mutual_links(col, row, span, 4.0)
    want = _links_passes(col, row, 4.0, span)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert (got[1] >= 0).sum() > col.size // 2


def test_heads_follow_the_links() -> None:
    col, row = _peaks(5)
    span = float(np.ceil(row.max())) + 10.0
    _, left = mutual_links(col, row, span, 4.0)
    head = chain_heads(left)
    # pointer jumping, the passes' way
    want = np.where(left >= 0, left, np.arange(left.size))
    while not np.array_equal(want[want], want):
        want = want[want]
    np.testing.assert_array_equal(head, want)


def test_labels_ranked_by_first_peak_short_lines_dropped() -> None:
    label = np.array([7, 3, 7, -1, 3, 9, 7, 3, 9, 2], dtype=np.int64)
    out = ranked_labels(label, 3)
    assert out.tolist() == [0, 1, 0, -1, 1, -1, 0, 1, -1, -1]
    assert out.dtype == np.int32
    assert ranked_labels(np.full(4, -1, dtype=np.int64), 1).tolist() == [-1] * 4
    assert ranked_labels(np.zeros(0, dtype=np.int64), 1).shape == (0,)


def test_no_peaks() -> None:
    right, left = mutual_links(np.zeros(0, np.int64), np.zeros(0), 10.0, 4.0)
    assert right.shape == left.shape == (0,)
    assert chain_heads(left).shape == (0,)


def test_a_link_to_a_later_peak_is_refused() -> None:
    with pytest.raises(ValueError, match="sorted"):
        chain_heads(np.array([-1, 2, -1], dtype=np.int64))
