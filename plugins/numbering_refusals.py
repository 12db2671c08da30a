"""Refusals: what line numbering leaves unnumbered, and the reasons it gives.

A component refused as a whole carries its reason in its :class:`ComponentNumbering`;
lines refused inside numbered components are counted in entries of component -1
(:func:`refusal`); peaks refused one by one (:func:`refuse_peaks`, and last, after the
bracketed peaks, the doubtful line ends: :func:`settle_last`) add notes. The stage's
``reason`` joins them all (:func:`summarise`), and the overlay shows it.
"""

from __future__ import annotations

import numpy as np

from rasterserver.raster import Raster
from rasterserver.records_lines import OrderedLines

from .ambiguous_gaps import ambiguous_gap_lines
from .bracketed_peaks import fill_brackets
from .code_evidence import ComponentNumbering, area_ratio_of
from .column_blocks import contradicted_blocks
from .column_reading import misread_columns
from .detached_pieces import detached_pieces
from .end_surroundings import ends_among_unnumbered
from .frame_edges import edge_ends
from .kinked_ends import kinked_ends
from .meeting_ends import meeting_ends
from .numbering_checks import column_order_conflicts, local_spacing, unordered_pairs
from .numbering_params import CodeWindowParams
from .one_sided_lines import one_sided_components, one_sided_lines
from .outer_ends import outer_ends
from .peak_checks import (
    beside_doubtful,
    column_islands,
    isolated_peaks,
    line_ends,
    line_jumps,
    stranded_runs,
)
from .skipped_lines import skipped_lines
from .turned_courses import turned_courses

__all__ = [
    "edge_doubts",
    "faint_code",
    "least_pair_departure",
    "refusal",
    "refuse_ends",
    "refuse_peaks",
    "settle_last",
    "summarise",
]


def refusal(count: int, reason: str) -> ComponentNumbering:
    """The entry counting ``count`` lines refused inside numbered components."""
    return ComponentNumbering(-1, count, -1, float("nan"), 0.0, np.zeros(0, np.int8), reason)


def summarise(results: list[ComponentNumbering], sizes: np.ndarray) -> tuple[float, str]:
    """Confidence (worst numbered component) and the reasons of the refused ones.

    Parameters
    ----------
    results : list of ComponentNumbering
        Every component's numbering, and the entries of lines refused inside numbered
        components (component -1).
    sizes : numpy.ndarray
        Peaks per component.

    Returns
    -------
    confidence : float
        ``1 - exp(-margin / 4)`` of the least clear numbered component; 0 when none.
    reason : str
        The refusals joined by "; " (components too short to read are counted together).
    """
    numbered = [r for r in results if r.offset >= 0 and not np.isnan(r.cost)]
    margins = [r.margin for r in numbered if np.isfinite(r.margin) and r.margin > 0]
    if any(r.offset >= 0 for r in results):
        worst = min(margins) if margins else float("inf")
        confidence = float(1.0 - np.exp(-worst / 4.0)) if np.isfinite(worst) else 1.0
    else:
        confidence = 0.0
    refused = [r for r in results if r.offset < 0]
    if not results:
        return 0.0, "no ordered lines"
    if not refused:
        return confidence, ""
    small = [r for r in refused if "fewer than" in r.reason and ";" not in r.reason]
    small_ids = {id(r) for r in small}  # identity: comparing the dataclasses is quadratic
    other = [r for r in refused if id(r) not in small_ids]
    # entries of component -1 count lines refused inside numbered components: their reason
    # says it all
    parts = [
        r.reason
        if r.component < 0
        else f"component {r.component} ({r.n_levels} lines, {int(sizes[r.component])} peaks): "
        f"{r.reason}"
        for r in other
    ]
    if small:
        peaks = int(sum(sizes[r.component] for r in small))
        parts.append(
            f"{len(small)} component(s) with too few lines to read the code ({peaks} peaks)"
        )
    return confidence, "; ".join(parts)


def _unnumber(number: np.ndarray, refused: np.ndarray, notes: list[str], why: str) -> np.ndarray:
    """``number`` with the ``refused`` peaks unnumbered; appends the note "N peak(s) ``why``
    left unnumbered" to ``notes`` when there are any."""
    if not np.any(refused):
        return number
    notes.append(f"{int(refused.sum())} peak(s) {why} left unnumbered")
    return np.where(refused, -1, number).astype(np.int32)


