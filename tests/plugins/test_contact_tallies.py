"""The compiled contacts of contact_votes against the whole-array passes they replaced."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
from rasterserver_plugins.numbering_checks import by_line, contact_votes


def _line_ends(
    col: np.ndarray, row: np.ndarray, line_id: np.ndarray, n_lines: int, fit: int
) -> tuple[np.ndarray, ...]:
    """numbering_checks._line_ends of rasterserver 0.x."""
    lid = line_id.astype(np.int64)
    ok = lid >= 0
    idx = np.flatnonzero(ok)
    order = idx[by_line(lid[idx])]
    lines = lid[order]
    starts = np.searchsorted(lines, np.arange(n_lines), side="left")
    stops = np.searchsorted(lines, np.arange(n_lines), side="right")
    count = stops - starts
    c0 = np.full(n_lines, -1, np.int64)
    c1 = np.full(n_lines, -1, np.int64)
    r0 = np.full(n_lines, np.nan)
    r1 = np.full(n_lines, np.nan)
    s0 = np.zeros(n_lines)
    s1 = np.zeros(n_lines)
    cs, rs = col[order].astype(np.float64), row[order]
    has = np.flatnonzero(count > 0)
    a, b = starts[has], stops[has]
    c0[has], c1[has] = cs[a].astype(np.int64), cs[b - 1].astype(np.int64)
    r0[has], r1[has] = rs[a], rs[b - 1]
    m = np.minimum(fit, b - a)
    ok = m >= 3
    if np.any(ok):
        lines, a, b, m = has[ok], a[ok], b[ok], m[ok]
        for first, out in ((a, s0), (b - m, s1)):
            k = np.arange(fit)[None, :]
            inside = k < m[:, None]
            idx = np.where(inside, first[:, None] + k, first[:, None])
            x, y = cs[idx], rs[idx]
            w = inside.astype(np.float64)
            xm = (x * w).sum(axis=1) / m
            ym = (y * w).sum(axis=1) / m
            dx = (x - xm[:, None]) * w
            den = (dx * dx).sum(axis=1)
            num = (dx * (y - ym[:, None])).sum(axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                out[lines] = np.where(den > 0, num / den, 0.0)
    return c0, c1, r0, r1, s0, s1, count


def _passes(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
) -> dict[tuple[int, int], dict[int, float]]:
    """numbering_checks.contact_votes of rasterserver 0.x (default parameters)."""
    gap_tolerance, max_gap, row_tolerance, min_line, continuation_weight = 0.2, 40, 0.3, 5, 4.0
    votes: dict[tuple[int, int], dict[int, float]] = defaultdict(lambda: defaultdict(float))
    n = col.size
    n_lines = line_order.size
    if n < 2 or n_lines < 2:
        return votes
    lid = line_id.astype(np.int64)
    comp = np.where(lid >= 0, line_component[np.maximum(lid, 0)], -1).astype(np.int64)
    lev = np.where(lid >= 0, line_order[np.maximum(lid, 0)], -1).astype(np.int64)
    same_col = col[1:] == col[:-1]
    gap = row[1:] - row[:-1]
    inside = same_col & (comp[1:] == comp[:-1]) & (comp[:-1] >= 0) & (lev[1:] == lev[:-1] + 1)
    spacing = float(np.median(gap[inside])) if np.any(inside) else float("nan")
    if not np.isfinite(spacing) or spacing <= 0:
        return votes
    g_prev = np.full(n - 1, np.nan)
    g_prev[1:] = np.where(same_col[:-1] & inside[:-1], gap[:-1], np.nan)
    g_next = np.full(n - 1, np.nan)
    g_next[:-1] = np.where(same_col[1:] & inside[1:], gap[1:], np.nan)
    with np.errstate(invalid="ignore"):
        ref = np.where(
            np.isnan(g_prev),
            np.where(np.isnan(g_next), spacing, g_next),
            np.where(np.isnan(g_next), g_prev, 0.5 * (g_prev + g_next)),
        )
    cross = same_col & (comp[:-1] >= 0) & (comp[1:] >= 0) & (comp[:-1] != comp[1:])
    cross &= np.abs(gap / ref - 1.0) <= gap_tolerance
    cross &= np.abs(ref / spacing - 1.0) <= 0.5
    k = np.flatnonzero(cross)
    if k.size:
        comp_a, comp_b = comp[k], comp[k + 1]
        deltas = lev[k] + 1 - lev[k + 1]
        n_comp = int(comp.max()) + 1
        d0 = int(deltas.min())
        span = int(deltas.max()) - d0 + 1
        key = (comp_a * n_comp + comp_b) * span + (deltas - d0)
        groups, first, count = np.unique(key, return_index=True, return_counts=True)
        for i in np.argsort(first, kind="stable"):
            g = int(groups[i])
            d = g % span + d0
            a, b = divmod(g // span, n_comp)
            votes[(a, b)][d] += float(count[i])
            votes[(b, a)][-d] += float(count[i])
    c0, c1, r0, r1, s0, s1, count = _line_ends(col, row, line_id, n_lines, fit=8)
    ok = (count >= min_line) & (line_component >= 0) & (line_order >= 0)
    ends = np.flatnonzero(ok)
    if ends.size < 2:
        return votes
    tol = row_tolerance * spacing
    e_c0, e_r0, e_s0 = c0[ends], r0[ends], s0[ends]
    e_comp = line_component[ends]
    pairs: list[tuple[int, int]] = []
    for lo in range(0, ends.size, 256):
        a_ = ends[lo : lo + 256]
        dc = e_c0[None, :] - c1[a_][:, None]
        cand = (dc >= 1) & (dc <= max_gap) & (e_comp[None, :] != line_component[a_][:, None])
        dcc = dc.astype(np.float64)
        fwd = r1[a_][:, None] + s1[a_][:, None] * dcc
        bwd = e_r0[None, :] - e_s0[None, :] * dcc
        hit = cand & (np.abs(fwd - e_r0[None, :]) <= tol) & (np.abs(bwd - r1[a_][:, None]) <= tol)
        one = np.flatnonzero(hit.sum(axis=1) == 1)
        pairs.extend(zip(a_[one].tolist(), ends[np.argmax(hit[one], axis=1)].tolist(), strict=True))
    for a, b in pairs:
        ca, cb = int(line_component[a]), int(line_component[b])
        delta = int(line_order[a] - line_order[b])
        w = continuation_weight * min(1.0, min(count[a], count[b]) / 20.0)
        votes[(ca, cb)][delta] += w
        votes[(cb, ca)][-delta] += w
    return votes


def _frame(seed: int) -> tuple[np.ndarray, ...]:
    """Pieces of lines of several components over 400 columns: components meeting in a
    column a level or two off, lines interrupted and continued by another component,
    unlined and unordered peaks, and rows with fractions (the slopes' sums' order shows)."""
    rng = np.random.default_rng(seed)
    cols, rows, lids = [], [], []
    orders, comps = [], []
    n_comp = 6
    shift = rng.integers(-2, 3, n_comp)
    for line in range(90):
        comp = int(rng.integers(0, n_comp))
        level = int(rng.integers(0, 30))
        c_lo = int(rng.integers(0, 360))
        c = np.arange(c_lo, min(400, c_lo + int(rng.integers(2, 120))))
        c = c[rng.random(c.size) < 0.9]
        r = 7.3 + 9.7 * (level + shift[comp]) + 0.013 * c + rng.normal(0, 0.25, c.size)
        cols.append(c)
        rows.append(r)
        lids.append(np.full(c.size, line))
        orders.append(level if rng.random() > 0.05 else -1)
        comps.append(comp if rng.random() > 0.05 else -1)
    c = rng.integers(0, 400, 300)  # peaks outside the lines
    cols.append(c)
    rows.append(rng.uniform(0, 300, c.size))
    lids.append(np.full(c.size, -1))
    col = np.concatenate(cols).astype(np.int32)
    row = np.concatenate(rows)
    lid = np.concatenate(lids).astype(np.int32)
    order = np.lexsort((row, col))
    return (
        col[order],
        row[order],
        lid[order],
        np.array(orders, dtype=np.int32),
        np.array(comps, dtype=np.int32),
    )


def _same(got: dict, want: dict) -> None:
    """The same votes, entered in the same order, as the same bits."""
    assert list(got) == list(want)
    for key in want:
        assert list(got[key].items()) == list(want[key].items())
        for d in want[key]:
            assert np.float64(got[key][d]).tobytes() == np.float64(want[key][d]).tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_same_votes_as_the_whole_array_passes(seed: int) -> None:
    frame = _frame(seed)
    want = _passes(*frame)
    assert sum(len(v) for v in want.values()) > 4  # contacts of both kinds to compare
    _same(contact_votes(*frame), want)


def test_same_line_ends() -> None:
    from rasterserver_plugins.contact_tallies import line_ends

    col, row, lid, order, _ = _frame(7)
    want = _line_ends(col, row, lid, order.size, 8)
    got = line_ends(col, row, lid, order.size, 8)
    for g, w in zip(got, want, strict=True):
        assert g.tobytes() == w.tobytes()


def test_degenerate_frames() -> None:
    col, row, lid, order, comp = _frame(5)
    empty_i, empty_f = np.zeros(0, np.int32), np.zeros(0)
    cases = [
        (empty_i, empty_f, empty_i, order, comp),  # no peaks
        (col[:1], row[:1], lid[:1], order, comp),  # one peak
        (col, row, lid, order[:1], comp[:1] * 0),  # one line
        (col, row, np.full(col.size, -1, np.int32), order, comp),  # no peak on a line
        (col, row, lid, order, np.full(comp.size, -1, np.int32)),  # no component
        (np.arange(col.size, dtype=np.int32), row, lid, order, comp),  # one peak a column
    ]
    for case in cases:
        _same(contact_votes(*case), _passes(*case))
