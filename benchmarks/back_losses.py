"""Where the back's line crossings are lost: the stage that left each one without its number.

On the clinic scenes of :mod:`real_bodies` (read from ``--cache`` where rendered before,
rendered and kept there otherwise), stages 1-4 run with their defaults, as
``real_bodies.py`` runs them, and every exact line crossing of the back (the trunk at or
below the vertebra prominens) that does not carry a peak with its correct number is put
in the first of these that applies:

* ``no peak at an edge`` / ``no peak inside``: the detector finds no peak within 1.5 px of
  the crossing even with its trust checks off; *at an edge* where another object or the
  background lies within two columns of the crossing's pixel in its row (a line cut by a
  silhouette or an occluding arm: the image holds no measurable peak there);
* ``dropped``: a peak is there, but the detector drops it as untrustworthy
  (``Peaks.dropped``: its location cannot be trusted);
* ``off its line``: the peak lies off its line's pixels in the rendering (no truth);
* ``in no line``: the line search put the peak in no line;
* ``line unnumbered``: the numbering left its whole line unnumbered (the component's code
  did not decide it, or a line-level check refused it);
* ``peak refused``: its line is numbered, a peak-level check refused this peak;
* ``numbered wrongly``.

Each is counted apart for the *top of the back* (the first eight crossings of the back in
their column: under long hair, at the shoulders' upper edge) and below it. The shares are
of all the back's crossings, so that the categories and the coverage add up to 100 %.
What each numbering step costs on its own is ``numbering_ablation.py``'s measure.

Usage::

    python benchmarks/back_losses.py --first-seed 7000 --scenes 800 \\
        --raster mseq8b-35to65 --cache /tmp/bodies --out benchmarks/out/losses-7000.json
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

# in the order they are judged; "covered" first
CATEGORIES = (
    "covered",
    "no peak at an edge",
    "no peak inside",
    "dropped",
    "off its line",
    "in no line",
    "line unnumbered",
    "peak refused",
    "numbered wrongly",
)
TOP_LINES = 8  # crossings of the back counted from its top in each column
EDGE_REACH = 2  # columns either side in which another object makes a crossing "at an edge"


def _real_bodies() -> Any:
    return importlib.import_module("real_bodies")  # beside this script; once per process


def top_of_back(column: np.ndarray, row: np.ndarray, on_back: np.ndarray) -> np.ndarray:
    """Per crossing, whether it is one of the first :data:`TOP_LINES` crossings of the back
    from the top in its column.

    Parameters
    ----------
    column, row : numpy.ndarray
        The exact crossings' columns and rows.
    on_back : numpy.ndarray
        Bool, the crossings on the back.

    Returns
    -------
    numpy.ndarray
        Bool per crossing (False off the back).
    """
    out = np.zeros(column.size, dtype=bool)
    idx = np.nonzero(on_back)[0]
    if idx.size == 0:
        return out
    order = np.lexsort((row[idx], column[idx]))
    cols = column[idx][order]
    first = np.r_[True, cols[1:] != cols[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(order.size), 0))
    rank = np.arange(order.size) - start
    out[idx[order[rank < TOP_LINES]]] = True
    return out


def at_an_edge(
    object_index: np.ndarray, column: np.ndarray, row: np.ndarray, reach: int = EDGE_REACH
) -> np.ndarray:
    """Per crossing, whether another object (or the background) lies within ``reach``
    columns of its pixel in its row.

    Parameters
    ----------
    object_index : numpy.ndarray
        ``(H, W)`` per-pixel object of the rendering (-1: background).
    column, row : numpy.ndarray
        The crossings.
    reach : int
        Columns either side.

    Returns
    -------
    numpy.ndarray
        Bool per crossing.
    """
    h, w = object_index.shape
    c = column.astype(np.int64)
    r = np.clip(np.rint(row).astype(np.int64), 0, h - 1)
    own = object_index[r, c]
    out = np.zeros(c.size, dtype=bool)
    for dc in range(-reach, reach + 1):
        if dc:
            out |= object_index[r, np.clip(c + dc, 0, w - 1)] != own
    return out


def _crossing_of_peaks(bench: Any, frame: Any, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Per crossing, whether a peak lies within 1.5 px of it in its column."""
    idx, _ = bench._match(col, row, frame.line_rows)
    found = np.zeros(len(frame.line_rows), dtype=bool)
    found[idx[idx >= 0]] = True
    return found


