"""The code read in column bands of a numbered component: blocks of lines placed levels off.

Line sequence analysis links lines by their neighbourhoods in the image. Where a depth step
hides one or more raster lines over a stretch (the upper edge of a waistband, a fold), or
the light lines of a dark cloth are too dim to be found, the lines on either side look like
consecutive ones, and a whole block (the cloth below the waistband) is ordered one or more
levels off, consistently, inside its component. The component's code fit does not see it:
its level differences mix, at the same levels, the block's lines with correctly placed
lines elsewhere in the image, and the rest outvote them. The pair check sees only the pairs
whose kinds happen to disagree at the wrong place.

So the code is read again in **column bands** of each numbered component (``band`` columns
wide, overlapping by half): each band's level differences come from its own columns only.
Along the levels of a band, the cost of every difference at the component's placement is
compared with its cost at every other placement (``shift`` levels on); the run of levels
where another placement gains most (a maximum-sum run) is a block the code places
elsewhere. A band *contradicts* its component on that run when the gain reaches
``min_gain`` (more than one misread line can cost: a misread line costs two differences)
and the other placement explains the run cleanly (at most ``max_cost_rate`` of it bad). A
line lying mostly in contradicted runs is left unnumbered: the evidence says it may be
levels off, and a wrong number is worse than none.

The thresholds were set on the tuning scenes of ``benchmarks/real_bodies.py`` (seeds
7000-7599); see BENCHMARKS.md, "Real bodies".
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
    *,
    lam: float,
    tolerance: float,
    max_cost_rate: float,
    min_columns: int,
    correlation: float,
    band: int = 64,
    min_gain: float = 2.5,
    max_shift: int = 9,
    min_share: float = 0.5,
) -> np.ndarray:
    """Lines of numbered components lying mostly in runs of levels that the code read in
    their own columns places elsewhere.

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
    lam, tolerance, max_cost_rate, min_columns, correlation : float
        As in :func:`.line_numbering.number_lines`.
    band : int
        Width (columns) of a band; bands overlap by half.
    min_gain : float
        Least cost that another placement saves on a run of levels for the run to
        contradict the component.
    max_shift : int
        Other placements tried: up to this many levels either way.
    min_share : float
        A line is refused when this share of its peaks (of those in a judged band) lies in
        contradicted runs.

    Returns
    -------
    numpy.ndarray
        ``(L,)`` bool, True for the lines to leave unnumbered.
    """
    n_lines = line_order.size
    refuse = np.zeros(n_lines, dtype=bool)
    n_comp = int(line_component.max(initial=-1)) + 1
    off_of = np.full(n_comp + 1, -1, dtype=np.int64)
    for c, off in offset.items():
        if 0 <= c < n_comp:
            off_of[c] = off
    if col.size < 2 or n_lines == 0 or not np.any(off_of >= 0):
        return refuse
    lid = line_id.astype(np.int64)
    has = lid >= 0
    safe = np.maximum(lid, 0)
    comp = np.where(has, line_component[safe], -1).astype(np.int64)
    lev = np.where(has, line_order[safe], -1).astype(np.int64)
    numbered = (comp >= 0) & (lev >= 0) & (off_of[np.maximum(comp, 0)] >= 0)
    # numbered components by a compact index (a fragmented frame has thousands of others)
    ids = np.flatnonzero(off_of[:n_comp] >= 0)
    compact = np.full(n_comp, -1, dtype=np.int64)
    compact[ids] = np.arange(ids.size)
    same_col = col[1:] == col[:-1]
    pair = same_col & (comp[1:] == comp[:-1]) & numbered[:-1] & (lev[1:] == lev[:-1] + 1)
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
    n_bands = int(col.max()) // step + 2
    n_lev = int(lev[numbered].max()) + 1  # differences k -> k + 1 for k < n_lev - 1
    p_ci, p_lev, p_band = compact[comp[k]], lev[k], col[k].astype(np.int64) // step
    # every difference belongs to two overlapping bands: (band, band - 1)
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
    rows = np.unique(groups // n_lev)
    lvl = groups % n_lev
    r_inv = np.searchsorted(rows, groups // n_lev)
    d = np.zeros((rows.size, n_lev))
    w = np.zeros((rows.size, n_lev))
    d[r_inv, lvl] = centre
    w[r_inv, lvl] = weight
    r_off = off_of[ids[rows // n_bands]]
    # cost of each difference against each expected value (-lam, 0, +lam)
    expected = np.array([-lam, 0.0, lam])
    u = (d[:, :, None] - expected[None, None, :]) / (tolerance * lam)
    c3 = np.minimum(u * u, 1.0) * w[:, :, None]  # (rows, levels, 3)
    n_code = code.size
    kinds = code.astype(np.int64)
    diff_at = np.full(n_code + 1, -1, dtype=np.int64)
    diff_at[: n_code - 1] = kinds[:-1] - kinds[1:] + 1  # index into expected; -1 off the code
    levels = np.arange(n_lev)
    pos_here = r_off[:, None] + levels[None, :]  # (rows, levels) code position of each diff
    measured = w > 0

    def cost_at(pos: np.ndarray) -> np.ndarray:
        """Cost of every difference placed at code positions ``pos``; inf off the code
        where measured."""
        inside = (pos >= 0) & (pos < n_code - 1)
        e = diff_at[np.clip(pos, 0, n_code)]
        c = np.take_along_axis(c3, np.clip(e, 0, 2)[:, :, None], axis=2)[:, :, 0]
        return np.where(inside & (e >= 0), c, np.where(measured, np.inf, 0.0))

    here_cost = cost_at(pos_here)
    here_cost = np.where(np.isfinite(here_cost), here_cost, 0.0)
    # the other placements: a block is a few levels off (lines hidden by a step, dim lines
    # not found), so shifts up to a code window each way
    shifts = np.array([s for s in range(-max_shift, max_shift + 1) if s != 0])
    alt = np.stack([cost_at(pos_here + s) for s in shifts], axis=1)  # (rows, shifts, levels)
    off_code = ~np.isfinite(alt)
    alt = np.where(off_code, 0.0, alt)
    # an off-code level ends a run: a gain no run survives
    gain = np.where(off_code, -1e9, here_cost[:, None, :] - alt)
    gain = np.where(measured[:, None, :], gain, 0.0)
    # maximum-sum run of levels of every (row, shift): the largest S[b + 1] - min S[<= b]
    csum = np.concatenate([np.zeros((*gain.shape[:2], 1)), np.cumsum(gain, axis=2)], axis=2)
    run_min = np.minimum.accumulate(csum[:, :, :-1], axis=2)
    ends = csum[:, :, 1:] - run_min
    best = ends.max(axis=2)
    # the longest such run: the last end and (below) the first start reaching the maximum,
    # so that levels where both placements agree stay with the block around them
    hi = n_lev - 1 - np.argmax(ends[:, :, ::-1] >= best[:, :, None] - 1e-9, axis=2)
    cand = best >= min_gain
    refuse_levels = np.zeros((rows.size, n_lev + 1), dtype=bool)
    if not np.any(cand):
        return refuse
    idx = np.arange(n_lev + 1)[None, None, :]
    lo = np.argmin(np.where(idx <= hi[:, :, None], csum, np.inf), axis=2)  # run = lo..hi
    a_sum = np.concatenate([np.zeros((*alt.shape[:2], 1)), np.cumsum(alt, axis=2)], axis=2)
    w_sum = np.concatenate([np.zeros((rows.size, 1)), np.cumsum(w, axis=1)], axis=1)
    run_alt = (
        np.take_along_axis(a_sum, (hi + 1)[:, :, None], axis=2)
        - np.take_along_axis(a_sum, lo[:, :, None], axis=2)
    )[:, :, 0]
    run_w = np.take_along_axis(w_sum, hi + 1, axis=1) - np.take_along_axis(w_sum, lo, axis=1)
    # the other placement must explain the run cleanly
    cand &= run_alt <= max_cost_rate * run_w
    for r, sh in zip(*np.nonzero(cand), strict=True):
        # differences lo..hi join levels lo..hi + 1
        refuse_levels[r, lo[r, sh] : hi[r, sh] + 2] = True
    # peaks: contradicted when a band holding them is contradicted at their level
    pk = np.flatnonzero(numbered)
    pci, pl, pb = compact[comp[pk]], lev[pk], col[pk].astype(np.int64) // step
    row_of = np.full(ids.size * n_bands, -1, dtype=np.int64)
    row_of[rows] = np.arange(rows.size)
    in_band = np.zeros(pk.size, dtype=bool)
    in_run = np.zeros(pk.size, dtype=bool)
    for db in (0, 1):
        b = pb - db
        ok = (b >= 0) & (b < n_bands)
        r = np.where(ok, row_of[np.clip(pci * n_bands + b, 0, row_of.size - 1)], -1)
        seen = r >= 0
        in_band |= seen
        in_run |= seen & refuse_levels[np.maximum(r, 0), np.minimum(pl, n_lev)]
    seen_per_line = np.bincount(lid[pk[in_band]], minlength=n_lines)
    hit_per_line = np.bincount(lid[pk[in_run]], minlength=n_lines)
    return (hit_per_line > 0) & (hit_per_line >= min_share * np.maximum(seen_per_line, 1))
