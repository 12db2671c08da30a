"""The compiled runs of levels against the whole-array passes they replaced: the same levels."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.code_evidence import locally_contradicted

from rasterserver.raster import make_raster

LAM = float(np.log(1.5))


def _passes(
    d: np.ndarray,
    w: np.ndarray,
    code: np.ndarray,
    offset: int,
    span: int,
    lam: float,
    tolerance: float,
    min_margin: float,
    max_cost_rate: float,
    poor_factor: float = 2.0,
) -> np.ndarray:
    """code_evidence.locally_contradicted of rasterserver 0.x (``poor_factor`` 2 then)."""
    n_levels = d.size + 1
    if n_levels < span + 2:
        return np.zeros(0, dtype=np.int64)
    bad = np.zeros(n_levels, dtype=bool)
    windows = np.lib.stride_tricks.sliding_window_view(code.astype(np.float64), span)
    expected = (windows[:, :-1] - windows[:, 1:]) * lam
    for start in range(0, n_levels - span + 1, 2):
        dd = d[start : start + span - 1]
        ww = w[start : start + span - 1]
        measured = ~np.isnan(dd) & (ww > 0)
        terms = float(ww[measured].sum())
        if terms < 0.5 * (span - 1):
            continue
        u = (np.where(measured, dd, 0.0)[None, :] - expected) / (tolerance * lam)
        cost = (np.minimum(u * u, 1.0) * np.where(measured, ww, 0.0)[None, :]).sum(axis=1)
        here = offset + start
        if not 0 <= here < cost.size:
            continue
        order = np.argsort(cost, kind="stable")
        best = int(order[0])
        if best == here:
            continue
        excess = float(cost[here] - cost[best])
        local_margin = float(cost[order[1]] - cost[best])
        clean_elsewhere = cost[best] <= max_cost_rate * terms and local_margin >= min_margin
        poorly_explained = poor_factor > 0 and cost[here] > poor_factor * max_cost_rate * terms
        if excess >= min_margin and (clean_elsewhere or poorly_explained):
            bad[start : start + span] = True
    return np.flatnonzero(bad)


def _component(seed: int, n_levels: int = 50) -> tuple[np.ndarray, np.ndarray, int]:
    """Level differences of a component placed at offset 20 whose levels 14..35 read as the
    code some levels on (a block line sequence put off), under noise; some unmeasured."""
    rng = np.random.default_rng(seed)
    code = make_raster().code.astype(np.float64)
    place = np.full(n_levels - 1, 20) + np.arange(n_levels - 1)
    place[14:36] += int(rng.choice([-3, -1, 1, 2]))
    d = (code[place] - code[place + 1]) * LAM + rng.normal(0, 0.08, n_levels - 1)
    w = rng.uniform(0.2, 1.0, n_levels - 1)
    w[rng.random(n_levels - 1) < 0.1] = 0.0
    d[rng.random(n_levels - 1) < 0.1] = np.nan
    return d, w, 20


@pytest.mark.parametrize("seed", range(6))
def test_same_levels_as_the_passes(seed: int) -> None:
    code = make_raster().code
    d, w, offset = _component(seed)
    found = 0
    for span, margin, rate in ((18, 2.0, 0.25), (14, 4.0, 0.25), (18, 1.0, 0.1)):
        args = (d, w, code, offset, span, LAM, 0.5, margin, rate)
        want = _passes(*args)
        got = locally_contradicted(*args)
        assert got.dtype == want.dtype and np.array_equal(got, want)
        found += want.size
    assert found > 0  # runs refused: the comparison is not of empty sets only


@pytest.mark.parametrize("seed", range(3))
def test_tied_costs(seed: int) -> None:
    """Exact differences at full weight: every cost a whole number, many placements tied
    (the stable order decides the best two)."""
    code = make_raster().code
    d, w, offset = _component(seed)
    place = np.full(d.size, offset) + np.arange(d.size)
    place[14:36] += 2
    exact = (code[place].astype(np.float64) - code[place + 1]) * LAM
    for span, margin in ((18, 2.0), (10, 1.0), (6, 1.0)):
        args = (exact, np.ones_like(w), code, offset, span, LAM, 0.5, margin, 0.25)
        assert np.array_equal(locally_contradicted(*args), _passes(*args))


def test_few_levels_and_edges() -> None:
    code = make_raster().code
    d, w, _ = _component(9)
    cases = [
        (d[:10], w[:10], 20, 18),  # fewer levels than a run
        (d[:19], w[:19], 20, 18),  # one run
        (d, np.zeros_like(w), 20, 18),  # nothing measured
        (d, w, 80, 18),  # runs placed past the code's end
        (d, w, -5, 18),
        (np.full(d.size, np.nan), w, 20, 18),
    ]
    for dd, ww, offset, span in cases:
        args = (dd, ww, code, offset, span, LAM, 0.5, 2.0, 0.25)
        assert np.array_equal(locally_contradicted(*args), _passes(*args))


def test_poorly_explained_runs_only_with_a_factor() -> None:
    """A block whose differences scatter (shading, a dim code) is explained poorly by the
    component's placement and cleanly by none: refused with ``poor_factor`` 2 (numbering
    version 17), kept with 0 (version 18), where the runs another placement reads cleanly
    are refused either way."""
    code = make_raster().code
    rng = np.random.default_rng(4)
    differing = 0
    for seed in range(12):
        d, w, offset = _component(seed)
        noisy = d.copy()
        noisy[2:12] += rng.normal(0, 0.5, 10)  # a scattered block the code reads nowhere
        for dd in (d, noisy):
            args = (dd, w, code, offset, 14, LAM, 0.5, 2.0, 0.25)
            with_poor = locally_contradicted(*args, 2.0)
            clean_only = locally_contradicted(*args, 0.0)
            assert np.array_equal(with_poor, _passes(*args, 2.0))
            assert np.array_equal(clean_only, _passes(*args, 0.0))
            assert set(clean_only) <= set(with_poor)
            differing += clean_only.size < with_poor.size
    assert differing > 0