def refuse_peaks(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    column_check: bool = True,
    doubtful_lines: np.ndarray | None = None,
    block_gap: float = 1.25,
    block_share: float = 0.0,
    island_peaks: int = 0,
    min_run: int = 6,
    spacing: np.ndarray | None = None,
) -> tuple[np.ndarray, list[str]]:
    """The peak-by-peak checks of the numbered peaks, and a note for each that refused any.

    Line jumps (:func:`.peak_checks.line_jumps`), column order
    (:func:`.numbering_checks.column_order_conflicts`), with ``doubtful_lines`` peaks directly
    beside doubtful ones (:func:`.peak_checks.beside_doubtful`), short runs standing
    alone in their column (:func:`.peak_checks.column_islands`), with
    ``column_check`` peaks with no numbered column neighbour
    (:func:`.peak_checks.isolated_peaks`) and short runs the others cut off
    (:func:`.peak_checks.stranded_runs`), in that order.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    column_check : bool
        Refuse numbered peaks with no numbered peak directly above or below them.
    doubtful_lines : numpy.ndarray, optional
        ``(L,)`` bool, doubtful lines: those the code refused inside numbered components
        (a block ordered off, a line against its component's order), or every line left
        unnumbered (version 7). With it, numbered peaks directly
        beside them or beside a peak out of column order are refused
        (:func:`.peak_checks.beside_doubtful`), after the column order check.
    block_gap : float
        The largest gap, in line spacings, counted as directly beside.
    block_share : float
        With a share above 0, a peak beside a doubtful one is refused only among as many
        doubtful peaks as this share of the numbered ones around it
        (:func:`.peak_checks.doubtful_share`).
    island_peaks : int
        Runs of fewer numbered lines standing alone in their column are refused
        (:func:`.peak_checks.column_islands`), after the peaks beside doubtful ones; 0 or
        1 for none.
    min_run : int
        Last, runs of fewer numbered peaks of a line next to its refused peaks are refused
        (:func:`.peak_checks.stranded_runs`); 0 or 1 for none.
    spacing : numpy.ndarray, optional
        Per-peak local line spacing of ``number`` (:func:`.numbering_checks.local_spacing`),
        when already computed.

    Returns
    -------
    number : numpy.ndarray
        ``(N,)`` int32, the refused peaks set to -1.
    notes : list of str
        One sentence per check that refused peaks.
    """
    notes: list[str] = []

    def refuse(refused: np.ndarray, why: str) -> np.ndarray:
        return _unnumber(number, refused, notes, why)

    if spacing is None:
        spacing = local_spacing(col, row, number)
    clash = column_order_conflicts(col, row, number, spacing=spacing)
    jumps = line_jumps(col, row, line_id, number, spacing=spacing)
    number = refuse(
        jumps,
        "where their line jumps by a fraction of a line spacing (a peak of the neighbouring line)",
    )
    number = refuse(
        clash,
        "numbered out of order in their column (a peak taken from a neighbouring line where "
        "lines crowd)",
    )
    if doubtful_lines is not None and spacing is not None:
        lid = line_id.astype(np.int64)
        per_line = np.append(np.asarray(doubtful_lines, dtype=bool), False)
        doubt = per_line[np.where(lid >= 0, lid, -1)]
        edge = beside_doubtful(
            col, row, number, doubt | clash, spacing, max_gap=block_gap, min_share=block_share
        )
        number = refuse(
            edge,
            "directly beside a doubtful line or a peak out of column order, with no gap "
            "between, among doubtful peaks (a line's end may have crossed onto the "
            "neighbouring line)",
        )
    if island_peaks > 1 and spacing is not None:
        islands = column_islands(col, row, number, spacing, min_peaks=island_peaks)
        number = refuse(
            islands,
            f"in runs of fewer than {island_peaks} numbered lines standing alone in their "
            "column (numbered across gaps that hide an unknown count of lines)",
        )
    if column_check:
        number = refuse(
            isolated_peaks(col, number),
            "with no numbered peak above or below them in their column (numbered by their "
            "line's continuity alone)",
        )
    if min_run > 1:
        number = refuse(
            stranded_runs(line_id, number, min_run),
            f"in runs of fewer than {min_run} numbered peaks of a line cut off by its refused "
            "peaks",
        )
    return number, notes


