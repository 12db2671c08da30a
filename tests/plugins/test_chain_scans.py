"""The compiled scans along chains against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.line_search import (
    _chain_layout,
    _corner_cuts,
    _roots,
    _side_max,
    _smooth_along,
    _step_cuts,
    link_peaks,
)

# ---- the whole-array passes of rasterserver 0.x (plugins/line_search.py)


def _layout(left: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from rasterserver_plugins.line_links import chain_heads

    n = left.size
    idx = np.arange(n, dtype=np.int64)
    head = chain_heads(np.ascontiguousarray(left, dtype=np.int64))
    depth = col.astype(np.int64) - col[head]
    length = np.bincount(head, minlength=n)
    start = np.cumsum(length) - length
    pos = start[head] + depth
    perm = np.empty(n, dtype=np.int64)
    perm[pos] = idx
    return perm, head[perm]


def _corners(r: np.ndarray, linked: np.ndarray, corner: float) -> np.ndarray:
    n = r.size
    step = np.zeros(n)
    step[1:] = r[1:] - r[:-1]
    step[~linked] = np.nan
    prev_step = np.full(n, np.nan)
    prev_step[1:] = step[:-1]
    next_step = np.full(n, np.nan)
    next_step[:-1] = step[1:]
    with np.errstate(invalid="ignore"):
        around = np.where(
            np.isnan(prev_step),
            next_step,
            np.where(np.isnan(next_step), prev_step, 0.5 * (prev_step + next_step)),
        )
        dev = np.abs(step - around)
        dev = np.where(np.isnan(dev), 0.0, dev)
    prev_dev = np.zeros(n)
    prev_dev[1:] = dev[:-1]
    next_dev = np.zeros(n)
    next_dev[:-1] = dev[1:]
    return (dev > corner) & (dev >= prev_dev) & (dev >= next_dev)


def _bounds(linked: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = linked.size
    idx = np.arange(n)
    first = np.where(linked, 0, idx)
    np.maximum.accumulate(first, out=first)
    ends = np.ones(n, dtype=bool)
    ends[:-1] = ~linked[1:]
    last = np.where(ends, idx, n)
    last = np.minimum.accumulate(last[::-1])[::-1]
    return idx, first, last


def _smooth(a: np.ndarray, linked: np.ndarray, half: int) -> np.ndarray:
    idx, first, last = _bounds(linked)
    lo = np.maximum(idx - half, first)
    hi = np.minimum(idx + half, last)
    total = np.zeros(a.size + 1)
    np.cumsum(a, out=total[1:])
    return (total[hi + 1] - total[lo]) / (hi - lo + 1)


def _steps(a: np.ndarray, linked: np.ndarray, half: int, ratio: float) -> np.ndarray:
    n = a.size
    if n < 2 * half or half < 1:
        return np.zeros(n, dtype=bool)
    idx, first, last = _bounds(linked)
    total = np.zeros(n + 1)
    np.cumsum(a, out=total[1:])
    lo = np.maximum(idx - half, first)
    hi = np.minimum(idx + half - 1, last)
    n_before = idx - lo
    n_after = hi - idx + 1
    with np.errstate(divide="ignore", invalid="ignore"):
        before = (total[idx] - total[lo]) / n_before
        after = (total[hi + 1] - total[idx]) / n_after
        jump = np.abs(np.log(before / after))
    full = linked & (n_before >= half) & (n_after >= half) & np.isfinite(jump)
    jump = np.where(full, jump, 0.0)
    prev_j = np.zeros(n)
    prev_j[1:] = jump[:-1]
    next_j = np.zeros(n)
    next_j[:-1] = jump[1:]
    return full & (jump > np.log(ratio)) & (jump >= prev_j) & (jump > next_j)


def _sides(a: np.ndarray, head: np.ndarray, at: np.ndarray, step: int, window: int) -> np.ndarray:
    src = at[:, None] + step * np.arange(1, window + 1)[None, :]
    np.clip(src, 0, a.size - 1, out=src)
    same = head[src] == head[at][:, None]
    return np.where(same, a[src], 0.0).max(axis=1)


def _jumps(parent: np.ndarray, ids: np.ndarray) -> np.ndarray:
    ids = np.asarray(ids, dtype=np.int64)
    if parent.size == 0:
        return ids
    out = np.where(ids >= 0, parent[np.maximum(ids, 0)], -1)
    while True:
        nxt = np.where(out >= 0, parent[np.maximum(out, 0)], -1)
        if np.array_equal(nxt, out):
            return out
        out = nxt


# ---- chains


def _chains(seed: int, n: int = 6000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chain-ordered rows (walks with kinks and jumps), areas (steps of kind and surface,
    a few zero), and links (chains of 1 to 200 positions)."""
    rng = np.random.default_rng(seed)
    linked = rng.random(n) > 0.02
    linked[0] = False
    r = np.cumsum(rng.normal(0, 0.3, n) + np.where(rng.random(n) < 0.02, 3.0, 0.0))
    a = rng.uniform(0.8, 1.2, n) * np.where(np.arange(n) % 300 < 150, 1.0, 2.5)
    a[rng.random(n) < 0.002] = 0.0
    return r, a, linked


