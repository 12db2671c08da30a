"""The compiled grid interpolation against the whole-array passes it replaced: same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.smoothing import grid_from_lines

from rasterserver.records_surface import Points

# ---- the whole-array passes of rasterserver 0.x (plugins/smoothing.py before numba)


def _grid_frame(x: np.ndarray, y: np.ndarray, spacing: float) -> tuple[float, float, int, int]:
    x0 = float(np.floor(x.min() / spacing) * spacing)
    y0 = float(np.floor(y.min() / spacing) * spacing)
    nx = int(np.floor((x.max() - x0) / spacing)) + 1
    ny = int(np.floor((y.max() - y0) / spacing)) + 1
    return x0, y0, nx, ny


def _three_point_slope(
    d_prev: np.ndarray, s_prev: np.ndarray, d_next: np.ndarray, s_next: np.ndarray
) -> np.ndarray:
    """Derivative at a node from the secant slopes on both sides (exact for parabolas)."""
    return (d_prev * s_next + d_next * s_prev) / (d_prev + d_next)


def _hermite(
    t: np.ndarray, h: np.ndarray, f0: np.ndarray, f1: np.ndarray, m0: np.ndarray, m1: np.ndarray
) -> np.ndarray:
    """Cubic Hermite interpolation on ``[0, 1]`` of an interval of length ``h``."""
    t2 = t * t
    t3 = t2 * t
    return (
        (2 * t3 - 3 * t2 + 1) * f0
        + (t3 - 2 * t2 + t) * h * m0
        + (-2 * t3 + 3 * t2) * f1
        + (t3 - t2) * h * m1
    )


def _interval_slopes(
    x: np.ndarray, f: np.ndarray, has_prev: np.ndarray, has_next: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slopes at both ends of the interval between nodes 1 and 2 of ``(4, K)`` nodes.

    Each end takes the slope of the parabola through it and its two neighbours (exact for
    parabolas); where node 0 or 3 is missing, the parabola through the three nodes that are
    there is used, and with only nodes 1 and 2 the secant (linear).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        h0, h1, h2 = x[1] - x[0], x[2] - x[1], x[3] - x[2]
        s0, s1, s2 = (f[1] - f[0]) / h0, (f[2] - f[1]) / h1, (f[3] - f[2]) / h2
        centred_1 = _three_point_slope(h0, s0, h1, s1)
        centred_2 = _three_point_slope(h1, s1, h2, s2)
        forward_1 = s1 - (s2 - s1) * h1 / (h1 + h2)  # parabola through 1, 2, 3 at node 1
        backward_2 = s1 + (s1 - s0) * h1 / (h0 + h1)  # parabola through 0, 1, 2 at node 2
    m1 = np.where(has_prev, centred_1, np.where(has_next, forward_1, s1))
    m2 = np.where(has_next, centred_2, np.where(has_prev, backward_2, s1))
    return m1, m2


def _grid_passes(
    samples: Points,
    *,
    spacing: float,
    max_gap: float,
    max_line_step: int = 1,
    max_line_distance: float = 25.0,
    cubic: bool = True,
) -> tuple[float, float, np.ndarray]:
    """smoothing.grid_from_lines of rasterserver 0.x, whole-array passes."""
    x0, y0, nx, ny = _grid_frame(samples.x, samples.y, spacing)
    z = np.full((ny, nx), np.nan)
    lines, rank = np.unique(samples.number, return_inverse=True)
    n_lines = lines.size
    line_y, line_z = _along_lines(samples, rank, n_lines, x0, nx, spacing, max_gap, cubic)
    valid = np.isfinite(line_y)
    if n_lines < 2:
        return x0, y0, z
    # next / previous valid line of each (line, column): running min / max of valid ranks
    ranks = np.arange(n_lines)[:, None]
    nxt = np.minimum.accumulate(np.where(valid, ranks, n_lines)[::-1], axis=0)[::-1]
    nxt = np.vstack([nxt[1:], np.full((1, nx), n_lines)])
    prv = np.maximum.accumulate(np.where(valid, ranks, -1), axis=0)
    prv = np.vstack([np.full((1, nx), -1), prv[:-1]])

    def linked(r0: np.ndarray, r1: np.ndarray, col: np.ndarray) -> np.ndarray:
        ok = (r0 >= 0) & (r1 < n_lines)
        a, b = np.clip(r0, 0, n_lines - 1), np.clip(r1, 0, n_lines - 1)
        dy = line_y[b, col] - line_y[a, col]
        dz = line_z[b, col] - line_z[a, col]
        near = dy * dy + dz * dz <= max_line_distance**2
        return ok & (lines[b] - lines[a] <= max_line_step) & (dy > 0) & near

    r_a, col = np.nonzero(valid & (nxt < n_lines))
    r_b = nxt[r_a, col]
    pair = linked(r_a, r_b, col)
    r_a, r_b, col = r_a[pair], r_b[pair], col[pair]
    ya, yb = line_y[r_a, col], line_y[r_b, col]
    i_lo = np.ceil((ya - y0) / spacing).astype(np.int64)
    i_hi = np.ceil((yb - y0) / spacing).astype(np.int64)
    count = np.maximum(i_hi - i_lo, 0)
    rep = np.repeat(np.arange(count.size), count)
    i = i_lo[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(count) - count, count))
    inside = (i >= 0) & (i < ny)
    rep, i = rep[inside], i[inside]
    h = yb - ya
    t = (y0 + i * spacing - ya[rep]) / h[rep]
    za, zb = line_z[r_a, col], line_z[r_b, col]
    if not cubic:
        z[i, col[rep]] = za[rep] + t * (zb[rep] - za[rep])
        return x0, y0, z
    r_p = prv[r_a, col]
    r_n = nxt[r_b, col]
    has_p = linked(r_p, r_a, col)
    has_n = linked(r_b, r_n, col)
    r_p, r_n = np.clip(r_p, 0, n_lines - 1), np.clip(r_n, 0, n_lines - 1)
    yy = np.stack([line_y[r_p, col], ya, yb, line_y[r_n, col]])
    zz = np.stack([line_z[r_p, col], za, zb, line_z[r_n, col]])
    m_a, m_b = _interval_slopes(yy, zz, has_p, has_n)
    z[i, col[rep]] = _hermite(t, h[rep], za[rep], zb[rep], m_a[rep], m_b[rep])
    return x0, y0, z


def _along_lines(
    samples: Points,
    rank: np.ndarray,
    n_lines: int,
    x0: float,
    nx: int,
    spacing: float,
    max_gap: float,
    cubic: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``y`` and ``z`` of every line at every grid column, ``(n_lines, nx)``, NaN where absent."""
    # one sorted key for all lines: rank * span + x keeps lines apart and x ascending inside
    span = (nx + 2) * spacing
    xs = samples.x - x0 + spacing
    key = rank * span + xs
    order = np.argsort(key, kind="stable")
    key, xs = key[order], xs[order]
    ys, zs, rk = samples.y[order], samples.z[order], rank[order]
    n = key.size
    xg = np.tile((np.arange(nx) + 1.0) * spacing, n_lines)
    q_rank = np.repeat(np.arange(n_lines), nx)
    hi = np.searchsorted(key, q_rank * span + xg, side="left")
    lo = hi - 1
    hi_c, lo_c = np.minimum(hi, n - 1), np.maximum(lo, 0)
    on_hi = (hi < n) & (rk[hi_c] == q_rank)
    exact = on_hi & (xs[hi_c] == xg)
    dx = xs[hi_c] - xs[lo_c]

    def close(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = (xs[a] - xs[b]) ** 2 + (ys[a] - ys[b]) ** 2 + (zs[a] - zs[b]) ** 2
        return d2 <= max_gap**2

    ok = on_hi & (lo >= 0) & (rk[lo_c] == q_rank) & close(lo_c, hi_c)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(dx > 0, (xg - xs[lo_c]) / dx, 0.0)
    if cubic:
        lp, hn = np.maximum(lo - 1, 0), np.minimum(hi + 1, n - 1)
        has_p = (lo >= 1) & (rk[lp] == q_rank) & close(lp, lo_c) & (xs[lo_c] > xs[lp])
        has_n = (hi + 1 < n) & (rk[hn] == q_rank) & close(hn, hi_c) & (xs[hn] > xs[hi_c])
        xx = np.stack([xs[lp], xs[lo_c], xs[hi_c], xs[hn]])
        out = []
        for f in (ys, zs):
            ff = np.stack([f[lp], f[lo_c], f[hi_c], f[hn]])
            m0, m1 = _interval_slopes(xx, ff, has_p, has_n)
            out.append(_hermite(t, dx, ff[1], ff[2], m0, m1))
        line_y, line_z = out
    else:
        line_y = ys[lo_c] + t * (ys[hi_c] - ys[lo_c])
        line_z = zs[lo_c] + t * (zs[hi_c] - zs[lo_c])
    line_y = np.where(exact, ys[hi_c], line_y)
    line_z = np.where(exact, zs[hi_c], line_z)
    valid = (ok | exact).reshape(n_lines, nx)
    return (
        np.where(valid, line_y.reshape(n_lines, nx), np.nan),
        np.where(valid, line_z.reshape(n_lines, nx), np.nan),
    )


# ---- the comparison


def _samples(seed: int, *, fold: bool) -> Points:
    """Lines across a curved surface, with gaps, missing lines, a step, and optionally a fold
    (a line whose y goes back over its neighbour's: grid nodes claimed by two pairs)."""
    rng = np.random.default_rng(seed)
    xs, ys, zs, numbers = [], [], [], []
    for k, number in enumerate(range(10, 40)):
        if rng.random() < 0.1:
            continue  # a line not found
        x = np.sort(rng.uniform(-150, 150, rng.integers(40, 120)))
        x = x[(x < -40) | (x > -20)] if k % 5 == 0 else x  # a gap wider than max_gap
        y = -200 + 10.0 * k + 0.02 * x + rng.normal(0, 0.05, x.size)
        if fold and k == 12:
            y = y - 14.0  # below the previous line: a fold
        z = 0.002 * x**2 + 0.001 * y**2 + (30.0 if k > 22 else 0.0)  # a depth step
        xs.append(x)
        ys.append(y)
        zs.append(z)
        numbers.append(np.full(x.size, number))
    x, y, z = np.concatenate(xs), np.concatenate(ys), np.concatenate(zs)
    n = x.size
    return Points(
        x=x,
        y=y,
        z=z,
        number=np.concatenate(numbers).astype(np.int32),
        col=np.zeros(n, np.int32),
        row=np.zeros(n),
        area=np.ones(n, np.float32),
        image_shape=np.asarray((576, 604), dtype=np.int64),
        reason="",
    )


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("fold", [False, True])
@pytest.mark.parametrize("cubic", [True, False])
def test_same_bits_as_the_passes(seed: int, fold: bool, cubic: bool) -> None:
    samples = _samples(seed, fold=fold)
    kw = {"spacing": 3.0, "max_gap": 9.0, "max_line_step": 1, "max_line_distance": 25.0}
    got = grid_from_lines(samples, cubic=cubic, **kw)
    want = _grid_passes(samples, cubic=cubic, **kw)
    assert got[:2] == want[:2]
    np.testing.assert_array_equal(got[2], want[2])  # NaN where NaN, every other bit equal
    assert np.isfinite(got[2]).sum() > 1000


def test_one_line_gives_no_grid() -> None:
    samples = _samples(3, fold=False)
    one = samples.number == samples.number[0]
    single = Points(
        **{f: getattr(samples, f)[one] for f in ("x", "y", "z", "number", "col", "row", "area")},
        image_shape=samples.image_shape,
        reason="",
    )
    _, _, z = grid_from_lines(single, spacing=3.0, max_gap=9.0)
    assert np.isnan(z).all()
