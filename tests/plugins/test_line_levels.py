"""The compiled threshold levels of the line search against the numpy passes they replaced."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from rasterserver_plugins.line_levels import level_labels
from rasterserver_plugins.line_links import ranked_labels
from rasterserver_plugins.line_search import (
    DEFAULT_LEVELS,
    _chain_layout,
    _corner_cuts,
    _line_labels,
    _roots,
    _side_max,
    _smooth_along,
    _step_cuts,
    link_peaks,
    search_lines,
)

# ---- the level loop of rasterserver 0.x (plugins/line_search.py), counting its cases


def _levels(
    a: np.ndarray,
    linked: np.ndarray,
    perm: np.ndarray,
    levels: tuple[float, ...],
    *,
    dip: float,
    dip_window: int,
    min_seed: int,
    min_length: int,
    tally: Counter[str] | None = None,
) -> np.ndarray:
    tally = Counter() if tally is None else tally
    n = a.size
    head = perm[np.maximum.accumulate(np.where(linked, 0, np.arange(n)))]
    label = np.full(n, -1, dtype=np.int64)
    parent = np.zeros(0, dtype=np.int64)
    scale = float(np.median(a))
    unlabelled = np.arange(n)
    for li, factor in enumerate(levels):
        last = li == len(levels) - 1
        unlabelled = unlabelled[label[unlabelled] < 0]
        free = unlabelled[a[unlabelled] >= factor * scale]
        if free.size == 0:
            continue
        brk = np.ones(free.size, dtype=bool)
        brk[1:] = (free[1:] != free[:-1] + 1) | ~linked[free[1:]]
        run_start = np.flatnonzero(brk)
        run_len = np.diff(np.append(run_start, free.size))
        s_pos = free[run_start]
        e_pos = free[run_start + run_len - 1]
        left_lab = np.where(linked[s_pos], label[np.maximum(s_pos - 1, 0)], -1)
        nxt = np.minimum(e_pos + 1, n - 1)
        right_lab = np.where((e_pos + 1 < n) & linked[nxt], label[nxt], -1)
        left_lab = _roots(parent, left_lab)
        right_lab = _roots(parent, right_lab)
        run_label = np.where(left_lab >= 0, left_lab, right_lab)
        run_of = np.repeat(np.arange(run_start.size), run_len)
        new_label = run_label[run_of]
        conflict = (left_lab >= 0) & (right_lab >= 0) & (left_lab != right_lab)
        tally["one line"] += int(np.sum((left_lab >= 0) != (right_lab >= 0)))
        if np.any(conflict):
            cr = np.flatnonzero(conflict)
            a_free = a[free]
            lowest = np.minimum.reduceat(a_free, run_start)
            at_min = np.flatnonzero(conflict[run_of] & (a_free == lowest[run_of]))
            tally["tied minima"] += at_min.size - cr.size
            _, first = np.unique(run_of[at_min], return_index=True)
            cut_at = free[at_min[first]]
            side = np.minimum(
                _side_max(a, head, s_pos[cr], -1, dip_window),
                _side_max(a, head, e_pos[cr], 1, dip_window),
            )
            pronounced = a[cut_at] < dip * side
            tally["pronounced"] += int(pronounced.sum())
            cut_of_run = np.full(run_start.size, -1, dtype=np.int64)
            cut_of_run[cr[pronounced]] = cut_at[pronounced]
            cut_el = cut_of_run[run_of]
            split = cut_el >= 0
            new_label[split] = np.where(
                free[split] < cut_el[split],
                left_lab[run_of[split]],
                np.where(free[split] > cut_el[split], right_lab[run_of[split]], -1),
            )
            shallow = cr[~pronounced]
            tally["shallow"] += shallow.size
            if shallow.size:
                par = parent.tolist()
                for x, y in zip(
                    left_lab[shallow].tolist(), right_lab[shallow].tolist(), strict=True
                ):
                    while par[x] != x:
                        x = par[x]
                    while par[y] != y:
                        y = par[y]
                    tally["joined"] += x != y
                    if x != y:
                        par[max(x, y)] = min(x, y)
                parent = np.asarray(par, dtype=np.int64)
        label[free] = new_label
        lonely = (left_lab < 0) & (right_lab < 0)
        need = min_length if last else max(min_seed, min_length)
        seeds = lonely & (run_len >= need)
        tally["too short"] += int(np.sum(lonely & ~seeds))
        if np.any(seeds):
            tally["seeds"] += int(seeds.sum())
            ids = parent.size + np.cumsum(seeds) - 1
            label[free] = np.where(seeds[run_of], ids[run_of], label[free])
            parent = np.concatenate([parent, parent.size + np.arange(int(seeds.sum()))])
    label = np.where(label >= 0, _roots(parent, label), -1)
    out = np.full(label.size, -1, dtype=np.int64)  # _compact before its ranking
    out[perm] = label
    return out


def _search(
    col: np.ndarray,
    row: np.ndarray,
    area: np.ndarray,
    levels: tuple[float, ...] = DEFAULT_LEVELS,
    min_length: int = 3,
) -> np.ndarray:
    """search_lines of rasterserver 0.x with its default parameters, the levels as above."""
    n = col.size
    _, left = link_peaks(col, row, max_step=4.0)
    perm, head = _chain_layout(left, col)
    linked = np.zeros(n, dtype=bool)
    linked[1:] = head[1:] == head[:-1]
    linked &= ~_corner_cuts(row[perm], linked, 1.5)
    a = area[perm].astype(np.float64)
    linked &= ~_step_cuts(a, linked, 3, 1.6)
    a = _smooth_along(a, linked, 2)
    label = _levels(
        a, linked, perm, levels, dip=0.6, dip_window=20, min_seed=8, min_length=min_length
    )
    return ranked_labels(label, min_length)


# ---- chains


def _chains(
    seed: int, n: int, *, p_break: float, quantum: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chain-ordered areas (bright and faint stretches, dips of every depth, a few zeros;
    rounded to ``quantum``, 0 for none, so that minima tie), links (a break with probability
    ``p_break``) and a random peak of every position."""
    rng = np.random.default_rng(seed)
    linked = rng.random(n) > p_break
    if n:
        linked[0] = False
    k = np.arange(n)
    wave = 1.0 + 0.6 * np.sin(k / rng.uniform(3.0, 15.0)) * np.sin(k / rng.uniform(20.0, 90.0))
    a = wave * rng.uniform(0.7, 1.3, n) * np.where(k % 400 < 250, 1.0, 2.2)
    a[rng.random(n) < 0.01] = 0.0
    if quantum:
        a = np.round(a / quantum) * quantum
    return a, linked, rng.permutation(n).astype(np.int64)