@pytest.mark.parametrize("seed", range(4))
def test_same_scans(seed: int) -> None:
    r, a, linked = _chains(seed)
    for corner in (1.5, 0.5):
        want = _corners(r, linked, corner)
        assert want.any()
        assert np.array_equal(_corner_cuts(r, linked, corner), want)
    for half in (1, 2, 5):
        got = _smooth_along(a, linked, half)
        assert got.tobytes() == _smooth(a, linked, half).tobytes()
    for half, ratio in ((3, 1.6), (1, 1.2), (8, 2.0)):
        want = _steps(a, linked, half, ratio)
        assert want.any()
        assert np.array_equal(_step_cuts(a, linked, half, ratio), want)


def test_chain_layout_of_linked_peaks() -> None:
    rng = np.random.default_rng(0)
    cols, rows = [], []
    for line in range(60):
        c = np.arange(int(rng.integers(0, 100)), int(rng.integers(100, 300)))
        c = c[rng.random(c.size) < 0.95]
        cols.append(c)
        rows.append(5.0 + 10.0 * line + np.cumsum(rng.normal(0, 0.5, c.size)))
    col = np.concatenate(cols)
    row = np.concatenate(rows)
    order = np.lexsort((row, col))
    col, row = col[order].astype(np.int32), row[order]
    _, left = link_peaks(col, row, max_step=4.0)
    for got, want in zip(_chain_layout(left, col), _layout(left, col), strict=True):
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_short_and_unlinked_chains() -> None:
    r, a, linked = _chains(9, n=40)
    none = np.zeros(40, dtype=bool)
    for lk in (linked, none, np.ones(40, dtype=bool)):
        assert np.array_equal(_corner_cuts(r, lk, 1.5), _corners(r, lk, 1.5))
        assert _smooth_along(a, lk, 2).tobytes() == _smooth(a, lk, 2).tobytes()
        for half in (0, 3, 20, 21):
            assert np.array_equal(_step_cuts(a, lk, half, 1.6), _steps(a, lk, half, 1.6))
    one = np.array([True])
    assert np.array_equal(_corner_cuts(r[:1], one, 1.5), _corners(r[:1], one, 1.5))
    assert _smooth_along(a[:1], one, 2).tobytes() == _smooth(a[:1], one, 2).tobytes()


@pytest.mark.parametrize("seed", range(3))
def test_same_side_maxima_and_roots(seed: int) -> None:
    _, a, linked = _chains(seed)
    head = np.maximum.accumulate(np.where(linked, 0, np.arange(a.size)))
    at = np.random.default_rng(seed).integers(0, a.size, 300)
    at[:4] = [0, 1, a.size - 1, a.size - 2]
    for step, window in ((-1, 20), (1, 20), (1, 1), (-1, 3)):
        got = _side_max(a, head, at, step, window)
        assert got.tobytes() == _sides(a, head, at, step, window).tobytes()
    nan = a.copy()
    nan[at[10] + 1] = np.nan
    assert np.array_equal(
        _side_max(nan, head, at, 1, 20), _sides(nan, head, at, 1, 20), equal_nan=True
    )
    # a forest of 500 ids, roots their own parents, every other id below its parent
    rng = np.random.default_rng(seed)
    parent = np.arange(500)
    for i in range(1, 500):
        if rng.random() < 0.7:
            parent[i] = int(rng.integers(0, i))
    ids = rng.integers(-1, 500, 2000)
    assert np.array_equal(_roots(parent, ids), _jumps(parent, ids))
    assert _roots(np.zeros(0, np.int64), np.array([-1, -1])).tolist() == [-1, -1]
    assert _roots(parent, np.zeros(0, np.int64)).size == 0


