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

from .code_evidence import level_pairs, reliability, robust_centres

__all__ = ["CodeBands", "band_gains", "contradicted_lines"]


class CodeBands:
    """The level differences of every component, read in overlapping column bands.

    Built once per frame; :meth:`contradicted` then judges any set of placements (the
    numbering asks twice: with the placements the code decides alone, and with the final
    ones).

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_order, line_component : numpy.ndarray
        Per-line level and component (-1: none).
    lam, tolerance : float
        Log area ratio of a heavy to a light line; departure counted as a miss.
    min_columns, correlation : float
        As in :func:`.line_numbering.number_lines` (a difference's weight).
    band : int
        Width (columns) of a band; bands overlap by half.
    """

    def __init__(
        self,
        col: np.ndarray,
        area: np.ndarray,
        line_id: np.ndarray,
        line_order: np.ndarray,
        line_component: np.ndarray,
        *,
        lam: float,
        tolerance: float,
        min_columns: float,
        correlation: float,
        band: int = 64,
    ) -> None:
        self.n_lines = line_order.size
        self.step = max(band // 2, 1)
        # per-peak loops compiled (column_pairs); the numba import costs ~0.3 s, hence here
        from .column_pairs import band_keys, peak_levels

        self.lid = line_id.astype(np.int64)
        comp, lev = peak_levels(line_id, line_order, line_component)
        self.comp, self.lev = comp, lev
        self.col = col.astype(np.int64)
        self.rows = np.zeros(0, dtype=np.int64)
        if col.size < 2 or self.n_lines == 0:
            return
        k, lr = level_pairs(col, area, comp, lev)
        if k.size == 0:
            return
        # components with differences, by a compact index (a fragmented frame has
        # thousands of one-line components, which have none)
        self.ids = np.flatnonzero(np.bincount(comp[k]))  # np.unique's result, without a sort
        self.compact = np.full(int(comp.max()) + 1, -1, dtype=np.int64)
        self.compact[self.ids] = np.arange(self.ids.size)
        self.n_bands = int(col.max()) // self.step + 2
        self.n_lev = n_lev = int(lev[k].max()) + 2
        # every difference belongs to two overlapping bands: (band, band - 1)
        keys, ratios = band_keys(
            k, lr, comp, lev, self.col, self.compact, self.step, self.n_bands, n_lev
        )
        groups, centre, count, spread = robust_centres(keys, ratios)
        weight = np.minimum(1.0, count / float(min_columns)) * reliability(
            count.astype(np.float64), spread, lam, correlation
        )
        # the groups ascend: their rows (np.unique's) are where the row changes
        row_of = groups // n_lev
        new_row = np.empty(row_of.size, dtype=bool)
        new_row[:1] = True
        np.not_equal(row_of[1:], row_of[:-1], out=new_row[1:])
        self.rows = row_of[new_row]
        r_inv = np.cumsum(new_row) - 1
        self.w = np.zeros((self.rows.size, n_lev))
        d = np.zeros((self.rows.size, n_lev))
        d[r_inv, groups % n_lev] = centre
        self.w[r_inv, groups % n_lev] = weight
        # cost of each difference against each expected value (-lam, 0, +lam)
        expected = np.array([-lam, 0.0, lam])
        u = (d[:, :, None] - expected[None, None, :]) / (tolerance * lam)
        self.c3 = np.minimum(u * u, 1.0) * self.w[:, :, None]  # (rows, levels, 3)

    def contradicted(
        self,
        offset: dict[int, int],
        code: np.ndarray,
        *,
        max_cost_rate: float,
        min_gain: float = 2.5,
        max_shift: int = 9,
        min_share: float = 0.5,
    ) -> np.ndarray:
        """Lines of the placed components lying mostly in runs of levels that the code read
        in their own columns places elsewhere.

        Parameters
        ----------
        offset : dict
            Offset on the code (index of level 0) of every placed component; -1 or absent
            when unplaced.
        code : numpy.ndarray
            The raster's kinds (0 light, 1 heavy) in line order.
        max_cost_rate : float
            The other placement must leave at most this share of the run unexplained.
        min_gain : float
            Least cost that another placement saves on a run of levels for the run to
            contradict the component.
        max_shift : int
            Other placements tried: up to this many levels either way.
        min_share : float
            A line is refused when this share of its peaks (of those in a judged band) lies
            in contradicted runs.

        Returns
        -------
        numpy.ndarray
            ``(L,)`` bool, True for the lines to leave unnumbered.
        """
        refuse = np.zeros(self.n_lines, dtype=bool)
        if self.rows.size == 0:
            return refuse
        r_off = np.array([offset.get(int(c), -1) for c in self.ids], dtype=np.int64)
        r_off = r_off[self.rows // self.n_bands]
        judged = np.flatnonzero(r_off >= 0)
        if judged.size == 0:
            return refuse
        c3, w, r_off = self.c3[judged], self.w[judged], r_off[judged]
        n_rows, n_lev = judged.size, self.n_lev
        n_code = code.size
        kinds = code.astype(np.int64)
        diff_at = np.full(n_code + 1, 3, dtype=np.int64)
        diff_at[: n_code - 1] = kinds[:-1] - kinds[1:] + 1  # index into expected; 3 off
        # the component's placement and the others: a block is a few levels off (lines
        # hidden by a step, dim lines not found), so shifts up to a code window each way
        shifts = np.array([0] + [s for s in range(-max_shift, max_shift + 1) if s != 0])
        # On most frames no run gains enough: the best gains in one compiled loop decide
        # that (band_runs, the same bits as ``best`` below; the numba import costs ~0.3 s).
        from .band_runs import best_gains

        if not np.any(best_gains(c3, w, r_off, diff_at, shifts) >= min_gain):
            return refuse
        alt, csum, ends = band_gains(c3, w, r_off, diff_at, shifts)
        best = ends.max(axis=2)
        cand = best >= min_gain
        if not np.any(cand):
            return refuse
        # the longest such run: the last end and the first start reaching the maximum, so
        # that levels where both placements agree stay with the block around them
        hi = n_lev - 1 - np.argmax(ends[:, :, ::-1] >= best[:, :, None] - 1e-9, axis=2)
        idx = np.arange(n_lev + 1)[None, None, :]
        lo = np.argmin(np.where(idx <= hi[:, :, None], csum, np.inf), axis=2)  # run = lo..hi
        a_sum = np.concatenate([np.zeros((*alt.shape[:2], 1)), np.cumsum(alt, axis=2)], axis=2)
        w_sum = np.concatenate([np.zeros((n_rows, 1)), np.cumsum(w, axis=1)], axis=1)
        run_alt = (
            np.take_along_axis(a_sum, (hi + 1)[:, :, None], axis=2)
            - np.take_along_axis(a_sum, lo[:, :, None], axis=2)
        )[:, :, 0]
        run_w = np.take_along_axis(w_sum, hi + 1, axis=1) - np.take_along_axis(w_sum, lo, axis=1)
        # the other placement must explain the run cleanly
        cand &= run_alt <= max_cost_rate * run_w
        run_levels = np.zeros((self.rows.size, n_lev + 1), dtype=bool)
        for r, sh in zip(*np.nonzero(cand), strict=True):
            # differences lo..hi join levels lo..hi + 1
            run_levels[judged[r], lo[r, sh] : hi[r, sh] + 2] = True
        # peaks: contradicted when a band holding them is contradicted at their level
        comp_ok = (self.comp >= 0) & (self.comp < self.compact.size)
        pk = np.flatnonzero(comp_ok & (self.lev >= 0))
        pci = self.compact[self.comp[pk]]
        pk, pci = pk[pci >= 0], pci[pci >= 0]
        pl, pb = self.lev[pk], self.col[pk] // self.step
        row_of = np.full(self.ids.size * self.n_bands, -1, dtype=np.int64)
        row_of[self.rows[judged]] = judged
        in_band = np.zeros(pk.size, dtype=bool)
        in_run = np.zeros(pk.size, dtype=bool)
        for db in (0, 1):
            b = pb - db
            ok = (b >= 0) & (b < self.n_bands)
            r = np.where(ok, row_of[np.clip(pci * self.n_bands + b, 0, row_of.size - 1)], -1)
            seen = r >= 0
            in_band |= seen
            in_run |= seen & run_levels[np.maximum(r, 0), np.minimum(pl, n_lev)]
        seen_per_line = np.bincount(self.lid[pk[in_band]], minlength=self.n_lines)
        hit_per_line = np.bincount(self.lid[pk[in_run]], minlength=self.n_lines)
        return (hit_per_line > 0) & (hit_per_line >= min_share * np.maximum(seen_per_line, 1))


def band_gains(
    c3: np.ndarray, w: np.ndarray, r_off: np.ndarray, diff_at: np.ndarray, shifts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What every run of a band's levels gains, placed at each shift instead of its own
    offset (the whole-array passes of :meth:`CodeBands.contradicted`).

    Parameters
    ----------
    c3 : numpy.ndarray
        ``(rows, levels, 3)`` cost of each band level's difference for each expected kind.
    w : numpy.ndarray
        ``(rows, levels)`` weights; 0 where a level is not measured.
    r_off : numpy.ndarray
        ``(rows,)`` each band's placement on the code.
    diff_at : numpy.ndarray
        ``(n_code + 1,)`` expected kind of each code position (3: off the code).
    shifts : numpy.ndarray
        Shifts tried, 0 (the placement itself) first.

    Returns
    -------
    alt : numpy.ndarray
        ``(rows, shifts - 1, levels)`` cost at each other shift.
    csum : numpy.ndarray
        ``(rows, shifts - 1, levels + 1)`` running sums of the gains.
    ends : numpy.ndarray
        ``(rows, shifts - 1, levels)`` the best gain of a run ending at each level.
    """
    n_rows, n_lev = w.shape
    n_code = diff_at.size - 1
    c4 = np.concatenate([c3, np.zeros((n_rows, n_lev, 1))], axis=2)
    measured = w > 0
    pos = r_off[:, None, None] + shifts[None, :, None] + np.arange(n_lev)[None, None, :]
    inside = (pos >= 0) & (pos < n_code - 1)
    e = diff_at[np.clip(pos, 0, n_code)]
    cost = np.take_along_axis(c4[:, None, :, :], e[:, :, :, None], axis=3)[:, :, :, 0]
    off_code = ~inside & measured[:, None, :]
    here = np.where(off_code[:, 0], 0.0, cost[:, 0])
    alt = np.where(off_code[:, 1:], 0.0, cost[:, 1:])
    # an off-code level ends a run: a gain no run survives
    gain = np.where(off_code[:, 1:], -1e9, here[:, None, :] - alt)
    gain = np.where(measured[:, None, :], gain, 0.0)
    # maximum-sum run of levels of every (row, shift): the largest S[b + 1] - min S[<= b]
    csum = np.concatenate([np.zeros((*gain.shape[:2], 1)), np.cumsum(gain, axis=2)], axis=2)
    ends = csum[:, :, 1:] - np.minimum.accumulate(csum[:, :, :-1], axis=2)
    return alt, csum, ends


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
    """:class:`CodeBands` built and judged once: the lines of placed components lying
    mostly in runs of levels that the code read in their own columns places elsewhere.

    Parameters are those of :class:`CodeBands` and :meth:`CodeBands.contradicted`.

    Returns
    -------
    numpy.ndarray
        ``(L,)`` bool, True for the lines to leave unnumbered.
    """
    bands = CodeBands(
        col,
        area,
        line_id,
        line_order,
        line_component,
        lam=lam,
        tolerance=tolerance,
        min_columns=min_columns,
        correlation=correlation,
        band=band,
    )
    return bands.contradicted(
        offset,
        code,
        max_cost_rate=max_cost_rate,
        min_gain=min_gain,
        max_shift=max_shift,
        min_share=min_share,
    )