def _same(
    a: np.ndarray,
    linked: np.ndarray,
    perm: np.ndarray,
    tally: Counter[str],
    levels: tuple[float, ...] = DEFAULT_LEVELS,
    **kw: int | float,
) -> None:
    params = {"dip": 0.6, "dip_window": 20, "min_seed": 8, "min_length": 3} | kw
    want = _levels(a, linked, perm, levels, tally=tally, **params)  # type: ignore[arg-type]
    got = _line_labels(a, linked, perm, levels, **params)  # type: ignore[arg-type]
    assert got.dtype == want.dtype and np.array_equal(got, want)


PARAMS: list[dict[str, int | float]] = [
    {},
    {"dip": 0.9},
    {"dip": 0.2, "dip_window": 3},
    {"dip_window": 1, "min_seed": 1, "min_length": 1},
    {"min_seed": 3, "min_length": 8},
    {"dip": 1.0, "min_seed": 20},
]
LEVELS: list[tuple[float, ...]] = [
    DEFAULT_LEVELS,
    DEFAULT_LEVELS[:-1],  # no last level of 0: the faint peaks stay out
    (1.0,),
    (0.0,),
    (),
    tuple(np.linspace(3.0, 0.0, 31)),  # a level at every area
    (1.4, 1.4, 1.0, 0.7, 0.7, 0.35),
]


@pytest.mark.parametrize("seed", range(12))
def test_same_labels_on_random_chains(seed: int) -> None:
    tally: Counter[str] = Counter()
    for i, (p_break, quantum) in enumerate(((0.02, 0.0), (0.01, 0.05), (0.1, 0.2), (0.0, 0.1))):
        a, linked, perm = _chains(100 * seed + i, 3000, p_break=p_break, quantum=quantum)
        for params in PARAMS:
            _same(a, linked, perm, tally, **params)
        for levels in LEVELS:
            _same(a, linked, perm, tally, levels)
    # every case of the loop was met: runs growing a line, splits, joins, tied minima
    for case in ("one line", "tied minima", "pronounced", "shallow", "joined"):
        assert tally[case] > 0, case
    assert tally["seeds"] > 0 and tally["too short"] > 0


