"""Line numbering: the absolute raster line numbers, from the light/heavy code of the lines.

Line sequence analysis gives each line a relative order within its component; the absolute
number is that order plus an offset, which the pattern of light and heavy lines decides
(the raster's window code: any ``window`` consecutive kinds identify their position).

Reading the kinds robustly: absolute intensity varies along the back (distance, inclination,
skin), but two neighbouring lines in one column are lit and seen alike, so the ratio of their
peak areas is the ratio of their line widths: 1.5 for a heavy line over a light one (60:40),
1 for equal kinds. For each pair of consecutive levels ``k, k + 1`` of a component, a robust
mean over the columns where they are direct neighbours of ``log(area_k / area_k+1)`` is
``+λ``, ``0`` or ``-λ`` (``λ = log 1.5``).

The offset is the maximum-likelihood placement of these differences on the code: every
placement is scored by the number of differences it explains badly (a soft count, so one
misread line costs two differences and no more), and the best must beat the second best by
a clear margin. A component with fewer lines than the code window, or whose best placement
is not clearly better than another, is left unnumbered with the reason: refusing is always
better than a wrong number.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field

from rasterserver.errors import InputError
from rasterserver.raster import Raster
from rasterserver.records_lines import NumberedLines, OrderedLines
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["CodeWindowNumbering", "ComponentNumbering", "level_differences", "number_lines"]


def level_differences(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust mean log-area ratio of every pair of consecutive levels, per component.

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_order, line_component : numpy.ndarray
        Per-line relative order and component (-1: unordered).

    Returns
    -------
    comp, level, ratio, count : numpy.ndarray
        One entry per (component, level ``k``) with measurements: the robust mean over
        columns of ``log(area at k / area at k + 1)`` where a line of level ``k`` lies
        directly above one of level ``k + 1``, and the number of such columns.
    """
    empty_i = np.zeros(0, dtype=np.int64)
    if col.size < 2 or line_order.size == 0:
        return empty_i, empty_i, np.zeros(0), empty_i
    lid = line_id.astype(np.int64)
    ok_line = lid >= 0
    comp_of = np.where(ok_line, line_component[np.maximum(lid, 0)], -1).astype(np.int64)
    lev_of = np.where(ok_line, line_order[np.maximum(lid, 0)], -1).astype(np.int64)
    pair = (
        (col[1:] == col[:-1])
        & (comp_of[1:] == comp_of[:-1])
        & (comp_of[:-1] >= 0)
        & (lev_of[:-1] >= 0)
        & (lev_of[1:] == lev_of[:-1] + 1)
    )
    k = np.flatnonzero(pair)
    if k.size == 0:
        return empty_i, empty_i, np.zeros(0), empty_i
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(area[k].astype(np.float64) / area[k + 1].astype(np.float64))
    good = np.isfinite(lr)
    k, lr = k[good], lr[good]
    if k.size == 0:
        return empty_i, empty_i, np.zeros(0), empty_i
    comp, level = comp_of[k], lev_of[k]
    span = int(lev_of.max()) + 2
    key = comp * span + level
    # Keys are small (components x levels): count by key directly, no sort.
    n_keys = int(key.max()) + 1
    counts = np.bincount(key, minlength=n_keys)
    # A robust centre without sorting: the mean of the clipped ratios, then twice the mean
    # of those near the previous centre (silhouette columns and skin spots are outliers).
    lr = np.clip(lr, -1.0, 1.0)
    centre = np.bincount(key, weights=lr, minlength=n_keys) / np.maximum(counts, 1)
    for window in (0.3, 0.15):
        near = np.abs(lr - centre[key]) <= window
        total = np.bincount(key[near], weights=lr[near], minlength=n_keys)
        n_near = np.bincount(key[near], minlength=n_keys)
        centre = np.where(n_near > 0, total / np.maximum(n_near, 1), centre)
    groups = np.flatnonzero(counts)
    return groups // span, groups % span, centre[groups], counts[groups]


