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

from collections import defaultdict
from typing import Any, ClassVar

import numpy as np

from rasterserver.errors import InputError
from rasterserver.raster import Raster
from rasterserver.records_lines import NumberedLines, OrderedLines
from rasterserver.stage import Stage, StageContext

from .code_evidence import (
    EXPLAINS_TOO_LITTLE,
    CodeFit,
    ComponentNumbering,
    area_ratio_of,
    code_fit,
    code_objection,
    contradicted_lines,
    level_differences,
    level_statistics,
    observed_kinds,
    reliability,
)
from .code_tiles import CodeBands
from .component_groups import component_groups, group_placement
from .contradicted_pairs import PairRule, pair_refusal
from .numbering_checks import (
    by_line,
    contact_votes,
    local_spacing,
    plausible_distance,
)
from .numbering_params import CodeWindowParams
from .numbering_refusals import (
    edge_doubts,
    least_pair_departure,
    refusal,
    refuse_peaks,
    settle_last,
    summarise,
)

__all__ = [
    "CodeWindowNumbering",
    "ComponentNumbering",
    "level_differences",
    "level_statistics",
    "number_lines",
]


def number_lines(
    data: OrderedLines,
    raster: Raster,
    *,
    area_ratio: float | None = None,
    tolerance: float = 0.5,
    min_lines: int | None = None,
    min_margin: float | None = None,
    max_cost_rate: float = 0.25,
    poor_run_factor: float = 0.0,
    min_columns: int = 5,
    correlation: float = 4.0,
    min_votes: float = 8.0,
    max_conflict: float = 0.2,
    min_conflict: float = 3.0,
    station: Any = None,
    max_depth: float = 600.0,
    pair_check: bool = True,
    pair_rule: PairRule = PairRule(),
    min_contact_share: float = 0.2,
    tile_check: bool = True,
    tile_band: int = 64,
    tile_gain: float = 2.5,
    loose_cost_rate: float = 0.4,
    doubtful_lines: np.ndarray | None = None,
    group_ties: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, list[ComponentNumbering]]:
    """Absolute number and observed kind of every line, component by component.

    A component is numbered when its code evidence is unique with a margin and the result
    agrees with the numbered components it touches (:mod:`.numbering_checks`: column
    neighbours at one line spacing, lines continued across short gaps), and, with a
    calibration, puts it at a plausible distance. A component the code alone does not
    decide inherits its number from numbered components it touches when their contacts
    agree (and its own code does not contradict them); pieces too small to inherit alone
    inherit as a group (``group_ties``). Components are taken largest first.

    Parameters
    ----------
    data : OrderedLines
        Ordered lines.
    raster : Raster
        The diapositive's code.
    area_ratio : float, optional
        Expected peak-area ratio of a heavy to a light line; by default the ratio of the
        raster's heavy to light line widths.
    tolerance : float
        A difference departing from the expected one by this fraction of ``log(area_ratio)``
        counts as fully unexplained; smaller departures count quadratically.
    min_lines : int, optional
        Least number of lines (levels) of a component numbered by its code alone; the
        raster's code window by default, one more for a code whose windows may differ in
        one line only.
    min_margin : float, optional
        Least cost difference between the best and the second-best placement; by default 2
        for a code whose windows differ in two lines or more (one misread line is then
        detected), 4 for a code where two windows may differ in one line only.
    max_cost_rate : float
        Largest cost of the best placement per measured difference.
    poor_run_factor : float
        Also refuse a run of a numbered component's levels whose placement costs over this
        many times ``max_cost_rate`` per difference (0: only runs another placement reads
        cleanly; :func:`.code_evidence.locally_contradicted`).
    min_columns : int
        Columns of neighbourhood at which a difference gets full weight; fewer weigh less.
    correlation : float
        Columns over which the albedo texture is correlated (for a difference's reliability).
    min_votes : float
        Least contact weight (columns) for a component to inherit a number.
    max_conflict, min_conflict : float
        A component is refused when the contact weight contradicting its number reaches
        ``min_conflict`` and ``max_conflict`` of its contacts with numbered components.
    station : Station, optional
        The calibration; when given, the plausible-distance test is made.
    max_depth : float
        Largest distance (mm) of a component from the calibrated back plane's distance.
    pair_check : bool
        Refuse the shorter line of numbered column neighbours whose intensity ratio
        contradicts the code at their numbers (:func:`.numbering_checks.pair_contradictions`).
    pair_rule : PairRule
        How the pair check judges and spares (:class:`.contradicted_pairs.PairRule`: the
        agreement that spares a line confirmed on its other side, the least departure that
        contradicts, in log ratios, and the blocks placed a line off: version 22).
    min_contact_share : float
        Least contact weight, as a share of a component's column extent, for it to inherit
        a number: a wide component touching numbered lines at a corner only (across a
        waistband's depth step) is refused.
    tile_check : bool
        Leave unnumbered the lines lying mostly where the code read in their own columns
        contradicts their component's placement (:class:`.code_tiles.CodeBands`).
    tile_band : int
        Width (columns) of a band in which the code is read again.
    tile_gain : float
        Least cost another placement must save on a run of a band's levels to refuse it.
    loose_cost_rate : float
        With the code bands on, a component whose best placement leaves up to this share
        of its differences unexplained (more than ``max_cost_rate``) is still placed there
        when the placement is unique by far (a margin of four times ``min_margin`` and
        15 % of the differences); the bands then refuse the lines placed off.
    doubtful_lines : numpy.ndarray, optional
        ``(L,)`` bool, filled in place: the lines of numbered components the code refused
        (a block ordered off, a line against its component's order); the peaks beside them
        are judged next (:func:`.numbering_refusals.refuse_peaks`).
    group_ties : float
        Components the code does not place and that cannot inherit alone are grouped by
        agreeing contacts over this many columns and inherit together
        (:mod:`.component_groups`); 0: no groups.

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
    lam = float(np.log(area_ratio_of(raster, area_ratio)))
    if min_margin is None:
        min_margin = 2.0 if raster.min_distance >= 2 else 4.0
    need = min_lines
    if need is None:
        need = raster.window + (1 if raster.min_distance < 2 else 0)
    c_idx, l_idx, ratio, count, spread = level_statistics(
        data.col, data.area, data.line_id, data.line_order, data.line_component
    )
    reliable = reliability(count.astype(np.float64), spread, lam, correlation)
    n_comp = int(comps[valid].max()) + 1
    fits: dict[int, CodeFit] = {}
    n_levels_of: dict[int, int] = {}
    kinds_of: dict[int, np.ndarray] = {}
    diffs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    size = np.zeros(n_comp)
    peaks_per_line = np.bincount(data.line_id[data.line_id >= 0], minlength=n_lines)
    np.add.at(size, comps[valid], peaks_per_line[valid])
    # column extent of every component (for the share of it a link touches)
    lid_all = data.line_id.astype(np.int64)
    peak_comp = np.where(lid_all >= 0, comps[np.maximum(lid_all, 0)], -1)
    has = np.flatnonzero((peak_comp >= 0) & valid[np.maximum(lid_all, 0)])
    first_col = np.zeros(n_comp, dtype=np.int64)
    last_col = np.full(n_comp, -1, dtype=np.int64)
    if has.size:
        # peaks are sorted by column: grouped by component (a stable sort), each group's
        # first and last peak are its first and last column
        grouped = has[by_line(peak_comp[has])]
        gc = peak_comp[grouped]
        start = np.flatnonzero(np.r_[True, gc[1:] != gc[:-1]])
        end = np.r_[start[1:], gc.size] - 1
        cols = data.col.astype(np.int64)
        first_col[gc[start]] = cols[grouped[start]]
        last_col[gc[start]] = cols[grouped[end]]
    width = last_col - first_col + 1
    for c in range(n_comp):
        mine = valid & (comps == c)
        if not np.any(mine):
            continue
        n_levels = int(levels[mine].max()) + 1
        d = np.full(max(n_levels - 1, 0), np.nan)
        w = np.zeros(max(n_levels - 1, 0))
        sel = c_idx == c
        d[l_idx[sel]] = ratio[sel]
        w[l_idx[sel]] = np.minimum(1.0, count[sel] / float(min_columns)) * reliable[sel]
        n_levels_of[c] = n_levels
        diffs[c] = (d, w)
        kinds_of[c] = observed_kinds(d, w, lam, tolerance)
        fits[c] = code_fit(
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
        fit = fits[c]
        if (
            tile_check
            and fit.reason.startswith(EXPLAINS_TOO_LITTLE)
            and fit.cost.size
            and fit.cost[fit.best] <= loose_cost_rate * fit.terms
            and fit.margin >= max(4.0 * min_margin, 0.15 * fit.terms)
        ):
            # A whole back whose best placement stands out by far but leaves more than a
            # quarter unexplained: line sequence put a block of it (the cloth below a
            # waistband) a level off. The placement is taken; the code bands below then
            # refuse the block that another placement explains.
            fits[c] = CodeFit(fit.cost, fit.terms, fit.best, fit.margin, "")

    bands = (
        CodeBands(
            data.col,
            data.area,
            data.line_id,
            data.line_order,
            data.line_component,
            lam=lam,
            tolerance=tolerance,
            min_columns=min_columns,
            correlation=correlation,
            band=tile_band,
        )
        if tile_check
        else None
    )

    def off_bands(offsets: dict[int, int]) -> np.ndarray:
        """Lines that the code read in column bands places elsewhere than ``offsets``."""
        assert bands is not None
        return bands.contradicted(
            offsets, code, max_cost_rate=max_cost_rate, min_gain=tile_gain, max_shift=raster.window
        )

    contact_component = data.line_component
    by_code = {c: (fit.best if not fit.reason else -1) for c, fit in fits.items()}
    early = np.zeros(n_lines, dtype=bool)
    if tile_check:
        # Lines that the code decides a component's placement for, but that their own
        # columns place elsewhere, pass no number on: no component inherits through them.
        early = off_bands(by_code)
        if np.any(early):
            contact_component = np.where(early, -1, data.line_component).astype(np.int32)
    votes = contact_votes(data.col, data.row, data.line_id, data.line_order, contact_component)
    offset = dict.fromkeys(fits, -1)
    reason = {c: fits[c].reason for c in fits}
    decided: set[int] = set()
    how_of: dict[int, str] = {}
    order = sorted(fits, key=lambda c: (-size[c], c))

    # Each component's contacts, in component order (the order of the sums below): a
    # fragmented frame has thousands of components, and visiting every component for
    # every tally made this loop quadratic.
    partners: dict[int, list[int]] = defaultdict(list)
    for a, b in votes:
        if a != b and a in fits and b in fits:
            partners[b].append(a)
    for plist in partners.values():
        plist.sort()

    def tally(c: int) -> dict[int, float]:
        """Offsets of ``c`` implied by its contacts with numbered components."""
        out: dict[int, float] = defaultdict(float)
        for other in partners.get(c, ()):
            if offset[other] < 0:
                continue
            for delta, weight in votes[(other, c)].items():
                out[offset[other] + delta] += weight
        return out

    def settle(c: int, off: int, how: str) -> None:
        """Number component ``c`` at ``off`` (decided by ``how``: its code, or linked to
        its neighbours) unless its distance from the station is implausible there."""
        why = ""
        if station is not None:
            mine = valid & (comps == c)
            why = plausible_distance(data, mine, levels, off, raster, station, max_depth)
        offset[c] = offset[c] if why else off
        reason[c] = why
        how_of[c] = "" if why else how
        decided.add(c)

    def rounds() -> None:
        """Components numbered by their code or by their numbered neighbours."""
        for _ in range(6):
            changed = False
            for c in order:
                if c in decided:
                    continue
                fit = fits[c]
                implied = tally(c)
                total = float(sum(implied.values()))
                n_off = code.size - n_levels_of[c] + 1
                if not fit.reason:
                    off = fit.best
                    against = total - implied.get(off, 0.0)
                    if against >= min_conflict and against >= max_conflict * total:
                        worst = max(implied, key=lambda o: implied[o])
                        reason[c] = (
                            f"code says offset {off}, but it touches numbered lines that imply "
                            f"{worst} ({against:.0f} of {total:.0f} contact columns disagree: "
                            f"a depth step of {abs(worst - off)} line spacing(s) or a wrong order)"
                        )
                        decided.add(c)
                        changed = True
                        continue
                    settle(c, off, "code")
                    changed = True
                    continue
                # the code alone does not decide: inherit from touching numbered components
                if total < min_votes:
                    continue
                if total < min_contact_share * width[c]:
                    # a few contact columns along a wide component: a corner of it touches a
                    # numbered surface, possibly across a depth step (a waistband); too little
                    reason[c] = (
                        f"{fit.reason}; touches numbered lines over {total:.0f} columns only, "
                        f"{width[c]} wide"
                    )
                    continue
                off = max(implied, key=lambda o: implied[o])
                if implied[off] < (1.0 - max_conflict) * total or not 0 <= off < n_off:
                    reason[c] = (
                        f"{fit.reason}; touching numbered lines disagree on its number "
                        f"({implied[off]:.0f} of {total:.0f} contact columns agree)"
                    )
                    continue
                # its own code must not speak against the inherited placement
                objection = code_objection(fit, off, n_off, max_cost_rate)
                if objection:
                    reason[c] = f"{fit.reason}; {objection}"
                    decided.add(c)
                    changed = True
                    continue
                settle(c, off, "linked")
                changed = True
            if not changed:
                break

    def settle_groups() -> bool:
        """Groups of components the code does not place, numbered together (whether any
        component was numbered)."""
        members = {c for c in fits if c not in decided and offset[c] < 0}
        placed = False
        for group in component_groups(
            members, votes, max_conflict=max_conflict, min_weight=group_ties
        ):
            off0, _ = group_placement(
                group, votes, partners, offset, first_col, last_col, min_votes=min_votes,
                min_contact_share=min_contact_share, max_conflict=max_conflict,
            )  # fmt: skip
            if off0 is None:  # each piece keeps its reason: counted together, not listed
                continue
            for c, rel in group.relative.items():
                off, n_off = off0 + rel, code.size - n_levels_of[c] + 1
                objection = code_objection(fits[c], off, n_off, max_cost_rate)
                reason[c] = f"{fits[c].reason}; {objection}"
                if not objection:
                    settle(c, off, "group")
                    placed = True
        return placed

    rounds()
    for _ in range(3 if group_ties > 0 else 0):
        if not settle_groups():
            break
        rounds()

    results: list[ComponentNumbering] = []
    judged = {c: offset[c] for c in sorted(fits) if offset[c] >= 0 and c in diffs}
    line_unnumbered = contradicted_lines(
        judged, diffs, comps, levels, valid, code, 2 * raster.window, lam,
        tolerance, min_margin, max_cost_rate, poor_run_factor,
    )  # fmt: skip
    local_refused = int(line_unnumbered.sum())
    for c in sorted(fits):
        fit = fits[c]
        mine = valid & (comps == c)
        kind[mine] = kinds_of[c][levels[mine]]
        off = offset[c]
        best_cost = float(fit.cost[off]) if off >= 0 and fit.cost.size else float("nan")
        results.append(
            ComponentNumbering(
                c,
                n_levels_of[c],
                off,
                best_cost,
                fit.margin,
                kinds_of[c],
                reason[c],
                how_of.get(c, "") if off >= 0 else "",
            )
        )
        if off >= 0:
            line_number[mine] = raster.numbers[off + levels[mine]].astype(np.int32)
    line_number[line_unnumbered] = -1
    if doubtful_lines is not None:
        # a line whose own code contradicts its component's order is as doubtful for the
        # peaks beside it as a block the bands refuse
        doubtful_lines |= line_unnumbered
    if tile_check:
        # Components judge independently: those still at their code placement were judged
        # above already, only the others (linked, moved) are judged again.
        kept = [c for c, off in offset.items() if off >= 0 and by_code.get(c, -1) == off]
        moved = {c: off for c, off in offset.items() if off >= 0 and by_code.get(c, -1) != off}
        off_band = (early & np.isin(comps, kept)) | off_bands(moved)
        off_band &= line_number >= 0
        if doubtful_lines is not None:
            doubtful_lines[off_band] = True
        if np.any(off_band):
            line_number[off_band] = -1
            results.append(
                refusal(
                    int(off_band.sum()),
                    f"{int(off_band.sum())} line(s) lying where the code read in their own "
                    "columns contradicts their component's placement (a block ordered a "
                    "level off, as below a waistband) left unnumbered",
                )
            )
    if local_refused:
        results.append(
            refusal(
                local_refused,
                f"{local_refused} line(s) whose own code contradicts their component's order "
                "(a line-order error inside a component) left unnumbered",
            )
        )
    if pair_check:
        entry = pair_refusal(data, raster, lam, line_number, peaks_per_line, pair_rule)
        if entry is not None:
            results.append(entry)
    return line_number, kind, results


class CodeWindowNumbering(Stage[OrderedLines, NumberedLines]):
    """Absolute line numbers from the light/heavy code, checked against the geometry.

    Neighbouring lines' intensity ratios in the same columns (shading cancels) are matched
    against every placement on the raster's window code, each ratio weighted by how
    decisively it is read (uneven albedo, hair, weighs little); a component is numbered only
    when its best placement is unique by a clear margin *and* agrees with the numbered
    components it touches (no depth step of a whole line spacing, order kept) *and*, with a
    calibration in the context, lies at a plausible distance. Components the code alone
    cannot decide inherit their numbers through short gaps from numbered ones they touch.
    Everything else is left unnumbered with the reason.

    Versions (``docs/numbering-versions.md``): 2 checks, linking; 3-7 column order, code bands,
    peak checks; 8 brackets; 9 pairs confirmed; 10 doubtful line ends; 11 :mod:`.component_groups`;
    12 :mod:`.frame_edges`; 13 :mod:`.end_surroundings`; 14 :mod:`.skipped_lines`; 15
    :mod:`.detached_pieces`; 16, 17 faint codes (:func:`.numbering_refusals.edge_doubts`,
    :func:`.numbering_refusals.least_pair_departure`); 18 runs another placement reads, lone
    peaks last; 19 :mod:`.column_reading`; 20 :mod:`.column_blocks`; 21 :mod:`.one_sided_lines`;
    22 blocks placed a line off behind an albedo edge (``pair_shift``, ``shift_block``); 23
    inherited components touched from one side only (``linked_one_sided``); 25 ``final_order``;
    29 line ends on another surface (:mod:`.outer_ends`, :mod:`.meeting_ends`, one-sided
    lines of six peaks); 30 bracketed runs whose peaks' lines carry other numbers
    (``bracket_line``). Options, off (not adopted when tried): :mod:`.kinked_ends`
    (``kink_bend``, 24); a step in brightness (``end_jump``) and lone runs judged again last
    (``final_run``), with ``meet_tolerance`` as 26; a line's end peaks on the course of its
    refused peaks beyond (:mod:`.turned_courses`, ``course_beyond``, 27); the block check's
    gain as a share of the code's contrast, in blocks of one shift (``block_gain_share``,
    ``block_one_shift``, 28); :mod:`.ambiguous_gaps` (``gap_peaks``, not yet judged).
    """

    name: ClassVar[str] = "numbers.code-window"
    stage: ClassVar[str] = "numbers"
    version: ClassVar[str] = "30"
    input_type = OrderedLines
    output_type = NumberedLines
    requires: ClassVar[tuple[str, ...]] = ("raster",)

    Params = CodeWindowParams

    def run(
        self, data: OrderedLines, params: CodeWindowParams, context: StageContext
    ) -> NumberedLines:
        """Number the lines of ``data`` with the raster from ``context.raster`` (and the
        calibration from ``context.calibration`` for the distance test, when it is a
        station)."""
        raster = context.raster
        if not isinstance(raster, Raster):
            raise InputError(
                f"{self.name} needs context.raster as a rasterserver.raster.Raster, "
                f"not {type(raster).__name__}"
            )
        station = context.calibration if hasattr(context.calibration, "triangulate") else None
        code_refused = np.zeros(data.line_order.shape[0], dtype=bool)
        line_number, kind, results = number_lines(
            data,
            raster,
            area_ratio=params.area_ratio,
            tolerance=params.tolerance,
            min_lines=params.min_lines,
            min_margin=params.min_margin,
            max_cost_rate=params.max_cost_rate,
            poor_run_factor=params.poor_run_factor,
            min_columns=params.min_columns,
            correlation=params.correlation,
            min_votes=params.min_votes,
            max_conflict=params.max_conflict,
            min_conflict=params.min_conflict,
            station=station,
            max_depth=params.max_depth,
            min_contact_share=params.min_contact_share,
            pair_rule=PairRule(
                params.pair_agreement,
                least_pair_departure(params, raster),
                params.pair_shift,
                params.shift_block,
            ),
            tile_check=params.tile_check,
            tile_band=params.tile_band,
            tile_gain=params.tile_gain,
            doubtful_lines=code_refused,
            group_ties=params.group_ties,
        )
        doubtful_lines, block_share = edge_doubts(code_refused, line_number, params, raster)
        lid = data.line_id
        comps = data.line_component
        n_comp = int(comps.max()) + 1 if comps.size and comps.max() >= 0 else 0
        peaks_per_line = np.bincount(lid[lid >= 0], minlength=comps.size)
        sizes = np.bincount(comps[comps >= 0], weights=peaks_per_line[comps >= 0], minlength=n_comp)
        confidence, reason = summarise(results, sizes)
        if data.n_peaks == 0:
            reason = "no peaks"
        elif comps.size == 0:
            reason = "no lines"
        table = np.append(line_number, -1).astype(np.int32)
        number = table[np.where(lid >= 0, lid, -1)]
        spacing = local_spacing(data.col, data.row, number)
        number, notes = refuse_peaks(
            data.col,
            data.row,
            lid,
            number,
            column_check=params.column_check,
            doubtful_lines=doubtful_lines,
            block_gap=params.block_gap,
            block_share=block_share,
            island_peaks=params.island_peaks,
            min_run=params.min_run,
            spacing=spacing,
        )
        linked = np.zeros(n_comp, dtype=bool)
        linked[[r.component for r in results if r.how == "linked" and r.component >= 0]] = True
        # the spacing of the numbers before the refusals: the geometry they measured
        number, last = settle_last(data, number, spacing, params, raster, linked)
        notes += last
        reason = "; ".join([reason, *notes]) if reason else "; ".join(notes)
        return NumberedLines.extend(
            data,
            number=number,
            line_number=line_number,
            kind_observed=kind,
            confidence=confidence,
            reason=reason,
        )
