"""Screening a peak-stage lead: dropped peaks flanked by trusted ones, kept.

The detector (:class:`~rasterserver_plugins.peak_detection.FirstMomentPeaks`) drops a peak
whose first moment cannot be trusted; where only its bounding minima or flanks are unequal
(a neighbouring line crowds it), a peak that trusted peaks flank in both adjacent columns
(the same line on either side) is located about as well as the line around it
(BENCHMARKS.md "Real bodies", 2026-11-30 (31)). This script keeps those peaks around the
installed detector, without a new version of it, and scores stages 1-4 on the clinic
scenes of :mod:`real_bodies` both ways on the same frames: the wrongly numbered peaks, the
back's coverage and the reconstructed peaks' rms, as ``real_bodies.py`` counts them.

A dropped peak is kept where both adjacent columns hold a trusted peak within 2.5 px of
its row, the two within ``--span`` px of each other, their mean within ``--tolerance``
px of it and their areas within a ratio of ``--area-ratio``; and where, two columns out on
either side, a peak (trusted or dropped) continues the line within ``--run-on`` px of the
row its flank's step extrapolates to (0: not required).

Usage::

    python benchmarks/flanked_peaks.py --first-seed 48000 --scenes 1200 --cache /tmp/bodies
    python benchmarks/flanked_peaks.py --first-seed 7000 --scenes 800 \\
        --raster mseq8b-35to65 --cache /tmp/twin --out benchmarks/out/flanked-7000.json
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, NamedTuple  # noqa: E402

import numpy as np  # noqa: E402

REACH = 2.5  # px: a flanking peak's row from the dropped peak's


class Rule(NamedTuple):
    """The lead's thresholds (px; the area ratio unitless)."""

    tolerance: float = 0.4
    span: float = 1.5
    area_ratio: float = 1.5
    run_on: float = 1.0


def _real_bodies() -> Any:
    return importlib.import_module("real_bodies")  # beside this script; once per process