def classify(frame: Any) -> dict[str, Any]:
    """Stages 1-4 on ``frame`` and the category of each of its back's crossings.

    Returns
    -------
    dict
        ``seed``, ``back_crossings`` and ``top``/``below``: per category the count of the
        back's crossings in it (categories with none left out).
    """
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.records import Image
    from rasterserver.stage import run_stage

    bench = _real_bodies()
    result, _ = bench.run_stages(frame)
    lr = frame.line_rows
    truth, _ = bench.peak_truth(frame, result)
    idx, _ = bench._match(result.col, result.row, lr)
    covered = bench.covered_crossings(frame, result, truth, idx)
    loose = run_stage(FirstMomentPeaks, Image(frame.image), params={"trust": False})
    any_peak = _crossing_of_peaks(bench, frame, loose.col, loose.row)
    kept = idx >= 0
    # the first kept peak matched to each crossing (the detector keeps one per line and
    # column; two only where lines crowd)
    peak_of = np.full(len(lr), -1, dtype=np.int64)
    hits = np.nonzero(kept)[0]
    peak_of[idx[hits[::-1]]] = hits[::-1]
    edge = at_an_edge(frame.object_index, lr.column, lr.row)
    line_id = result.line_id.astype(np.int64)
    line_number = np.append(result.line_number, -1)
    category = np.full(len(lr), -1, dtype=np.int64)
    name = {c: k for k, c in enumerate(CATEGORIES)}
    category[covered] = name["covered"]
    p = peak_of
    has = p >= 0
    pp = np.where(has, p, 0)
    lid = np.where(has, line_id[pp], -1)
    judged = [
        (~has & ~any_peak & edge, "no peak at an edge"),
        (~has & ~any_peak, "no peak inside"),
        (~has, "dropped"),
        (truth[pp] < 0, "off its line"),
        (lid < 0, "in no line"),
        (line_number[lid] < 0, "line unnumbered"),
        (result.number[pp] < 0, "peak refused"),
        (np.ones(len(lr), dtype=bool), "numbered wrongly"),
    ]
    for mask, label in judged:
        category[(category < 0) & mask] = name[label]
    back = frame.lr_on_back
    top = top_of_back(lr.column, lr.row, back)
    row: dict[str, Any] = {"seed": frame.seed, "back_crossings": int(back.sum())}
    for part, sel in (("top", back & top), ("below", back & ~top)):
        counts = np.bincount(category[sel], minlength=len(CATEGORIES))
        row[part] = {CATEGORIES[k]: int(n) for k, n in enumerate(counts) if n}
    return row


_CACHE: Path | None = None
_RASTER: str | None = None


def _init(cache: Path | None, raster: str | None) -> None:
    global _CACHE, _RASTER
    _CACHE, _RASTER = cache, raster


def _safe(seed: int) -> dict[str, Any]:
    try:
        return classify(_real_bodies().cached_frame(seed, _RASTER, _CACHE))
    except Exception as exc:  # one bad scene must not end a run of hundreds
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}"}


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Pooled shares (% of all the back's crossings) per category, top and below apart.

    Parameters
    ----------
    rows : list of dict
        :func:`classify`'s rows (rows with an ``error`` are counted apart).

    Returns
    -------
    dict
        ``scenes``, ``error_seeds``, ``back_crossings`` and per category ``top``,
        ``below`` and ``all`` (percent, four decimals).
    """
    ok = [r for r in rows if "error" not in r]
    total = sum(r["back_crossings"] for r in ok)
    shares: dict[str, dict[str, float]] = {}
    for label in CATEGORIES:
        n = {part: sum(r[part].get(label, 0) for r in ok) for part in ("top", "below")}
        shares[label] = {
            **{part: round(100.0 * v / max(total, 1), 4) for part, v in n.items()},
            "all": round(100.0 * (n["top"] + n["below"]) / max(total, 1), 4),
        }
    return {
        "scenes": len(ok),
        "error_seeds": sorted(r["seed"] for r in rows if "error" in r),
        "back_crossings": total,
        "shares": shares,
    }


def _table(summary: dict[str, Any]) -> str:
    lines = [
        f"{summary['scenes']} scenes, {summary['back_crossings']} crossings of the back "
        f"(% of them; top: the first {TOP_LINES} in each column)",
        f"{'category':20s} {'all':>9s} {'top':>9s} {'below':>9s}",
    ]
    for label, s in summary["shares"].items():
        lines.append(f"{label:20s} {s['all']:9.4f} {s['top']:9.4f} {s['below']:9.4f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    from _scene_pool import add_scene_arguments, report, scene_rows, scene_seeds  # beside

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    add_scene_arguments(ap)
    args = ap.parse_args(argv)
    seeds = scene_seeds(ap, args, _real_bodies()._raster_names())
    rows = scene_rows(
        _safe, seeds, workers=args.workers, initializer=_init, initargs=(args.cache, args.raster)
    )
    summary = summarise(rows)
    return report(summary, args, _table(summary))


if __name__ == "__main__":
    sys.exit(main())