def test_same_labels_on_degenerate_chains() -> None:
    tally: Counter[str] = Counter()
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 9, 40):
        perm = rng.permutation(n).astype(np.int64)
        for linked in (np.zeros(n, dtype=bool), np.r_[False, np.ones(n - 1, dtype=bool)]):
            for a in (
                np.full(n, 5.0),  # every area the median: ties at every threshold
                rng.uniform(0.5, 2.0, n),
                np.round(rng.uniform(0.0, 3.0, n)),
            ):
                for params in PARAMS:
                    _same(a, linked, perm, tally, **params)
                for levels in LEVELS:
                    _same(a, linked, perm, tally, levels)
    # one chain of all peaks, with non-finite areas (the side maxima propagate NaN)
    a, linked, perm = _chains(3, 500, p_break=0.0, quantum=0.1)
    for bad in (np.inf, -np.inf, np.nan):
        b = a.copy()
        b[rng.integers(0, 500, 6)] = bad
        for params in PARAMS:
            _same(b, linked, perm, tally, **params)
    empty = level_labels(
        np.zeros(0), np.zeros(0, bool), np.zeros(0, np.int64), np.ones(3), 0.6, 20, 8, 3
    )
    assert empty.dtype == np.int64 and empty.size == 0


def test_a_pronounced_minimum_splits_and_a_shallow_one_joins() -> None:
    # two bright stretches (the median) seeded at the first level, a fainter one between them
    # met at the second; the weakest peak between decides
    bright = np.full(12, 2.0)
    for low, split in ((0.5, True), (1.5, False)):
        middle = np.array([1.8, 1.7, low, 1.7, 1.8])
        a = np.concatenate([bright, middle, bright])
        n = a.size
        linked = np.r_[False, np.ones(n - 1, dtype=bool)]
        perm = np.arange(n, dtype=np.int64)
        tally: Counter[str] = Counter()
        _same(a, linked, perm, tally, (0.95, 0.0))
        got = _line_labels(
            a, linked, perm, (0.95, 0.0), dip=0.6, dip_window=20, min_seed=8, min_length=3
        )
        assert tally["pronounced" if split else "shallow"] == 1
        if split:  # the minimum in neither line, the two lines apart
            assert got[14] == -1 and np.unique(got).tolist() == [-1, 0, 1]
        else:
            assert np.unique(got).tolist() == [0]


@pytest.mark.parametrize("seed", range(6))
def test_same_lines_from_peaks(seed: int) -> None:
    # lines of peaks across columns, crossing and fading (links, corners, area steps and
    # smoothing as the stage has them), then search_lines against the old loop
    rng = np.random.default_rng(seed)
    cols, rows, areas = [], [], []
    for line in range(40):
        c = np.arange(int(rng.integers(0, 150)), int(rng.integers(150, 400)))
        c = c[rng.random(c.size) < 0.93]
        cols.append(c)
        rows.append(4.0 + 7.0 * line + np.cumsum(rng.normal(0, 0.6, c.size)))
        fade = 1.0 + 0.7 * np.sin(c / rng.uniform(8.0, 40.0))
        areas.append(100.0 * fade * rng.uniform(0.6, 1.4, c.size))
    col, row, area = np.concatenate(cols), np.concatenate(rows), np.concatenate(areas)
    order = np.lexsort((row, col))
    col, row = col[order].astype(np.int32), row[order]
    area = area[order].astype(np.float32)
    for levels in (DEFAULT_LEVELS, DEFAULT_LEVELS[:-1], (0.0,)):
        got = search_lines(col, row, area, levels=levels)
        want = _search(col, row, area, levels)
        assert got.dtype == want.dtype == np.int32 and np.array_equal(got, want)
    assert search_lines(col[:0], row[:0], area[:0]).size == 0
    for k, min_length in ((1, 1), (1, 3), (5, 1)):  # a single peak, a few unlinked ones
        got = search_lines(col[:k], row[:k], area[:k], min_length=min_length)
        assert np.array_equal(got, _search(col[:k], row[:k], area[:k], min_length=min_length))