def _nearest(keys: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Index into sorted ``keys`` of the key nearest each of ``key``."""
    j = np.clip(np.searchsorted(keys, key), 1, max(keys.size - 1, 1))
    lo = np.clip(j - 1, 0, keys.size - 1)
    hi = np.clip(j, 0, keys.size - 1)
    return np.where(np.abs(keys[lo] - key) <= np.abs(keys[hi] - key), lo, hi)


def flanked(pixels: np.ndarray, rule: Rule, params: Any = None) -> Any:
    """The installed detector's peaks of ``pixels`` plus the dropped peaks ``rule`` keeps.

    Parameters
    ----------
    pixels : numpy.ndarray
        ``(H, W)`` frame.
    rule : Rule
        The thresholds.
    params : FirstMomentPeaks.Params, optional
        The detector's parameters (its defaults).

    Returns
    -------
    PeakArrays
        Sorted by ``(col, row)``; ``dropped`` less the peaks kept.
    """
    from rasterserver_plugins import peak_detection as pd

    p = params or pd.FirstMomentPeaks.Params()
    kw = {
        name: getattr(p, name)
        for name in ("min_height", "min_slope", "bias", "bias_fraction", "min_width",
                     "max_width", "smooth", "min_trust_height", "clip_level", "narrow",
                     "noise_factor")
    }  # fmt: skip
    kept = pd.detect_peaks(
        pixels, max_base_step=p.max_base_step, max_flank_asymmetry=p.max_flank_asymmetry, **kw
    )
    # the peaks dropped for unequal minima or flanks only (not dim, not clipped)
    loose = pd.detect_peaks(pixels, max_base_step=np.inf, max_flank_asymmetry=2**30, **kw)
    stride = pixels.shape[0] + 10.0
    kkey = kept.col * stride + kept.row
    order = np.argsort(kkey)
    ks, ka = kkey[order], kept.area[order]
    lkey = loose.col * stride + loose.row
    new = ~np.isin(np.round(lkey, 6), np.round(kkey, 6))
    if ks.size < 2 or not np.any(new):
        return kept

    def flank(dc: int) -> tuple[np.ndarray, np.ndarray]:
        key = (loose.col + dc) * stride + loose.row
        i = _nearest(ks, key)
        d = ks[i] - key
        return np.where(np.abs(d) <= REACH, loose.row + d, np.nan), ka[i]

    rl, al = flank(-1)
    rr, ar = flank(+1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.maximum(al, ar) / np.minimum(al, ar)
        keep = new & np.isfinite(rl) & np.isfinite(rr)
        keep &= np.abs((rl + rr) / 2 - loose.row) <= rule.tolerance
        keep &= (np.abs(rl - rr) <= rule.span) & (ratio <= rule.area_ratio)
        if rule.run_on > 0:
            lsort = np.sort(lkey)
            for dc, r in ((-2, 2 * rl - loose.row), (2, 2 * rr - loose.row)):
                key = (loose.col + dc) * stride + np.nan_to_num(r, nan=-1e6)
                keep &= np.abs(lsort[_nearest(lsort, key)] - key) <= rule.run_on
    col = np.concatenate([kept.col, loose.col[keep]])
    row = np.concatenate([kept.row, loose.row[keep]])
    o = np.lexsort((row, col))
    return pd.PeakArrays(
        col=col[o],
        row=row[o],
        area=np.concatenate([kept.area, loose.area[keep]])[o],
        height=np.concatenate([kept.height, loose.height[keep]])[o],
        width=np.concatenate([kept.width, loose.width[keep]])[o],
        dropped=kept.dropped - int(keep.sum()),
    )


def score(frame: Any, peaks: Any) -> dict[str, Any]:
    """Stages 2-4 on ``peaks`` (a Peaks record of ``frame``) scored against the truth."""
    from rasterserver_plugins.line_numbering import CodeWindowNumbering
    from rasterserver_plugins.line_search import HierarchicalLineSearch
    from rasterserver_plugins.line_sequence import HierarchicalLineOrder

    from rasterserver.simulator.body import clinic_station
    from rasterserver.stage import StageContext, run_stage

    bench = _real_bodies()
    station = clinic_station(frame.seed, frame.code)
    ctx = StageContext(calibration=station, raster=station.raster_definition)
    ordered = run_stage(HierarchicalLineOrder, run_stage(HierarchicalLineSearch, peaks))
    result = run_stage(CodeWindowNumbering, ordered, context=ctx)
    truth, _ = bench.peak_truth(frame, result)
    idx, err = bench._match(result.col, result.row, frame.line_rows)
    covered = bench.covered_crossings(frame, result, truth, idx)
    rec = (result.number >= 0) & (truth >= 0) & (result.number == truth) & np.isfinite(err)
    return {
        "wrong_peaks": int(bench.wrong_peaks(result.number, truth).sum()),
        "back_covered": int((covered & frame.lr_on_back).sum()),
        "rec_n": int(rec.sum()),
        "rec_sse": float(np.sum(err[rec] ** 2)),
        "dropped": int(result.dropped or 0),
    }


_CACHE: Path | None = None
_RASTER: str | None = None
_RULE = Rule()


def _init(cache: Path | None, raster: str | None, rule: Rule) -> None:
    global _CACHE, _RASTER, _RULE
    _CACHE, _RASTER, _RULE = cache, raster, rule


def screen_scene(seed: int) -> dict[str, Any]:
    """Scene ``seed`` scored with the installed peaks and with the flanked ones kept."""
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.records import Image
    from rasterserver.stage import run_stage

    frame = _real_bodies().cached_frame(seed, _RASTER, _CACHE)
    shape = (int(frame.image.shape[0]), int(frame.image.shape[1]))
    installed = run_stage(FirstMomentPeaks, Image(frame.image))
    lead = flanked(frame.image, _RULE).to_record(shape)
    return {
        "seed": seed,
        "back_crossings": int(frame.lr_on_back.sum()),
        "installed": score(frame, installed),
        "flanked": score(frame, lead),
    }


def _safe(seed: int) -> dict[str, Any]:
    try:
        return screen_scene(seed)
    except Exception as exc:  # one bad scene must not end a run of hundreds
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}"}


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals per variant: wrong peaks, scenes with any, the back's coverage (%), rms (px)."""
    ok = [r for r in rows if "error" not in r]
    crossings = max(sum(r["back_crossings"] for r in ok), 1)
    out: dict[str, Any] = {
        "scenes": len(ok),
        "error_seeds": sorted(r["seed"] for r in rows if "error" in r),
    }
    for name in ("installed", "flanked"):
        n = max(sum(r[name]["rec_n"] for r in ok), 1)
        out[name] = {
            "wrong_peaks": sum(r[name]["wrong_peaks"] for r in ok),
            "scenes_with_wrong": sum(1 for r in ok if r[name]["wrong_peaks"]),
            "back_coverage": round(100.0 * sum(r[name]["back_covered"] for r in ok) / crossings, 4),
            "rec_rms": round(float(np.sqrt(sum(r[name]["rec_sse"] for r in ok) / n)), 4),
            "dropped": sum(r[name]["dropped"] for r in ok),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    from _scene_pool import add_scene_arguments, report, scene_rows, scene_seeds  # beside

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    add_scene_arguments(ap)
    ap.add_argument("--tolerance", type=float, default=Rule().tolerance)
    ap.add_argument("--span", type=float, default=Rule().span)
    ap.add_argument("--area-ratio", type=float, default=Rule().area_ratio)
    ap.add_argument("--run-on", type=float, default=Rule().run_on)
    args = ap.parse_args(argv)
    seeds = scene_seeds(ap, args, _real_bodies()._raster_names())
    if min(args.tolerance, args.span, args.run_on) < 0 or args.area_ratio < 1:
        ap.error("the thresholds must be >= 0 and --area-ratio >= 1")
    rule = Rule(args.tolerance, args.span, args.area_ratio, args.run_on)
    rows = scene_rows(
        _safe, seeds, workers=args.workers, initializer=_init,
        initargs=(args.cache, args.raster, rule),
    )  # fmt: skip
    summary = summarise(rows)
    summary["rule"] = rule._asdict()
    return report(summary, args)


if __name__ == "__main__":
    sys.exit(main())