@dataclass(frozen=True)
class ComponentNumbering:
    """How one component was numbered.

    Attributes
    ----------
    component : int
        Component index.
    n_levels : int
        Number of levels (relative orders) in the component.
    offset : int
        Index into the raster's lines of level 0; -1 when refused.
    cost : float
        Soft count of badly explained differences of the best placement.
    margin : float
        Cost of the second-best placement minus the best's.
    kinds : numpy.ndarray
        ``(n_levels,)`` int8 observed kind of each level: 0 light, 1 heavy, -1 unknown.
    reason : str
        Why it was refused; empty when numbered.
    """

    component: int
    n_levels: int
    offset: int
    cost: float
    margin: float
    kinds: np.ndarray
    reason: str


def _observed_kinds(d: np.ndarray, weight: np.ndarray, lam: float, tolerance: float) -> np.ndarray:
    """Most likely kind of every level from the differences alone (no code), by Viterbi.

    ``d[k] ≈ (kind[k] - kind[k + 1]) * lam``; the same robust cost as the placement. Levels
    without a measured difference on either side, or whose two kinds explain the data
    equally well, are unknown (-1).
    """
    n = d.size + 1
    kinds = np.full(n, -1, dtype=np.int8)
    if n < 2:
        return kinds
    measured = ~np.isnan(d)
    dd = np.where(measured, d, 0.0)
    ww = np.where(measured, weight, 0.0)
    # cost[k, a, b]: level k of kind a followed by level k + 1 of kind b
    expect = np.array([[0.0, -1.0], [1.0, 0.0]]) * lam
    u = (dd[:, None, None] - expect[None, :, :]) / (tolerance * lam)
    cost = np.minimum(u * u, 1.0) * ww[:, None, None]
    # forward and backward passes give each level's best total cost per kind
    fwd = np.zeros((n, 2))
    for k in range(n - 1):
        fwd[k + 1] = (fwd[k][:, None] + cost[k]).min(axis=0)
    bwd = np.zeros((n, 2))
    for k in range(n - 2, -1, -1):
        bwd[k] = (cost[k] + bwd[k + 1][None, :]).min(axis=1)
    total = fwd + bwd
    gap = total[:, 0] - total[:, 1]  # > 0: heavy explains better
    seen = np.zeros(n, dtype=bool)
    seen[:-1] |= measured
    seen[1:] |= measured
    sure = seen & (np.abs(gap) >= 0.5)
    kinds[sure] = (gap[sure] > 0).astype(np.int8)
    return kinds


def _number_component(
    comp: int,
    n_levels: int,
    d: np.ndarray,
    weight: np.ndarray,
    code: np.ndarray,
    *,
    lam: float,
    tolerance: float,
    min_lines: int,
    min_margin: float,
    max_cost_rate: float,
) -> ComponentNumbering:
    kinds = _observed_kinds(d, weight, lam, tolerance)
    if n_levels < min_lines:
        return ComponentNumbering(
            comp, n_levels, -1, np.nan, 0.0, kinds, f"{n_levels} lines, fewer than {min_lines}"
        )
    n_off = code.size - n_levels + 1
    if n_off < 1:
        return ComponentNumbering(
            comp, n_levels, -1, np.nan, 0.0, kinds, f"{n_levels} lines, more than the raster's"
        )
    measured = ~np.isnan(d)
    if measured.sum() < min_lines - 1:
        return ComponentNumbering(
            comp,
            n_levels,
            -1,
            np.nan,
            0.0,
            kinds,
            f"only {int(measured.sum())} neighbour intensity ratios measured",
        )
    windows = np.lib.stride_tricks.sliding_window_view(code.astype(np.float64), n_levels)
    expected = (windows[:, :-1] - windows[:, 1:]) * lam  # (offsets, n_levels - 1)
    u = (np.where(measured, d, 0.0)[None, :] - expected) / (tolerance * lam)
    cost = (np.minimum(u * u, 1.0) * np.where(measured, weight, 0.0)[None, :]).sum(axis=1)
    order = np.argsort(cost, kind="stable")
    best = int(order[0])
    best_cost = float(cost[best])
    margin = float(cost[order[1]] - best_cost) if n_off > 1 else float("inf")
    terms = float(weight[measured].sum())
    if best_cost > max_cost_rate * terms:
        reason = f"best code placement explains too little ({best_cost:.1f} of {terms:.0f} bad)"
        return ComponentNumbering(comp, n_levels, -1, best_cost, margin, kinds, reason)
    if margin < min_margin:
        reason = f"ambiguous code placement (margin {margin:.2f} < {min_margin:g})"
        return ComponentNumbering(comp, n_levels, -1, best_cost, margin, kinds, reason)
    return ComponentNumbering(comp, n_levels, best, best_cost, margin, kinds, "")


