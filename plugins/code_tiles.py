"""The code read in tiles of a numbered component: blocks of lines placed a level off.

Line sequence analysis links lines by their neighbourhoods in the image. Where a depth step
hides exactly one raster line over a stretch (the upper edge of a waistband, a fold), the
lines on either side look like consecutive ones, and a whole block (the cloth below the
waistband) is ordered one or two levels off, consistently, inside its component. The
component's code fit does not see it: its level differences mix, at the same levels, the
block's lines with correctly placed lines elsewhere in the image, and the rest outvote them.
The pair check sees only the pairs whose kinds happen to disagree at the wrong place.

So the code is read again in **tiles** of each numbered component: column bands
(``band`` columns wide, overlapping by half) times runs of ``2 * window`` levels
(overlapping by ``window``). A tile's level differences come from its own columns only;
every placement of them on the code is scored as the component's are
(:func:`.code_evidence.code_fit`). A tile *contradicts* its component when another
placement explains it better by the numbering's margin and either reads cleanly and
uniquely or the component's placement explains the tile poorly (the test of
:func:`.code_evidence.locally_contradicted`, in two dimensions). A line lying mostly in
contradicting tiles is left unnumbered: the evidence says it may be a level off, and a
wrong number is worse than none.
"""

from __future__ import annotations

import numpy as np

from .code_evidence import reliability, robust_centres

__all__ = ["contradicted_lines"]


