"""The flanked-peaks rule of the peak stage, scored with and without it on the same frames.

The detector (:class:`~rasterserver_plugins.peak_detection.FirstMomentPeaks`, version 5)
keeps a peak dropped only because a neighbouring line crowds it (unequal bounding minima or
flanks) where trusted peaks of the same line flank it
(:mod:`~rasterserver_plugins.flanked_peaks`; BENCHMARKS.md "Real bodies", 2026-11-30 (31)).
This script scores stages 1-4 on the clinic scenes of :mod:`real_bodies` without the rule
(``flank_tolerance`` 0: version 4's peaks) and with the thresholds given (by default the
stage's), both on the same frames: the wrongly numbered peaks, the back's coverage and the
reconstructed peaks' rms, as ``real_bodies.py`` counts them.

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


def _stage_rule() -> Any:
    from rasterserver_plugins.flanked_peaks import FlankRule
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    p = FirstMomentPeaks.Params()
    return FlankRule(p.flank_tolerance, p.flank_span, p.flank_area_ratio, p.flank_run_on)


def peaks(pixels: np.ndarray, rule: Any) -> Any:
    """The peak stage's record of ``pixels`` with the flanked-peaks thresholds ``rule``
    (a :class:`~rasterserver_plugins.flanked_peaks.FlankRule`; tolerance 0: none kept)."""
    from rasterserver_plugins.peak_detection import FirstMomentPeaks

    from rasterserver.records import Image
    from rasterserver.stage import run_stage

    params = {
        "flank_tolerance": rule.tolerance,
        "flank_span": rule.span,
        "flank_area_ratio": rule.area_ratio,
        "flank_run_on": rule.run_on,
    }
    return run_stage(FirstMomentPeaks, Image(pixels), params=params)


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
_RULE: Any = None


def _init(cache: Path | None, raster: str | None, rule: Any) -> None:
    global _CACHE, _RASTER, _RULE
    _CACHE, _RASTER, _RULE = cache, raster, rule


def screen_scene(seed: int) -> dict[str, Any]:
    """Scene ``seed`` scored without the flanked peaks and with them kept by ``_RULE``."""
    frame = _real_bodies().cached_frame(seed, _RASTER, _CACHE)
    rule = _RULE or _stage_rule()
    return {
        "seed": seed,
        "back_crossings": int(frame.lr_on_back.sum()),
        "unflanked": score(frame, peaks(frame.image, rule._replace(tolerance=0.0))),
        "flanked": score(frame, peaks(frame.image, rule)),
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
    for name in ("unflanked", "flanked"):
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
    stage = _stage_rule()
    ap.add_argument("--tolerance", type=float, default=stage.tolerance)
    ap.add_argument("--span", type=float, default=stage.span)
    ap.add_argument("--area-ratio", type=float, default=stage.area_ratio)
    ap.add_argument("--run-on", type=float, default=stage.run_on)
    args = ap.parse_args(argv)
    seeds = scene_seeds(ap, args, _real_bodies()._raster_names())
    if min(args.tolerance, args.span, args.run_on) < 0 or args.area_ratio < 1:
        ap.error("the thresholds must be >= 0 and --area-ratio >= 1")
    rule = type(stage)(args.tolerance, args.span, args.area_ratio, args.run_on)
    rows = scene_rows(
        _safe, seeds, workers=args.workers, initializer=_init,
        initargs=(args.cache, args.raster, rule),
    )  # fmt: skip
    summary = summarise(rows)
    summary["rule"] = rule._asdict()
    return report(summary, args)


if __name__ == "__main__":
    sys.exit(main())