def faint_code(raster: Raster, params: CodeWindowParams) -> bool:
    """Whether the code is faint: its heavy:light area ratio (``area_ratio``, or the
    raster's widths) below ``faint_ratio``, as the 45:55 raster's 1.22.

    A faint code's kinds differ by a log area ratio (0.2) no larger than the ratios' own
    scatter from shading and albedo between neighbouring lines, so small components rarely
    read it and a pair's ratio one kind off it is no evidence.

    Parameters
    ----------
    raster : Raster
        The diapositive's code.
    params : CodeWindowParams
        ``faint_ratio`` and ``area_ratio``.

    Returns
    -------
    bool
        True for a faint code.
    """
    return area_ratio_of(raster, params.area_ratio) < params.faint_ratio


def least_pair_departure(params: CodeWindowParams, raster: Raster) -> float:
    """The least departure, in units of the code's log ratio, of a pair's intensity ratio
    from the code's that contradicts it (:func:`.contradicted_pairs.refuse_contradicted_pairs`).

    0.75, but ``faint_departure`` (1.5) for a faint code (:func:`faint_code`; version 17):
    there a pair one kind off the code departs by one unit, 0.2 in log, within the scatter
    of the ratios, and only a ratio of the other sign (two units) is evidence. On the 45:55
    code's 450 tuning scenes the check at 0.75 refused mostly right lines (the back's
    coverage 96.81 -> 97.40 % and 96.72 -> 97.37 %, the same wrong peaks).

    Parameters
    ----------
    params : CodeWindowParams
        ``faint_ratio``, ``faint_departure`` and ``area_ratio``.
    raster : Raster
        The diapositive's code.

    Returns
    -------
    float
        The least departure that contradicts.
    """
    return params.faint_departure if faint_code(raster, params) else 0.75


def edge_doubts(
    code_refused: np.ndarray,
    line_number: np.ndarray,
    params: CodeWindowParams,
    raster: Raster,
) -> tuple[np.ndarray | None, float]:
    """The doubtful lines of the block-edge check (:func:`refuse_peaks`) and its share.

    With ``doubtful="unnumbered"`` every line left unnumbered is doubtful, whatever
    refused it, and the share of doubtful peaks around a peak (``block_share``) tells a
    refused block from a lone refused line. A faint code (heavy:light area ratio below
    ``faint_ratio``, as the 45:55 raster's 1.22) reads few small components, so there a
    line left unnumbered is mostly a piece too small to read, no sign of trouble: only the
    lines the code refused inside numbered components are doubtful, among the smaller
    share ``faint_share`` (version 16; on the 45:55 code's 150 tuning scenes the back's
    coverage 96.58 -> 96.81 %, wrongly numbered peaks 2 -> 1).

    Parameters
    ----------
    code_refused : numpy.ndarray
        ``(L,)`` bool, the lines the code refused inside numbered components (a block
        ordered off, a line against its component's order).
    line_number : numpy.ndarray
        ``(L,)`` per-line number, -1 when unnumbered.
    params : CodeWindowParams
        ``block_edge_check``, ``doubtful``, ``block_share``, ``faint_ratio``,
        ``faint_share``, ``area_ratio``.
    raster : Raster
        The diapositive's code (its heavy:light width ratio, unless ``area_ratio`` is set).

    Returns
    -------
    doubtful_lines : numpy.ndarray or None
        ``(L,)`` bool, None with the check switched off.
    block_share : float
        The share of doubtful peaks around a peak the check needs.
    """
    if not params.block_edge_check:
        return None, params.block_share
    if faint_code(raster, params):
        return code_refused, params.faint_share
    if params.doubtful == "unnumbered":
        return code_refused | (line_number < 0), params.block_share
    return code_refused, params.block_share