def contradicted_lines(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
    offset: dict[int, int],
    code: np.ndarray,
    window: int,
    *,
    lam: float,
    tolerance: float,
    min_margin: float,
    max_cost_rate: float,
    min_columns: int,
    correlation: float,
    band: int = 64,
    min_share: float = 0.5,
) -> np.ndarray:
    """Lines of numbered components lying mostly in tiles whose code contradicts the
    component's placement.

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_order, line_component : numpy.ndarray
        Per-line level and component (-1: none).
    offset : dict
        Offset on the code (index of level 0) of every component; -1 when unnumbered.
    code : numpy.ndarray
        The raster's kinds (0 light, 1 heavy) in line order.
    window : int
        The raster's code window; tiles span ``2 * window`` levels.
    lam, tolerance, min_margin, max_cost_rate, min_columns, correlation : float
        As in :func:`.line_numbering.number_lines`.
    band : int
        Width (columns) of a tile; tiles overlap by half.
    min_share : float
        A line is refused when this share of its peaks (of those in a judged tile) lies in
        contradicting tiles.

    Returns
    -------
    numpy.ndarray
        ``(L,)`` bool, True for the lines to leave unnumbered.
    """
    n_lines = line_order.size
    refuse = np.zeros(n_lines, dtype=bool)
    off_of = np.full(int(line_component.max(initial=-1)) + 2, -1, dtype=np.int64)
    for c, off in offset.items():
        off_of[c] = off
    if col.size < 2 or n_lines == 0 or not np.any(off_of >= 0):
        return refuse
    lid = line_id.astype(np.int64)
    has = lid >= 0
    safe = np.maximum(lid, 0)
    comp = np.where(has, line_component[safe], -1).astype(np.int64)
    lev = np.where(has, line_order[safe], -1).astype(np.int64)
    numbered = (comp >= 0) & (lev >= 0) & (off_of[np.maximum(comp, 0)] >= 0)
    pair = (
        (col[1:] == col[:-1]) & (comp[1:] == comp[:-1]) & numbered[:-1] & (lev[1:] == lev[:-1] + 1)
    )
    k = np.flatnonzero(pair)
    if k.size == 0:
        return refuse
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(area[k].astype(np.float64) / area[k + 1].astype(np.float64))
    good = np.isfinite(lr)
    k, lr = k[good], lr[good]
    if k.size == 0:
        return refuse
    step = max(band // 2, 1)
    span = 2 * window - 1  # level differences per tile
    n_bands = int(col.max()) // step + 2
    n_wins = int(lev.max()) // window + 2
    p_comp, p_lev, p_band = comp[k], lev[k], col[k].astype(np.int64) // step
    # every difference belongs to two column bands and (at most) two level runs
    keys, ratios = [], []
    for db in (0, 1):
        for dw in (0, 1):
            b = p_band - db
            w = p_lev // window - dw
            j = p_lev - w * window
            ok = (b >= 0) & (w >= 0) & (j < span)
            tile = (p_comp[ok] * n_bands + b[ok]) * n_wins + w[ok]
            keys.append(tile * span + j[ok])
            ratios.append(lr[ok])
    key = np.concatenate(keys)
    groups, centre, count, spread = robust_centres(key, np.concatenate(ratios))
    weight = np.minimum(1.0, count / float(min_columns)) * reliability(
        count.astype(np.float64), spread, lam, correlation
    )
    tile_of, j_of = groups // span, groups % span
    tiles, t_inv = np.unique(tile_of, return_inverse=True)
    d = np.zeros((tiles.size, span))
    w = np.zeros((tiles.size, span))
    d[t_inv, j_of] = centre
    w[t_inv, j_of] = weight
    terms = w.sum(axis=1)
    # a tile with less than half a window of reliable differences cannot speak
    judged = terms >= 0.5 * (window - 1)
    if not np.any(judged):
        return refuse
    tiles, d, w, terms = tiles[judged], d[judged], w[judged], terms[judged]
    t_comp = tiles // (n_bands * n_wins)
    t_win = tiles % n_wins
    here = off_of[t_comp] + t_win * window
    # the cost of each difference against each of the three expected values, then summed
    # along every placement (placements running off the code's end: no constraint there)
    expected = np.array([-lam, 0.0, lam])
    u = (d[:, :, None] - expected[None, None, :]) / (tolerance * lam)
    c3 = np.minimum(u * u, 1.0) * w[:, :, None]  # (tiles, span, 3)
    c3 = np.concatenate([c3, np.zeros((tiles.size, span, 1))], axis=2)
    n_code = code.size
    diff_idx = np.full(n_code + span, 3, dtype=np.int64)
    diff_idx[: n_code - 1] = (code[:-1].astype(np.int64) - code[1:].astype(np.int64)) + 1
    place = np.arange(n_code)[:, None] + np.arange(span)[None, :]  # (offsets, span)
    idx = diff_idx[place]
    # cost[t, o] = sum_j c3[t, j, idx[o, j]]: one product with the placements' one-hot
    one_hot = np.zeros((span, 4, n_code))
    one_hot[np.arange(span)[None, :], idx, np.arange(n_code)[:, None]] = 1.0
    cost = c3.reshape(tiles.size, span * 4) @ one_hot.reshape(span * 4, n_code)
    # a placement must keep every measured difference on the code
    last = span - 1 - np.argmax((w > 0)[:, ::-1], axis=1)
    cost[np.arange(n_code)[None, :] > (n_code - 2 - last)[:, None]] = np.inf
    valid = (here >= 0) & (here <= n_code - 2 - last)
    rows = np.arange(tiles.size)
    c_here = np.where(valid, cost[rows, np.clip(here, 0, n_code - 1)], 0.0)
    part = np.partition(cost, 1, axis=1)
    best, second = part[:, 0], part[:, 1]
    excess = c_here - best
    clean = (best <= max_cost_rate * terms) & (second - best >= min_margin)
    poor = c_here > 2.0 * max_cost_rate * terms
    bad = valid & (excess >= min(min_margin, 3.0)) & (clean | poor)
    # peaks of numbered lines in judged tiles, and those in contradicting ones
    pk = np.flatnonzero(numbered)
    pc, pl, pb = comp[pk], lev[pk], col[pk].astype(np.int64) // step
    n_judged = np.zeros(pk.size, dtype=np.int64)
    n_bad = np.zeros(pk.size, dtype=np.int64)
    # 0: not judged, 1: judged, 2: contradicting; by tile key
    status = np.zeros(int(tiles.max()) + 1, dtype=np.int8)
    status[tiles] = 1
    status[tiles[bad]] = 2
    for db in (0, 1):
        for dw in (0, 1):
            b = pb - db
            win = pl // window - dw
            ok = (b >= 0) & (win >= 0) & (pl - win * window <= span)
            tile = (pc * n_bands + b) * n_wins + win
            st = np.where(ok, status[np.clip(tile, 0, status.size - 1)], 0)
            st[ok & (tile >= status.size)] = 0
            n_judged += st >= 1
            n_bad += st == 2
    # a peak is contradicted when any judged tile holding it is: the tiles overlap by
    # half, so the block's edges lie in mixed tiles that may read as neither placement
    hit = n_bad > 0
    seen = n_judged > 0
    n_seen = np.bincount(lid[pk[seen]], minlength=n_lines)
    n_hit = np.bincount(lid[pk[hit]], minlength=n_lines)
    refuse = (n_hit > 0) & (n_hit >= min_share * np.maximum(n_seen, 1))
    return refuse
