"""Lines refused for their intensity ratios with column neighbours, and when they are spared.

The pair check of line numbering (versions 4, 9 and 22): numbered column neighbours whose
intensity ratio contradicts the code at their numbers lose their shorter line, unless the
code confirms it on its other side through pairs that tell its placement from the one the
contradiction suggests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rasterserver.raster import Raster
from rasterserver.records_lines import OrderedLines

from .code_evidence import ComponentNumbering
from .numbering_checks import pair_judgements
from .numbering_refusals import refusal

__all__ = ["PairRule", "pair_refusal", "refuse_contradicted_pairs"]


@dataclass(frozen=True)
class PairRule:
    """How contradicting pairs are judged and spared (the keywords of
    :func:`refuse_contradicted_pairs`: ``max_agreement``, ``min_departure``,
    ``shift_support``, ``shift_block``)."""

    agreement: float = 0.4
    departure: float = 0.75
    shift: bool = False
    block: int = 0


def pair_refusal(
    data: OrderedLines,
    raster: Raster,
    lam: float,
    line_number: np.ndarray,
    peaks_per_line: np.ndarray,
    rule: PairRule,
) -> ComponentNumbering | None:
    """:func:`refuse_contradicted_pairs` by ``rule``; the entry counting the lines it
    refused, None when it refused none."""
    refused = refuse_contradicted_pairs(
        data,
        raster,
        lam,
        line_number,
        peaks_per_line,
        max_agreement=rule.agreement,
        min_departure=rule.departure,
        shift_support=rule.shift,
        shift_block=rule.block,
    )
    if not refused:
        return None
    return refusal(
        refused,
        f"{refused} line(s) whose intensity ratio with a column neighbour contradicts the "
        "code at their numbers (a piece placed a level off, as across a waistband) left "
        "unnumbered",
    )


def refuse_contradicted_pairs(
    data: OrderedLines,
    raster: Raster,
    lam: float,
    line_number: np.ndarray,
    peaks_per_line: np.ndarray,
    *,
    max_agreement: float = 0.0,
    min_departure: float = 0.75,
    shift_support: bool = False,
    shift_block: int = 0,
) -> int:
    """Unnumber (in place) the shorter line of every pair of column neighbours whose
    intensity ratio contradicts the code at their numbers.

    Parameters
    ----------
    data : OrderedLines
        The ordered lines.
    raster : Raster
        The diapositive's code.
    lam : float
        Log area ratio of a heavy to a light line.
    line_number : numpy.ndarray
        ``(L,)`` absolute numbers, -1 when unnumbered; changed in place.
    peaks_per_line : numpy.ndarray
        ``(L,)`` peak count of every line.
    max_agreement : float
        When positive, the shorter line is spared where its pairs with its other column
        neighbours that agree with the code (judged over five columns or more, departing
        from it by less than this in units of ``lam`` and by less than three standard
        errors; the neighbour agreeing with another line as well) span more columns than
        its contradicting pairs: the contradiction is then the longer line's doing or the
        intensities' (an albedo edge, a shadow), not a piece placed off. 0 refuses the
        shorter line always.
    min_departure : float
        Least departure of a pair's ratio from the code's, in units of ``lam``, that
        contradicts (:func:`.numbering_checks.pair_judgements`).
    shift_support : bool
        Where a contradicting pair would agree with the code were both its lines numbered
        one less (or one more), the pair may be a block placed off whose edge with the
        rest lies where the intensities cannot tell (an albedo edge: a cloth's lines
        under the skin's); its shorter line's agreeing pairs then spare it only where they
        would no longer agree under that shift (a run of lines of one kind agrees under
        either).
    shift_block : int
        With ``shift_support``, the lines of at most this many peaks tied to a refused line
        by pairs that agree under its shift too (its block) are refused with it (0: none).

    Returns
    -------
    int
        The number of lines refused.
    """
    upper, lower, columns, departure, z, bad, moved = pair_judgements(
        data.col,
        data.area,
        data.line_id,
        line_number,
        raster,
        lam,
        min_departure=min_departure,
        shifted=True,
    )
    if not np.any(bad):
        return 0
    # The image cannot tell which of the two is off; the shorter is the piece (a whole line
    # misread as the other kind loses one of its neighbours or itself, never a number).
    bu, bl = upper[bad], lower[bad]
    short_is_upper = peaks_per_line[bu] <= peaks_per_line[bl]
    shorter = np.where(short_is_upper, bu, bl)
    if max_agreement > 0:
        # Spared: a shorter line that the code confirms on its other side over more
        # columns than it contradicts it, through neighbours the code confirms on their
        # own other side too (a lone confirming pair may be a block placed off agreeing
        # with itself; its lines beyond then show the contradiction).
        n = line_number.size
        # judged like a contradiction (five columns or more), close to the code and not
        # significantly off it (a ratio half a kind off over many columns is no agreement)
        ok = (columns >= 5) & (departure < max_agreement) & (z < 3.0)
        agreeing = np.bincount(upper[ok], minlength=n) + np.bincount(lower[ok], minlength=n)
        # per line, the shifts (one less, one more) under which a contradicting pair of it
        # would agree: its block may be placed off by that much
        resolved = np.zeros((n, 2), dtype=bool)
        if shift_support:
            fits = np.nan_to_num(moved[bad], nan=np.inf) < max_agreement
            for side in (bu, bl):
                np.logical_or.at(resolved, side, fits)
        # an agreeing pair that agrees under the shift as well tells nothing of it
        blind = np.nan_to_num(moved[ok], nan=np.inf) < max_agreement
        support = np.zeros(n)
        for x, y in ((upper[ok], lower[ok]), (lower[ok], upper[ok])):
            confirmed = (agreeing[y] >= 2) & ~np.any(resolved[x] & blind, axis=1)
            np.add.at(support, x[confirmed], columns[ok][confirmed])
        against = np.bincount(bu, columns[bad], n) + np.bincount(bl, columns[bad], n)
        shorter = shorter[support[shorter] <= against[shorter]]
        if shift_block > 0 and shift_support:
            shorter = _shifted_block(
                np.unique(shorter),
                resolved,
                upper[ok],
                lower[ok],
                blind,
                peaks_per_line,
                shift_block,
            )
    shorter = np.unique(shorter)
    line_number[shorter] = -1
    return int(shorter.size)


def _shifted_block(
    refused: np.ndarray,
    resolved: np.ndarray,
    upper: np.ndarray,
    lower: np.ndarray,
    blind: np.ndarray,
    peaks_per_line: np.ndarray,
    most: int,
) -> np.ndarray:
    """``refused`` with the lines of at most ``most`` peaks tied to them by agreeing pairs
    that agree under the shift their contradiction suggests (their block, placed off with
    them)."""
    n = resolved.shape[0]
    block = np.zeros(n, dtype=bool)
    block[refused] = True
    shift = np.zeros((n, 2), dtype=bool)
    shift[refused] = resolved[refused]
    small = peaks_per_line <= most
    while True:
        grown = False
        for x, y in ((upper, lower), (lower, upper)):
            tie = block[x] & ~block[y] & small[y] & np.any(shift[x] & blind, axis=1)
            if np.any(tie):
                block[y[tie]] = True
                np.logical_or.at(shift, y[tie], shift[x[tie]] & blind[tie])
                grown = True
        if not grown:
            return np.flatnonzero(block)
