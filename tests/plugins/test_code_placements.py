"""The compiled code fit and level kinds against the passes they replaced: the same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.code_evidence import CodeFit, code_fit, observed_kinds
from rasterserver_plugins.code_placements import best_two

from rasterserver.raster import make_raster

LAM = float(np.log(1.5))


def _costs(
    n_levels: int, d: np.ndarray, weight: np.ndarray, code: np.ndarray, tolerance: float = 0.5
) -> tuple[np.ndarray, float, int, int, float]:
    """The numbers of code_evidence.code_fit of rasterserver 0.x: cost, terms, measured
    count, best and margin."""
    n_off = code.size - n_levels + 1
    measured = (~np.isnan(d)) & (weight > 0)
    terms = float(weight[measured].sum())
    if n_levels >= 2:
        windows = np.lib.stride_tricks.sliding_window_view(code.astype(np.float64), n_levels)
        expected = (windows[:, :-1] - windows[:, 1:]) * LAM
        u = (np.where(measured, d, 0.0)[None, :] - expected) / (tolerance * LAM)
        cost = (np.minimum(u * u, 1.0) * np.where(measured, weight, 0.0)[None, :]).sum(axis=1)
    else:
        cost = np.zeros(n_off)
    order = np.argsort(cost, kind="stable")
    best = int(order[0])
    margin = float(cost[order[1]] - float(cost[best])) if n_off > 1 else float("inf")
    return cost, terms, int(measured.sum()), best, margin


def _kinds(d: np.ndarray, weight: np.ndarray, tolerance: float = 0.5) -> np.ndarray:
    """code_evidence.observed_kinds of rasterserver 0.x."""
    n = d.size + 1
    kinds = np.full(n, -1, dtype=np.int8)
    if n < 2:
        return kinds
    measured = ~np.isnan(d)
    dd = np.where(measured, d, 0.0)
    ww = np.where(measured, weight, 0.0)
    expect = np.array([[0.0, -1.0], [1.0, 0.0]]) * LAM
    u = (dd[:, None, None] - expect[None, :, :]) / (tolerance * LAM)
    cost = np.minimum(u * u, 1.0) * ww[:, None, None]
    c = cost.reshape(n - 1, 4).tolist()
    f0, f1 = 0.0, 0.0
    fwd = [(0.0, 0.0)]
    for c00, c01, c10, c11 in c:
        f0, f1 = min(f0 + c00, f1 + c10), min(f0 + c01, f1 + c11)
        fwd.append((f0, f1))
    b0, b1 = 0.0, 0.0
    bwd = [(0.0, 0.0)]
    for c00, c01, c10, c11 in reversed(c):
        b0, b1 = min(c00 + b0, c01 + b1), min(c10 + b0, c11 + b1)
        bwd.append((b0, b1))
    total = np.array(fwd) + np.array(bwd[::-1])
    gap = total[:, 0] - total[:, 1]
    seen = np.zeros(n, dtype=bool)
    seen[:-1] |= measured
    seen[1:] |= measured
    sure = seen & (np.abs(gap) >= 0.5)
    kinds[sure] = (gap[sure] > 0).astype(np.int8)
    return kinds


def _component(seed: int, n_levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Differences of a component at a random offset, noisy, some misread or unmeasured."""
    rng = np.random.default_rng(seed)
    code = make_raster().code.astype(np.float64)
    off = int(rng.integers(0, code.size - n_levels + 1))
    d = (code[off : off + n_levels - 1] - code[off + 1 : off + n_levels]) * LAM
    d = d + rng.normal(0, 0.1, d.size)
    d[rng.random(d.size) < 0.1] = rng.normal(0, 0.5)
    d[rng.random(d.size) < 0.1] = np.nan
    w = rng.uniform(0.0, 1.0, d.size)
    w[rng.random(d.size) < 0.1] = 0.0
    return d, w


def _fit(n_levels: int, d: np.ndarray, w: np.ndarray, code: np.ndarray) -> CodeFit:
    return code_fit(
        n_levels,
        d,
        w,
        code,
        lam=LAM,
        tolerance=0.5,
        min_lines=9,
        min_margin=2.0,
        max_cost_rate=0.25,
    )


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("n_levels", [1, 2, 5, 9, 17, 40, 90])
def test_same_fit(seed: int, n_levels: int) -> None:
    code = make_raster().code
    d, w = _component(seed, n_levels)
    cost, terms, _, best, margin = _costs(n_levels, d, w, code)
    fit = _fit(n_levels, d, w, code)
    assert fit.cost.dtype == cost.dtype and fit.cost.tobytes() == cost.tobytes()
    assert np.float64(fit.terms).tobytes() == np.float64(terms).tobytes()
    assert (fit.best, type(fit.best)) == (best, int)
    assert np.float64(fit.margin).tobytes() == np.float64(margin).tobytes()


def test_tied_costs_and_their_order() -> None:
    code = make_raster().code
    # exact differences at full weight: whole-number costs, many placements tied
    exact = (code[10:29].astype(np.float64) - code[11:30]) * LAM
    for d in (exact, np.full(exact.size, 5.0), np.full(exact.size, np.nan)):
        w = np.ones(d.size)
        cost, terms, _, best, margin = _costs(d.size + 1, d, w, code)
        fit = _fit(d.size + 1, d, w, code)
        assert fit.cost.tobytes() == cost.tobytes() and fit.best == best
        assert fit.margin == margin and fit.terms == terms
    rng = np.random.default_rng(0)
    for values in (rng.integers(0, 4, 30).astype(np.float64), np.array([np.nan, 1.0, np.nan])):
        order = np.argsort(values, kind="stable")
        assert best_two(values) == (int(order[0]), int(order[1]))
    assert best_two(np.array([3.0])) == (0, -1)


@pytest.mark.parametrize("seed", range(6))
def test_same_kinds(seed: int) -> None:
    for n_levels in (2, 3, 10, 60):
        d, w = _component(seed, n_levels)
        for tolerance in (0.5, 0.3):
            want = _kinds(d, w, tolerance)
            got = observed_kinds(d, w, LAM, tolerance)
            assert got.dtype == want.dtype and np.array_equal(got, want)
    assert observed_kinds(np.zeros(0), np.zeros(0), LAM, 0.5).tolist() == [-1]
    code = make_raster().code.astype(np.float64)
    exact = (code[:30] - code[1:31]) * LAM  # ties between the kinds where nothing is read
    w = np.where(np.arange(30) % 7 == 0, 0.0, 1.0)
    assert np.array_equal(observed_kinds(exact, w, LAM, 0.5), _kinds(exact, w))