def _turns(r: np.ndarray, linked: np.ndarray, turn: float, half: int) -> np.ndarray:
    """The turn cuts written as whole-array passes (cumulative sums), the kernel's reference."""
    n = r.size
    step = np.full(n, np.nan)
    step[1:] = np.where(linked[1:], r[1:] - r[:-1], np.nan)
    total = np.concatenate([[0.0], np.cumsum(np.nan_to_num(step))])
    gaps = np.concatenate([[0], np.cumsum(np.isnan(step))])
    dev = np.zeros(n)
    k = np.arange(half, n - half)
    whole = ((gaps[k] - gaps[k - half]) == 0) & ((gaps[k + half + 1] - gaps[k + 1]) == 0)
    whole &= linked[k]
    before = (total[k] - total[k - half]) / half
    after = (total[k + half + 1] - total[k + 1]) / half
    dev[k] = np.where(whole, np.abs(after - before), 0.0)
    prev = np.concatenate([[0.0], dev[:-1]])
    nxt = np.concatenate([dev[1:], [0.0]])
    return (dev > turn) & (dev >= prev) & (dev >= nxt)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_turn_cuts_match_the_array_passes(seed: int) -> None:
    from rasterserver_plugins.line_search import _turn_cuts

    rng = np.random.default_rng(seed)
    n = 400
    r = np.cumsum(rng.normal(0.0, 0.8, n))
    linked = rng.random(n) > 0.05
    linked[0] = False
    for turn, half in ((0.5, 3), (1.0, 2), (2.0, 4)):
        assert np.array_equal(_turn_cuts(r, linked, turn, half), _turns(r, linked, turn, half))
    # chains too short to judge, and no positions at all
    short = np.array([False, True, True])
    assert not _turn_cuts(np.array([0.0, 5.0, 0.0]), short, 0.1, 3).any()
    assert _turn_cuts(np.zeros(0), np.zeros(0, dtype=bool), 1.0, 3).size == 0


def _vertices(r: np.ndarray, linked: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """The vertex cuts as whole-array passes and a loop over the cut links (reference)."""
    n = r.size
    step = np.full(n, np.nan)
    step[1:] = np.where(linked[1:], r[1:] - r[:-1], np.nan)
    prev = np.concatenate([[np.nan], step[:-1]])
    nxt = np.concatenate([step[1:], [np.nan]])
    around = np.where(np.isnan(prev), nxt, np.where(np.isnan(nxt), prev, 0.5 * (prev + nxt)))
    dev = np.nan_to_num(np.abs(step - around), nan=0.0)
    out = cut.copy()
    for k in np.nonzero(cut)[0]:
        beside = [j for j in (k - 1, k + 1) if 0 < j < n and linked[j] and not cut[j]]
        if beside:
            out[max(beside, key=lambda j: dev[j])] = True
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vertex_cuts_match_the_reference(seed: int) -> None:
    from rasterserver_plugins.chain_scans import vertex_cuts

    rng = np.random.default_rng(seed)
    n = 400
    r = np.cumsum(rng.normal(0.0, 0.8, n))
    linked = rng.random(n) > 0.05
    linked[0] = False
    cut = linked & (rng.random(n) < 0.05)
    assert np.array_equal(vertex_cuts(r, linked, cut), _vertices(r, linked, cut))
    # nothing cut, nothing added; no positions at all
    none = np.zeros(n, dtype=bool)
    assert not vertex_cuts(r, linked, none).any()
    assert vertex_cuts(np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)).size == 0