def number_lines(
    data: OrderedLines,
    raster: Raster,
    *,
    area_ratio: float = 1.5,
    tolerance: float = 0.5,
    min_lines: int | None = None,
    min_margin: float = 2.0,
    max_cost_rate: float = 0.25,
    min_columns: int = 5,
) -> tuple[np.ndarray, np.ndarray, list[ComponentNumbering]]:
    """Absolute number and observed kind of every line, component by component.

    Parameters
    ----------
    data : OrderedLines
        Ordered lines.
    raster : Raster
        The diapositive's code.
    area_ratio : float
        Expected peak-area ratio of a heavy to a light line (line width ratio).
    tolerance : float
        A difference departing from the expected one by this fraction of ``log(area_ratio)``
        counts as fully unexplained; smaller departures count quadratically.
    min_lines : int, optional
        Least number of lines (levels) of a component to number; the raster's code window
        by default.
    min_margin : float
        Least cost difference between the best and the second-best placement.
    max_cost_rate : float
        Largest cost of the best placement per measured difference.
    min_columns : int
        Columns of neighbourhood at which a difference gets full weight; fewer weigh less.

    Returns
    -------
    line_number : numpy.ndarray
        ``(L,)`` int32, -1 when unnumbered.
    kind : numpy.ndarray
        ``(L,)`` int8 observed kinds.
    components : list of ComponentNumbering
        One per component, in component order.
    """
    n_lines = data.line_order.shape[0]
    line_number = np.full(n_lines, -1, dtype=np.int32)
    kind = np.full(n_lines, -1, dtype=np.int8)
    comps = data.line_component.astype(np.int64)
    levels = data.line_order.astype(np.int64)
    valid = (comps >= 0) & (levels >= 0)
    if not np.any(valid):
        return line_number, kind, []
    code = raster.code
    lam = float(np.log(area_ratio))
    need = raster.window if min_lines is None else min_lines
    c_idx, l_idx, ratio, count = level_differences(
        data.col, data.area, data.line_id, data.line_order, data.line_component
    )
    n_comp = int(comps[valid].max()) + 1
    results: list[ComponentNumbering] = []
    for c in range(n_comp):
        mine = valid & (comps == c)
        if not np.any(mine):
            continue
        n_levels = int(levels[mine].max()) + 1
        d = np.full(max(n_levels - 1, 0), np.nan)
        w = np.zeros(max(n_levels - 1, 0))
        sel = c_idx == c
        d[l_idx[sel]] = ratio[sel]
        w[l_idx[sel]] = np.minimum(1.0, count[sel] / float(min_columns))
        res = _number_component(
            c,
            n_levels,
            d,
            w,
            code,
            lam=lam,
            tolerance=tolerance,
            min_lines=need,
            min_margin=min_margin,
            max_cost_rate=max_cost_rate,
        )
        results.append(res)
        kind[mine] = res.kinds[levels[mine]]
        if res.offset >= 0:
            line_number[mine] = raster.numbers[res.offset + levels[mine]].astype(np.int32)
    return line_number, kind, results