def refuse_ends(
    line_id: np.ndarray,
    number: np.ndarray,
    height: np.ndarray,
    *,
    end_refused: int = 6,
    end_margin: int = 0,
    end_dim: float = 0.0,
    end_jump: float = 0.0,
) -> tuple[np.ndarray, str]:
    """The doubtful ends of the lines' numbered peaks refused (:func:`.peak_checks.line_ends`),
    and the note for the numbering's reason.

    Judged last, after the bracketed peaks are numbered: a peak that is the end of its
    line's numbered peaks only then is judged as one, and the column count of the brackets
    does not number again a peak whose surface is in doubt.

    Parameters
    ----------
    line_id, number : numpy.ndarray
        Line and absolute number (-1: unnumbered) of every peak, sorted by ``(col, row)``.
    height : numpy.ndarray
        Height of every peak.
    end_refused, end_margin : int
        Beyond ``end_refused`` or more unnumbered peaks of a line, its first ``end_margin``
        numbered peaks are refused (0: none).
    end_dim : float
        A line's end peak lower than this share of its next six numbered peaks' mean
        height is refused (0: none).
    end_jump : float
        A line's end peak this many times higher or lower than its next two numbered
        peaks' mean height is refused (0: none).

    Returns
    -------
    number : numpy.ndarray
        ``(N,)`` int32, the refused peaks set to -1.
    note : str
        "N peak(s) ... left unnumbered", or "" when none was.
    """
    number = np.asarray(number, dtype=np.int32)
    ends = line_ends(
        line_id, number, height, min_refused=end_refused, margin=end_margin, dim_ratio=end_dim,
        jump=end_jump,
    )  # fmt: skip
    if not np.any(ends):
        return number, ""
    # the released note unchanged while the option is off: a result's text is part of it
    step = " or a step in brightness off it" if end_jump > 0 else ""
    return np.where(ends, -1, number).astype(np.int32), (
        f"{int(ends.sum())} peak(s) at a line's end beyond its refused peaks or dimmer than "
        f"the line{step} (the end may run onto another surface) left unnumbered"
    )


