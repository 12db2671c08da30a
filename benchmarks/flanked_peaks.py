"""Screening a peak-stage rule: dropped peaks flanked by trusted ones, kept.

The detector (:class:`~rasterserver_plugins.peak_detection.FirstMomentPeaks`) drops a peak
whose first moment cannot be trusted; where only its bounding minima or flanks are unequal
(a neighbouring line crowds it), a peak that trusted peaks flank in both adjacent columns
(the same line on either side) is located about as well as the line around it
(BENCHMARKS.md "Real bodies", 2026-11-30 (31) and (32)). The rule is
:func:`~rasterserver_plugins.flanked_peaks.flanked`, an option of
:func:`~rasterserver_plugins.peak_detection.detect_peaks` the stage does not use (measured,
not adopted: section (32)). This script scores stages 1-4 on the clinic scenes of
:mod:`real_bodies` with the installed stage's peaks and with the rule added to its
parameters, both on the same frames: the wrongly numbered peaks, the back's coverage and
the reconstructed peaks' rms, as ``real_bodies.py`` counts them.

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
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402


def _real_bodies() -> Any:
    return importlib.import_module("real_bodies")  # beside this script; once per process


def peaks(pixels: np.ndarray, rule: Any) -> Any:
    """The installed peak stage's record of ``pixels`` (its default parameters) with the
    flanked peaks ``rule`` keeps added (a
    :class:`~rasterserver_plugins.flanked_peaks.FlankRule`; None: the stage's own)."""
    from rasterserver_plugins.peak_detection import FirstMomentPeaks, detect_peaks

    p = FirstMomentPeaks.Params().model_dump()
    found = detect_peaks(pixels, **p, flank_rule=rule)
    return found.to_record((int(pixels.shape[0]), int(pixels.shape[1])))


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
_RULE: Any = None  # a FlankRule, set in each worker


def _init(cache: Path | None, raster: str | None, rule: Any) -> None:
    global _CACHE, _RASTER, _RULE
    _CACHE, _RASTER, _RULE = cache, raster, rule


def screen_scene(seed: int) -> dict[str, Any]:
    """Scene ``seed`` scored with the installed peaks and with the flanked ones kept."""
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.records import Image
    from rasterserver.stage import run_stage

    frame = _real_bodies().cached_frame(seed, _RASTER, _CACHE)
    return {
        "seed": seed,
        "back_crossings": int(frame.lr_on_back.sum()),
        "installed": score(frame, run_stage(FirstMomentPeaks, Image(frame.image))),
        "flanked": score(frame, peaks(frame.image, _RULE)),
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
    from rasterserver_plugins.flanked_peaks import FlankRule

    ap.add_argument("--tolerance", type=float, default=FlankRule().tolerance)
    ap.add_argument("--span", type=float, default=FlankRule().span)
    ap.add_argument("--area-ratio", type=float, default=FlankRule().area_ratio)
    ap.add_argument("--run-on", type=float, default=FlankRule().run_on)
    args = ap.parse_args(argv)
    seeds = scene_seeds(ap, args, _real_bodies()._raster_names())
    if min(args.tolerance, args.span, args.run_on) < 0 or args.area_ratio < 1:
        ap.error("the thresholds must be >= 0 and --area-ratio >= 1")
    rule = FlankRule(args.tolerance, args.span, args.area_ratio, args.run_on)
    rows = scene_rows(
        _safe, seeds, workers=args.workers, initializer=_init,
        initargs=(args.cache, args.raster, rule),
    )  # fmt: skip
    summary = summarise(rows)
    summary["rule"] = rule._asdict()
    return report(summary, args)


if __name__ == "__main__":
    sys.exit(main())
