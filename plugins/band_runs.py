"""The best gain of another placement on a run of a band's levels, compiled.

:meth:`.code_tiles.CodeBands.contradicted` scores every band of every placed component at
every shift with a dozen passes over ``(bands, shifts, levels)`` arrays (gathers of the
cost, masks, a cumulative sum and minimum): ~0.4 ms per call, twice per frame, and on most
frames no run gains enough, so that is all it does. Here one loop gives the best gain of
every (band, shift); the sums are the cumulative sums numpy took, added level by level, so
the gains, and the decision that no run gains enough, are the same bits. Frames where a
run does gain go on with the whole-array passes.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def best_gains(
    c3: np.ndarray, w: np.ndarray, r_off: np.ndarray, diff_at: np.ndarray, shifts: np.ndarray
) -> np.ndarray:
    """Largest gain of a run of levels of every judged band at every other shift.

    Parameters
    ----------
    c3 : numpy.ndarray
        ``(rows, levels, 3)`` cost of every level difference against each expected value.
    w : numpy.ndarray
        ``(rows, levels)`` weight of every level difference (0: unmeasured).
    r_off : numpy.ndarray
        Offset on the code of every row's component.
    diff_at : numpy.ndarray
        ``(n_code + 1,)`` index into the expected values of the code's difference at every
        line (3 past the code).
    shifts : numpy.ndarray
        The placements: 0 (the component's) first, then the others.

    Returns
    -------
    numpy.ndarray
        ``(rows, shifts - 1)``: the maximum over runs of the cost the other placement saves
        (``ends.max(axis=2)`` of the whole-array passes).
    """
    n_rows, n_lev = w.shape
    n_code = diff_at.shape[0] - 1
    n_shifts = shifts.shape[0]
    best = np.empty((n_rows, n_shifts - 1))
    here = np.empty(n_lev)
    for r in range(n_rows):
        for si in range(n_shifts):
            run_best = -np.inf
            csum = 0.0
            low = 0.0  # the running minimum of csum[0 .. level]
            for lev in range(n_lev):
                measured = w[r, lev] > 0
                pos = r_off[r] + shifts[si] + lev
                inside = pos >= 0 and pos < n_code - 1
                e = diff_at[min(max(pos, 0), n_code)]
                cost = c3[r, lev, e] if e < 3 else 0.0
                off_code = not inside and measured
                if si == 0:
                    here[lev] = 0.0 if off_code else cost
                    continue
                alt = 0.0 if off_code else cost
                gain = -1e9 if off_code else here[lev] - alt
                if not measured:
                    gain = 0.0
                # csum[1] is gain[0] itself (np.cumsum), then level by level
                previous = csum
                csum = gain if lev == 0 else csum + gain
                low = min(low, previous)
                end = csum - low
                if end > run_best or lev == 0:
                    run_best = end
            if si > 0:
                best[r, si - 1] = run_best
    return best