def _summarise(results: list[ComponentNumbering], sizes: np.ndarray) -> tuple[float, str]:
    """Confidence (worst numbered component) and the reasons of the refused ones."""
    numbered = [r for r in results if r.offset >= 0]
    if numbered:
        worst = min(r.margin for r in numbered)
        confidence = float(1.0 - np.exp(-worst / 4.0)) if np.isfinite(worst) else 1.0
    else:
        confidence = 0.0
    refused = [r for r in results if r.offset < 0]
    if not results:
        return 0.0, "no ordered lines"
    if not refused:
        return confidence, ""
    small = [r for r in refused if "fewer than" in r.reason]
    other = [r for r in refused if "fewer than" not in r.reason]
    parts = [
        f"component {r.component} ({r.n_levels} lines, {int(sizes[r.component])} peaks): {r.reason}"
        for r in other
    ]
    if small:
        peaks = int(sum(sizes[r.component] for r in small))
        parts.append(
            f"{len(small)} component(s) with too few lines to read the code ({peaks} peaks)"
        )
    return confidence, "; ".join(parts)


class CodeWindowNumbering(Stage[OrderedLines, NumberedLines]):
    """Absolute line numbers from the light/heavy code, by maximum likelihood over offsets.

    Neighbouring lines' intensity ratios in the same columns (shading cancels) are matched
    against every placement on the raster's window code; a component is numbered only when
    its best placement is unique by a clear margin, and left unnumbered with the reason
    otherwise.
    """

    name: ClassVar[str] = "numbers.code-window"
    stage: ClassVar[str] = "numbers"
    version: ClassVar[str] = "1"
    input_type = OrderedLines
    output_type = NumberedLines
    requires: ClassVar[tuple[str, ...]] = ("raster",)

    class Params(StageParams):
        """Parameters of :class:`CodeWindowNumbering`."""

        area_ratio: float = Field(
            1.5, gt=1, description="Peak-area ratio of a heavy to a light line."
        )
        tolerance: float = Field(
            0.5, gt=0, le=1, description="Departure (in log area ratios) counted as a miss."
        )
        min_lines: int | None = Field(
            None, ge=1, description="Least lines of a numbered component (default: window)."
        )
        min_margin: float = Field(
            2.0, ge=0, description="Least cost margin of the best over the second placement."
        )
        max_cost_rate: float = Field(
            0.25, ge=0, description="Largest share of differences the best may miss."
        )
        min_columns: int = Field(5, ge=1, description="Columns for a difference's full weight.")

    def run(self, data: OrderedLines, params: Params, context: StageContext) -> NumberedLines:
        """Number the lines of ``data`` with the raster from ``context.raster``."""
        raster = context.raster
        if not isinstance(raster, Raster):
            raise InputError(
                f"{self.name} needs context.raster as a rasterserver.raster.Raster, "
                f"not {type(raster).__name__}"
            )
        line_number, kind, results = number_lines(
            data,
            raster,
            area_ratio=params.area_ratio,
            tolerance=params.tolerance,
            min_lines=params.min_lines,
            min_margin=params.min_margin,
            max_cost_rate=params.max_cost_rate,
            min_columns=params.min_columns,
        )
        lid = data.line_id
        comps = data.line_component
        n_comp = int(comps.max()) + 1 if comps.size and comps.max() >= 0 else 0
        peaks_per_line = np.bincount(lid[lid >= 0], minlength=comps.size)
        sizes = np.bincount(comps[comps >= 0], weights=peaks_per_line[comps >= 0], minlength=n_comp)
        confidence, reason = _summarise(results, sizes)
        if data.n_peaks == 0:
            reason = "no peaks"
        elif comps.size == 0:
            reason = "no lines"
        table = np.append(line_number, -1).astype(np.int32)
        return NumberedLines(
            col=data.col,
            row=data.row,
            area=data.area,
            height=data.height,
            width=data.width,
            image_shape=data.image_shape,
            line_id=lid,
            order=data.order,
            line_order=data.line_order,
            line_component=comps,
            number=table[np.where(lid >= 0, lid, -1)],
            line_number=line_number,
            kind_observed=kind,
            confidence=confidence,
            reason=reason,
        )
