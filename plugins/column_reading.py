"""Numbered peaks whose column, read on through the unnumbered peaks beyond them, places
them a line off.

Where a line runs off the back onto a cloth (a waistband's side edge, its top edge) whose
surface stands off by about one line's depth, the cloth shows the next raster line at the
row the back's line would have had: the line search continues the back's line onto it, or
orders a short piece of the cloth as the back's next line, and the row, the spacing and the
surface all agree with the wrong number. The cloth's own lines beyond it in the column are
left unnumbered (the code refused their order), yet they still show the code: their peaks'
brightness ratios, read down the column from the numbered peak, follow the raster one line
further on than the peak's number (on the clinic tuning scenes, a line's end onto a cloth:
six ratios departing from the code's by 2.8-4.1 in all, in log, at the peak's number and
by 0.5-1.2 one line on).

A numbered peak ``n`` with a numbered column neighbour on one side and unnumbered peaks on
the other is read with up to ``run`` of those (each one spacing on, within 0.7-1.4 of the
gap before it): the log area ratios of consecutive peaks against the raster's at numbers
``n, n + 1, ...`` (going down; ``n, n - 1, ...`` going up) and at the same run shifted by up
to ``shifts`` lines. The peak is refused where a shifted reading explains the run cleanly
(at most ``clean`` per ratio) and better than its own number by ``margin`` per ratio, over
at least ``least`` ratios: the code itself then says the peak belongs to the surface beyond
it, whose lines lie a line off the number it carries.
"""

from __future__ import annotations

import numpy as np

from rasterserver.raster import Raster

__all__ = ["log_width_by_number", "misread_columns"]


def log_width_by_number(raster: Raster) -> np.ndarray:
    """The natural log of every raster line's width, indexed by its number (NaN where the
    raster has no such line).

    Parameters
    ----------
    raster : Raster
        The diapositive's code.

    Returns
    -------
    numpy.ndarray
        float64, ``max(raster.numbers) + 1`` long.
    """
    numbers = np.asarray(raster.numbers, dtype=np.int64)
    table = np.full(int(numbers.max()) + 1 if numbers.size else 0, np.nan)
    table[numbers] = np.log(np.asarray(raster.widths, dtype=np.float64))
    return table


def misread_columns(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    area: np.ndarray,
    raster: Raster,
    *,
    run: int = 6,
    least: int = 3,
    margin: float = 0.3,
    clean: float = 0.2,
    shifts: int = 2,
) -> np.ndarray:
    """Numbered peaks that the code, read on down or up their column through the unnumbered
    peaks beyond them, places on another line.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    area : numpy.ndarray
        Per-peak area (the brightness the code is read from).
    raster : Raster
        The diapositive's code.
    run : int
        Most unnumbered peaks read beyond the numbered one (0: none; the check is off).
    least : int
        Least ratios (consecutive peaks of the run, the numbered one included) read.
    margin : float
        Least advantage, per ratio, of the best shifted reading over the peak's own number
        (natural log of the area ratio).
    clean : float
        Largest departure, per ratio, of the shifted reading.
    shifts : int
        Largest shift, in lines, tried either way.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    number = np.asarray(number)
    if run <= 0 or least < 1 or number.size == 0 or not np.any(number >= 0):
        return np.zeros(number.size, dtype=bool)
    with np.errstate(divide="ignore"):  # a zero area reads as -inf: no shift fits it
        log_area = np.log(np.asarray(area, dtype=np.float64))
    from .check_scans import misread_flags  # compiled; the numba import costs ~0.3 s

    return misread_flags(
        np.asarray(col, dtype=np.int64), np.asarray(row, dtype=np.float64),
        number.astype(np.int64), log_area, log_width_by_number(raster),
        int(run), int(least), float(margin), float(clean), int(shifts),
    )  # fmt: skip
