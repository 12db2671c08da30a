"""Blocks of numbered peaks whose own columns read the code a line off their numbers.

Where a waistband's cloth stands off the skin by about one line's depth, the back's lines run
on smoothly onto it: the cloth shows raster line ``n + 1`` at the row where the skin would
have shown line ``n``, and the line search carries the skin's number onto the cloth. Row,
spacing and surface then all agree with the wrong number, and when the cloth's lines are
numbered with them no unnumbered peak is left beyond to read
(:mod:`.column_reading`). The code still tells: within the cloth, the brightness ratios of
consecutive numbered peaks of a column (the shading and the cloth's albedo cancel in them)
follow the raster a line or two off the numbers they carry, at every column of the piece
and on every line of it.

Each numbered peak is read with its numbered column neighbours (numbers one apart): the
log area ratios against the raster's at the peaks' numbers and at the same numbers shifted
by up to ``shifts`` lines either way. A peak supports a shift where the shifted reading
departs from the code by at most ``clean`` per ratio and explains its ratios better than
its own numbers by at least ``gain`` per ratio. Supporting peaks join into blocks along
their lines and down their columns; a block of at least ``least`` peaks that holds the
ends (the first or last numbered peak) of at least ``ends_least`` lines is refused: a cloth
is met where the lines leave the skin, while a dim patch of the back (a shoulder turning
away under the raster's top lines) reads off across the middle of its lines and holds no
more than a short line's end. Alone, one peak's reading is noise (a fold, a shadow's edge); a block
across several lines and columns, all read off, is the code's own verdict.

A faint code (45:55: its kinds differ by log 1.22 = 0.20) lets a shifted reading gain
little: the gain can be taken as a share of the code's contrast (``gain_share``), and then,
with so low a threshold, a block is joined from peaks supporting one shift only
(``one_shift``), or noise on the back forms blocks of mixed shifts.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rasterserver.raster import Raster

from .column_reading import log_width_by_number

__all__ = ["code_contrast", "contradicted_blocks"]


def code_contrast(raster: Raster) -> float:
    """The code's contrast: the natural log of its widest line's width over its narrowest's
    (from :func:`.column_reading.log_width_by_number`, the log widths the readings use);
    0 for a raster of one width (no code to read)."""
    table = log_width_by_number(raster)
    widths = table[np.isfinite(table)]
    return float(widths.max() - widths.min()) if widths.size else 0.0


def contradicted_blocks(
    col: np.ndarray,
    number: np.ndarray,
    line_id: np.ndarray,
    area: np.ndarray,
    raster: Raster,
    *,
    least: int = 15,
    gain: float = 0.3,
    gain_share: float = 0.0,
    clean: float = 0.15,
    shifts: int = 2,
    ends_least: int = 2,
    one_shift: bool = False,
) -> np.ndarray:
    """Numbered peaks in blocks, holding lines' ends, that their columns' code reads a line
    or two off (the column pairs read in one compiled loop,
    :func:`.check_scans.block_support_flags`).

    Parameters
    ----------
    col : numpy.ndarray
        Per-peak column; the peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    line_id : numpy.ndarray
        Per-peak line, -1 for none.
    area : numpy.ndarray
        Per-peak area (the brightness the code is read from).
    raster : Raster
        The diapositive's code.
    least : int
        Fewest peaks of a refused block (0: the check is off).
    gain : float
        Least advantage, per ratio (natural log), of a shifted reading over the peak's own
        numbers for the peak to support it.
    clean : float
        Largest departure, per ratio, of the shifted reading from the code.
    shifts : int
        Largest shift, in lines, tried either way.
    ends_least : int
        Fewest lines whose end (first or last numbered peak) a refused block holds.
    one_shift : bool
        Join into a block only peaks that support one and the same shift: a cloth's lines
        are all a line or two off together, while a fold's or a shadow's noise supports
        one shift here and another there (with a low ``gain`` such mixed blocks cover
        the back).

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    number = np.asarray(number, dtype=np.int64)
    n = number.size
    flags = np.zeros(n, dtype=bool)
    if least <= 0 or n < 2 or not np.any(number >= 0):
        return flags
    col = np.asarray(col)
    line_id = np.asarray(line_id)
    with np.errstate(divide="ignore"):  # a zero area reads as -inf: no reading explains it
        log_area = np.log(np.asarray(area, dtype=np.float64))
    table = log_width_by_number(raster)
    if gain_share > 0:
        gain = gain_share * code_contrast(raster)
    # column pairs (i, i + 1): numbered neighbours of one column, numbers one apart
    pair = (
        (col[:-1] == col[1:])
        & (number[:-1] >= 0)
        & (number[1:] >= 0)
        & (np.abs(number[1:] - number[:-1]) == 1)
    )
    if not np.any(pair):
        return flags
    with np.errstate(invalid="ignore"):  # -inf - -inf (zero areas): read as no reading
        step = log_area[1:] - log_area[:-1]
    from .check_scans import block_support_flags  # compiled; the numba import costs ~0.3 s

    by_shift = block_support_flags(
        number, step, pair, table, float(gain), float(clean), int(shifts), bool(one_shift)
    )
    # with one_shift each shift's peaks join alone; without, one column: any shift's
    for support in by_shift.T:
        if np.count_nonzero(support) >= least:
            flags |= _held_blocks(support, number >= 0, line_id, pair, least, ends_least)
    return flags


def _held_blocks(
    support: np.ndarray,
    numbered: np.ndarray,
    line_id: np.ndarray,
    pair: np.ndarray,
    least: int,
    ends_least: int,
) -> np.ndarray:
    """The supporting peaks in blocks of ``least`` or more, joined along their lines (a
    numbered peak that does not support parts them) and down their columns (``pair``),
    holding the ends (first or last numbered peaks) of ``ends_least`` or more lines."""
    n = support.size
    # along lines: consecutive numbered peaks of one line by column (the peaks come sorted
    # by column, and a stable sort by line keeps that order), of the lines that hold a
    # supporting peak (a lookup by line: a frame has few such lines)
    holds = np.zeros(int(line_id.max()) + 2, dtype=bool)
    holds[line_id[support]] = True
    holds[-1] = False  # line -1: none
    members = np.flatnonzero(numbered & holds[line_id])
    by_line = members[np.argsort(line_id[members], kind="stable")]
    same = line_id[by_line[1:]] == line_id[by_line[:-1]]
    below = np.flatnonzero(pair)
    a = np.concatenate([by_line[:-1][same], below])
    b = np.concatenate([by_line[1:][same], below + 1])
    keep = support[a] & support[b]
    # the blocks: components of the supporting peaks, indexed among themselves
    nodes = np.flatnonzero(support)
    local = np.full(n, -1, dtype=np.int64)
    local[nodes] = np.arange(nodes.size)
    graph = coo_matrix(
        (np.ones(int(keep.sum())), (local[a[keep]], local[b[keep]])), shape=(nodes.size,) * 2
    )
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    # a line's first and last numbered peaks
    ends = np.zeros(n, dtype=bool)
    if by_line.size:
        ends[by_line[np.r_[True, ~same]]] = True
        ends[by_line[np.r_[~same, True]]] = True
    # the lines whose ends each block holds, counted once per line and block
    held = ends[nodes]
    pairs = np.unique(np.stack([label[held], line_id[nodes[held]]]), axis=1)
    line_ends = np.bincount(pairs[0], minlength=size.size)
    flags = np.zeros(n, dtype=bool)
    flags[nodes] = ((size >= least) & (line_ends >= ends_least))[label]
    return flags