def settle_last(
    data: OrderedLines,
    number: np.ndarray,
    spacing: np.ndarray | None,
    params: CodeWindowParams,
    raster: Raster,
    linked: np.ndarray | None = None,
) -> tuple[np.ndarray, list[str]]:
    """The last steps after the peak checks: bracketed peaks numbered
    (:func:`.bracketed_peaks.fill_brackets`), the blocks at lines' ends that their own
    columns' code reads a line off refused (:func:`.column_blocks.contradicted_blocks`,
    ``block_least``; first, so that the steps on line ends judge the ends it leaves), then
    the doubtful line ends (:func:`refuse_ends`), the line ends where two numbered lines
    meet (:func:`.meeting_ends.meeting_ends`, ``meet_tolerance``), the ends leaving the frame
    (:func:`.frame_edges.edge_ends`) and the long lines' ends among unnumbered peaks
    (:func:`.end_surroundings.ends_among_unnumbered`), the consecutive numbers a skipped
    line apart (:func:`.skipped_lines.skipped_lines`) and the small pieces no standing
    contact holds to the frame's main block (:func:`.detached_pieces.detached_pieces`), the
    peaks their column's code, read on through the unnumbered peaks beyond them, places a
    line off (:func:`.column_reading.misread_columns`, ``reading_run``), the short lines no
    column confirms from both sides (:func:`.one_sided_lines.one_sided_lines`,
    ``one_sided_peaks``; with ``gap_peaks``, the short lines numbered across gaps no whole
    count of spacings explains, :func:`.ambiguous_gaps.ambiguous_gap_lines`), the line
    ends bent off their course where their neighbours end (:func:`.kinked_ends.kinked_ends`,
    ``kink_bend``), the outermost end peaks of their
    column farther from the next line than the line is further in
    (:func:`.outer_ends.outer_ends`, ``outer_gap``), the column neighbours whose numbers
    do not increase downwards (:func:`.numbering_checks.unordered_pairs`, ``final_order``),
    the runs of a line its refused peaks cut off, judged again (``final_run``),
    and last the peaks those steps left with no numbered column neighbour
    (:func:`.peak_checks.isolated_peaks`, ``final_isolated``) and, with ``linked``, the
    small inherited components touched from one side only
    (:func:`.one_sided_lines.one_sided_components`, ``linked_one_sided``); the notes of
    those that changed anything.

    Parameters
    ----------
    data : OrderedLines
        The peaks (sorted by ``(col, row)``), their lines and the frame's shape.
    number : numpy.ndarray
        Per-peak absolute number after the peak checks, -1 when unnumbered.
    spacing : numpy.ndarray or None
        Per-peak local line spacing of the numbers before the peak checks.
    params : CodeWindowParams
        ``bracket_run``, ``bracket_tolerance``, ``bracket_line``, ``end_refused``,
        ``end_margin``, ``end_dim``, ``end_jump``, ``meet_tolerance``, ``edge_run``,
        ``edge_reach``, ``edge_company``, ``surround_share``, ``surround_reach``,
        ``surround_length``, ``surround_passes``, ``skip_ratio``, ``skip_line_peaks``,
        ``skip_line_share``, ``detached_peaks``, ``detached_gap_low``, ``detached_gap_high``,
        ``detached_brightness``, ``reading_run``, ``reading_least``, ``reading_margin``,
        ``reading_clean``, ``block_least``, ``block_gain``, ``block_gain_share``,
        ``block_one_shift``, ``block_clean``, ``block_ends``, ``one_sided_peaks``,
        ``gap_peaks``, ``gap_departure``, ``kink_bend``, ``kink_ratio``, ``outer_gap``,
        ``final_order``, ``final_run``, ``column_check``, ``final_isolated``,
        ``linked_one_sided``.
    raster : Raster
        The diapositive's code.
    linked : numpy.ndarray, optional
        ``(C,)`` bool per component of ``data``: numbered by inheritance from the
        components it touches.

    Returns
    -------
    number : numpy.ndarray
        ``(N,)`` int32.
    notes : list of str
    """
    notes: list[str] = []
    col, row, line_id, height = data.col, data.row, data.line_id, data.height
    if params.bracket_run > 0:
        number, note = fill_brackets(
            col, row, number, spacing, params.bracket_run, params.bracket_tolerance,
            line_id if params.bracket_line else None,
        )  # fmt: skip
        notes += [note] if note else []
    if params.block_least > 0:
        blocks = contradicted_blocks(
            col, number, line_id, data.area, raster, least=params.block_least,
            gain=params.block_gain, gain_share=params.block_gain_share,
            clean=params.block_clean, ends_least=params.block_ends,
            one_shift=params.block_one_shift,
        )  # fmt: skip
        number = _unnumber(
            number, blocks, notes, f"in blocks of {params.block_least} or more, holding "
            f"{params.block_ends} or more lines' ends, whose column neighbours' brightness "
            "reads the code a line or two off their numbers (lines run on onto a cloth "
            "standing off by a line's depth)",
        )  # fmt: skip
    number, note = refuse_ends(
        line_id, number, height, end_refused=params.end_refused,
        end_margin=params.end_margin, end_dim=params.end_dim, end_jump=params.end_jump,
    )  # fmt: skip
    notes += [note] if note else []
    if params.meet_tolerance > 0:
        meeting = meeting_ends(col, row, line_id, number, tolerance=params.meet_tolerance)
        number = _unnumber(
            number, meeting, notes, "at a line's end lying as well on the course of another "
            "numbered line, of another number, ending beside it (where two surfaces' lines "
            "meet)",
        )  # fmt: skip
    if params.course_beyond > 0:
        turned = turned_courses(
            col, row, line_id, number, beyond=params.course_beyond,
            departure=params.course_departure,
        )  # fmt: skip
        number = _unnumber(
            number, turned, notes, "at a line's end on the course of its refused peaks beyond "
            "rather than its own (the line turns there onto another surface)",
        )  # fmt: skip
    if params.edge_run > 0:
        rows = int(data.image_shape[0])
        edge = edge_ends(
            col, row, line_id, number, spacing, rows,
            max_run=params.edge_run, reach=params.edge_reach, company=params.edge_company,
        )  # fmt: skip
        number = _unnumber(
            number, edge, notes, "at a line's end leaving the frame's top or bottom edge (the "
            "column cannot show a line hidden beyond them)",
        )  # fmt: skip
    if params.surround_share > 0:
        among = ends_among_unnumbered(
            col, row, line_id, number, spacing, reach=params.surround_reach,
            share=params.surround_share, min_length=params.surround_length,
            passes=params.surround_passes,
        )  # fmt: skip
        number = _unnumber(
            number, among, notes, "near a long line's end lying among unnumbered peaks (the "
            "line may run onto a refused surface)",
        )  # fmt: skip
    if params.skip_ratio > 0:
        skipped = skipped_lines(
            col, row, line_id, number, ratio=params.skip_ratio,
            min_peaks=params.skip_line_peaks, line_share=params.skip_line_share,
        )  # fmt: skip
        number = _unnumber(
            number, skipped, notes, "numbered consecutively but lying two line spacings apart "
            "in their column, or on their lines (a line between them went unfound and was not "
            "counted)",
        )  # fmt: skip
    if params.detached_peaks > 0:
        detached = detached_pieces(
            col, row, line_id, number, data.area, raster, max_peaks=params.detached_peaks,
            gap_low=params.detached_gap_low, gap_high=params.detached_gap_high,
            brightness=params.detached_brightness,
        )  # fmt: skip
        number = _unnumber(
            number, detached, notes, f"in pieces of at most {params.detached_peaks} numbered "
            "peaks that no contact at one line spacing with the code's brightness joins to the "
            "frame's main numbered block (their number rested on contacts refused since, or "
            "across a depth or brightness step, as below a waistband)",
        )  # fmt: skip
    if params.reading_run > 0:
        misread = misread_columns(
            col, row, number, data.area, raster, run=params.reading_run,
            least=params.reading_least, margin=params.reading_margin,
            clean=params.reading_clean,
        )  # fmt: skip
        number = _unnumber(
            number, misread, notes, "whose column, read on through the unnumbered peaks "
            "beyond them, shows the code a line off their number (a line's end run onto "
            "another surface)",
        )  # fmt: skip
    if params.one_sided_peaks > 0:
        one_sided = one_sided_lines(col, line_id, number, max_peaks=params.one_sided_peaks)
        number = _unnumber(
            number, one_sided, notes, f"on lines of at most {params.one_sided_peaks} numbered "
            "peaks with no numbered peak both above and below any of them (numbered by one "
            "neighbour's contact, across what may be a depth step)",
        )  # fmt: skip
    if params.gap_peaks > 0:
        ambiguous = ambiguous_gap_lines(
            col, row, line_id, number, max_peaks=params.gap_peaks, departure=params.gap_departure
        )
        number = _unnumber(
            number, ambiguous, notes, f"on lines of at most {params.gap_peaks} numbered peaks "
            "lying between two counts of line spacings from their column neighbours",
        )  # fmt: skip
    if params.kink_bend > 0:
        kinked = kinked_ends(
            col, row, line_id, number, least_bend=params.kink_bend, bend_ratio=params.kink_ratio
        )
        number = _unnumber(
            number, kinked, notes, "at a line's end that bends off the line's course where the "
            "lines numbered either side end too (a link onto another surface's line)",
        )  # fmt: skip
    if params.outer_gap > 0:
        outer = outer_ends(col, row, line_id, number, gap_ratio=params.outer_gap)
        number = _unnumber(
            number, outer, notes, "at a line's end, the outermost of their column, lying "
            "farther from the next line than the line does further in (the line runs onto "
            "another surface at a depth step)",
        )  # fmt: skip
    if params.final_order:
        number = _unnumber(
            number, unordered_pairs(col, row, number), notes, "whose numbers do not "
            "increase down their column (a surface shows the raster's lines in their order)",
        )  # fmt: skip
    if params.final_run > 1:
        # the same for the runs of a line that the steps above cut off by refusing the
        # peaks around them: nothing but the line's continuity carried their numbers
        number = _unnumber(
            number, stranded_runs(line_id, number, params.final_run), notes, f"in runs of "
            f"fewer than {params.final_run} numbered peaks of a line cut off by the peaks the "
            "last steps refused",
        )  # fmt: skip
    if params.column_check and params.final_isolated:
        # the steps above refuse peaks a column's order rested on: what is left numbered
        # by its line's continuity alone is judged as the peak checks judged it
        number = _unnumber(
            number, isolated_peaks(col, number), notes, "with no numbered peak above or "
            "below them once the last steps refused their column neighbours",
        )  # fmt: skip
    if linked is not None and params.linked_one_sided > 0:
        one_sided = one_sided_components(
            col, line_id, number, data.line_component, linked,
            max_peaks=params.linked_one_sided,
        )  # fmt: skip
        number = _unnumber(
            number, one_sided, notes, f"in components of at most {params.linked_one_sided} "
            "numbered peaks that inherited their numbers from lines touching them on one side "
            "only (the count rests on one boundary, as a cloth's below a waistband)",
        )  # fmt: skip
    return number, notes
