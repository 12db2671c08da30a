"""The compiled column pairs against the whole-array passes they replaced: the same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.code_evidence import level_statistics, reliability, robust_centres
from rasterserver_plugins.code_tiles import CodeBands
from rasterserver_plugins.column_pairs import grouped_pairs
from rasterserver_plugins.numbering_checks import pair_contradictions

from rasterserver.raster import Raster, make_raster

LAM = float(np.log(1.5))

# ---- the whole-array passes of rasterserver 0.x


def _level_pairs(
    col: np.ndarray, area: np.ndarray, comp_of: np.ndarray, lev_of: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """code_evidence.level_pairs of rasterserver 0.x."""
    pair = (
        (col[1:] == col[:-1])
        & (comp_of[1:] == comp_of[:-1])
        & (comp_of[:-1] >= 0)
        & (lev_of[:-1] >= 0)
        & (lev_of[1:] == lev_of[:-1] + 1)
    )
    k = np.flatnonzero(pair)
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(area[k].astype(np.float64) / area[k + 1].astype(np.float64))
    good = np.isfinite(lr)
    return k[good], lr[good]


def _peak_levels(
    line_id: np.ndarray, line_order: np.ndarray, line_component: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    lid = line_id.astype(np.int64)
    has = lid >= 0
    comp = np.where(has, line_component[np.maximum(lid, 0)], -1).astype(np.int64)
    lev = np.where(has, line_order[np.maximum(lid, 0)], -1).astype(np.int64)
    return comp, lev


def _level_statistics(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """code_evidence.level_statistics of rasterserver 0.x."""
    empty_i = np.zeros(0, dtype=np.int64)
    empty = (empty_i, empty_i, np.zeros(0), empty_i, np.zeros(0))
    if col.size < 2 or line_order.size == 0:
        return empty
    comp_of, lev_of = _peak_levels(line_id, line_order, line_component)
    k, lr = _level_pairs(col, area, comp_of, lev_of)
    if k.size == 0:
        return empty
    comp, level = comp_of[k], lev_of[k]
    span = int(lev_of.max()) + 2
    groups, centre, counts, spread = robust_centres(comp * span + level, lr)
    return groups // span, groups % span, centre, counts, spread


def _bands(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
    step: int = 32,
) -> dict[str, np.ndarray]:
    """code_tiles.CodeBands.__init__ of rasterserver 0.x: the attributes it sets."""
    lam, tolerance, min_columns, correlation = LAM, 0.5, 5, 4.0
    comp, lev = _peak_levels(line_id, line_order, line_component)
    out = {"comp": comp, "lev": lev, "rows": np.zeros(0, dtype=np.int64)}
    k, lr = _level_pairs(col, area, comp, lev)
    if k.size == 0:
        return out
    out["ids"] = ids = np.flatnonzero(np.bincount(comp[k]))
    out["compact"] = compact = np.full(int(comp.max()) + 1, -1, dtype=np.int64)
    compact[ids] = np.arange(ids.size)
    n_bands = int(col.max()) // step + 2
    n_lev = int(lev[k].max()) + 2
    p_ci, p_lev, p_band = compact[comp[k]], lev[k], col.astype(np.int64)[k] // step
    keys, ratios = [], []
    for db in (0, 1):
        b = p_band - db
        ok = b >= 0
        keys.append((p_ci[ok] * n_bands + b[ok]) * n_lev + p_lev[ok])
        ratios.append(lr[ok])
    groups, centre, count, spread = robust_centres(np.concatenate(keys), np.concatenate(ratios))
    weight = np.minimum(1.0, count / float(min_columns)) * reliability(
        count.astype(np.float64), spread, lam, correlation
    )
    out["rows"] = rows = np.unique(groups // n_lev)
    r_inv = np.searchsorted(rows, groups // n_lev)
    out["w"] = w = np.zeros((rows.size, n_lev))
    d = np.zeros((rows.size, n_lev))
    d[r_inv, groups % n_lev] = centre
    w[r_inv, groups % n_lev] = weight
    expected = np.array([-lam, 0.0, lam])
    u = (d[:, :, None] - expected[None, None, :]) / (tolerance * lam)
    out["c3"] = np.minimum(u * u, 1.0) * w[:, :, None]
    return out


def _group_pairs(first: np.ndarray, second: np.ndarray, span: int) -> tuple[np.ndarray, ...]:
    """numbering_checks._group_pairs of rasterserver 0.x (its radix branch)."""
    order = np.argsort(second.astype(np.uint16), kind="stable")
    order = order[np.argsort(first[order].astype(np.uint16), kind="stable")]
    keys = first[order] * span + second[order]
    start = np.empty(keys.size, dtype=bool)
    start[:1] = True
    np.not_equal(keys[1:], keys[:-1], out=start[1:])
    inv = np.empty(keys.size, dtype=np.int64)
    inv[order] = np.cumsum(start) - 1
    return keys[start], inv


def _pair_contradictions(
    col: np.ndarray, area: np.ndarray, line_id: np.ndarray, line_number: np.ndarray, raster: Raster
) -> tuple[np.ndarray, ...]:
    """numbering_checks.pair_contradictions of rasterserver 0.x (default thresholds)."""
    lam, min_columns, min_z, min_departure, correlation = LAM, 5, 3.0, 0.75, 4.0
    empty = np.zeros(0, dtype=np.int64)
    if col.size < 2 or line_number.size == 0 or raster.n_lines < 2:
        return empty, empty, empty
    lid = line_id.astype(np.int64)
    lut = np.full(int(raster.numbers.max()) + 2, -1, dtype=np.int64)
    lut[raster.numbers] = np.arange(raster.n_lines)
    num = line_number.astype(np.int64)
    pos_line = np.where((num >= 0) & (num < lut.size - 1), lut[np.clip(num, 0, lut.size - 1)], -1)
    pos = np.append(pos_line, -1)[lid]
    a = np.flatnonzero((col[1:] == col[:-1]) & (pos[:-1] >= 0) & (pos[1:] == pos[:-1] + 1))
    if a.size == 0:
        return empty, empty, empty
    b = a + 1
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(area[a].astype(np.float64) / area[b].astype(np.float64))
    good = np.isfinite(lr)
    a, b, lr = a[good], b[good], np.clip(lr[good], -1.0, 1.0)
    if a.size == 0:
        return empty, empty, empty
    code = raster.code.astype(np.float64)
    expected = (code[pos[a]] - code[pos[b]]) * lam
    keys, inv = _group_pairs(lid[a], lid[b], int(lid.max()) + 1)
    _, centre, counts, spread = robust_centres(inv, lr)
    exp_pair = np.zeros(keys.size)
    exp_pair[inv] = expected
    se = np.maximum(1.25 * spread / np.sqrt(np.maximum(counts / correlation, 1.0)), 0.01)
    departure = np.abs(centre - exp_pair)
    bad = (counts >= min_columns) & (departure >= min_departure * lam) & (departure >= min_z * se)
    span = int(lid.max()) + 1
    return keys[bad] // span, keys[bad] % span, counts[bad]


# ---- frames


def _frame(seed: int) -> tuple[np.ndarray, ...]:
    """Components of lines over 300 columns, each line's area its kind's under noise and a
    few blocks numbered a level off; a few zero areas (ratios not finite), unlined peaks.
    Returns col, row, area, line_id, line_order, line_component, line_number."""
    rng = np.random.default_rng(seed)
    code = make_raster().code
    cols, rows, areas, lids = [], [], [], []
    orders, comps, numbers = [], [], []
    n_comp = 5
    offset = rng.integers(0, 50, n_comp)
    for line in range(80):
        comp, level = line % n_comp, line // n_comp
        true = int(offset[comp]) + level
        c_lo = int(rng.integers(0, 150))
        c = np.arange(c_lo, min(300, c_lo + int(rng.integers(3, 200))))
        c = c[rng.random(c.size) < 0.9]
        cols.append(c)
        rows.append(5.0 + 10.0 * true + 0.01 * c + rng.normal(0, 0.2, c.size))
        a = (1.5 if code[true] else 1.0) * (1.0 + 0.05 * rng.standard_normal(c.size))
        a[rng.random(c.size) < 0.01] = 0.0
        areas.append(a)
        lids.append(np.full(c.size, line))
        orders.append(level if rng.random() > 0.05 else -1)
        comps.append(comp if rng.random() > 0.05 else -1)
        wrong = int(rng.choice([0, 0, 0, 1, -1]))
        numbers.append(true + 1 + wrong if rng.random() > 0.1 else -1)
    c = rng.integers(0, 300, 200)
    cols.append(c)
    rows.append(rng.uniform(0, 800, c.size))
    areas.append(rng.uniform(0.5, 2.0, c.size))
    lids.append(np.full(c.size, -1))
    col = np.concatenate(cols).astype(np.int32)
    row = np.concatenate(rows)
    order = np.lexsort((row, col))
    return (
        col[order],
        row[order],
        np.concatenate(areas).astype(np.float32)[order],
        np.concatenate(lids).astype(np.int32)[order],
        np.array(orders, dtype=np.int32),
        np.array(comps, dtype=np.int32),
        np.array(numbers, dtype=np.int64),
    )


def _same(got: tuple | list, want: tuple | list) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert g.tobytes() == w.tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_level_statistics_same_bits(seed: int) -> None:
    col, _, area, lid, order, comp, _ = _frame(seed)
    want = _level_statistics(col, area, lid, order, comp)
    assert want[0].size > 10
    _same(level_statistics(col, area, lid, order, comp), want)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_code_bands_same_bits(seed: int) -> None:
    col, _, area, lid, order, comp, _ = _frame(seed)
    want = _bands(col, area, lid, order, comp)
    bands = CodeBands(
        col, area, lid, order, comp, lam=LAM, tolerance=0.5, min_columns=5, correlation=4.0
    )
    assert want["rows"].size > 10
    _same([getattr(bands, name) for name in want], list(want.values()))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_pair_contradictions_same_bits(seed: int) -> None:
    col, _, area, lid, _, _, number = _frame(seed)
    raster = make_raster()
    want = _pair_contradictions(col, area, lid, number, raster)
    assert want[0].size > 0
    _same(pair_contradictions(col, area, lid, number, raster, LAM), want)


def test_degenerate_frames() -> None:
    col, _, area, lid, order, comp, number = _frame(4)
    raster = make_raster()
    none = np.full(lid.size, -1, np.int32)
    cases = [
        (col[:0], area[:0], lid[:0], order, comp, number),  # no peaks
        (col[:1], area[:1], lid[:1], order, comp, number),  # one peak
        (col, area, none, order, comp, number),  # no peak on a line
        (col, area, lid, order, np.full(comp.size, -1, np.int32), np.full(number.size, -1)),
        (col, np.zeros_like(area), lid, order, comp, number),  # no finite ratio
    ]
    for c, a, i, o, m, n in cases:
        _same(level_statistics(c, a, i, o, m), _level_statistics(c, a, i, o, m))
        _same(
            pair_contradictions(c, a, i, n, raster, LAM), _pair_contradictions(c, a, i, n, raster)
        )
        bands = CodeBands(c, a, i, o, m, lam=LAM, tolerance=0.5, min_columns=5, correlation=4.0)
        want = _bands(c, a, i, o, m)
        _same([getattr(bands, name) for name in want], list(want.values()))


@pytest.mark.parametrize("span", [1, 7, 300, 70000])
def test_grouped_pairs_as_unique(span: int) -> None:
    rng = np.random.default_rng(span)
    for n in (0, 1, 5000):
        first = rng.integers(0, span, n)
        second = np.minimum(first + rng.integers(0, 3, n), span - 1)
        keys, inv = grouped_pairs(first, second, span)
        if span < 65536:
            _same((keys, inv), _group_pairs(first, second, span))
        _same((keys, inv), np.unique(first * span + second, return_inverse=True))
